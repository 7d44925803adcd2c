"""``core.image_quality``: whether a frame's left image can show a defect at all."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from core.image_quality import ImageStats, image_problem, image_stats
from core.recipe.schema import ImageCheck

PLATE = Path(__file__).resolve().parents[1] / "sim_fixtures"
DEFAULTS = ImageCheck()
LIMITS = (DEFAULTS.min_mean_grey, DEFAULTS.max_saturated, DEFAULTS.min_texture)


def _noisy(image: np.ndarray, sigma: float = 2.0, seed: int = 0) -> np.ndarray:
    """As a sensor delivers it: every pixel with its noise."""
    noise = np.random.default_rng(seed).normal(0.0, sigma, image.shape)
    return np.clip(image.astype(np.float32) + noise, 0, 255).astype(np.uint8)


def _plate(folder: str = "plates_low_texture") -> np.ndarray:
    return cv2.imread(str(sorted((PLATE / folder / "left").iterdir())[0]))


class TestImageStats:
    def test_shapes_and_types_are_checked(self):
        with pytest.raises(ValueError, match="uint8"):
            image_stats(np.zeros((40, 60, 3), np.float32))
        with pytest.raises(ValueError, match="shape"):
            image_stats(np.zeros((2, 40, 60, 3), np.uint8))

    def test_grey_and_colour_give_the_same_figures(self):
        colour = _plate()
        assert image_stats(colour) == image_stats(cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY))

    def test_a_plate_has_texture_and_noise_alone_has_little(self):
        plate = image_stats(_plate())
        flat = image_stats(_noisy(np.full((376, 672, 3), 128, np.uint8)))
        assert plate.texture > 1.5 and flat.texture < 0.6
        assert flat.mean_grey == pytest.approx(128, abs=1) and flat.saturated == 0.0

    def test_saturated_share_and_mean(self):
        image = np.zeros((100, 100), np.uint8)
        image[:, :30] = 255
        stats = image_stats(image)
        assert stats.saturated == pytest.approx(0.3) and stats.mean_grey == pytest.approx(76.5)

    def test_a_tiny_image_is_read_as_it_is(self):
        assert image_stats(np.full((8, 8), 50, np.uint8)).mean_grey == 50.0


class TestImageProblem:
    @pytest.mark.parametrize("folder", ["steel_plate", "plates_textured", "plates_low_texture"])
    def test_the_committed_plates_pass(self, folder):
        for path in sorted((PLATE / folder / "left").iterdir()):
            assert image_problem(image_stats(cv2.imread(str(path))), *LIMITS) is None, path.name

    @pytest.mark.parametrize("make, says", [
        (lambda p: _noisy(np.zeros_like(p)), "too dark"),  # the lights off, a covered lens
        (lambda p: _noisy((p * 0.1).astype(np.uint8)), "too dark"),  # a tenth of the light
        (lambda p: _noisy(np.clip(p.astype(np.float32) * 8, 0, 255).astype(np.uint8)), "washed out"),  # blinded
        (lambda p: _noisy(np.full_like(p, 128)), "no texture"),  # a grey card in front of the lens
        (lambda p: _noisy(cv2.GaussianBlur(p, (0, 0), 12)), "no texture"),  # far out of focus
    ])
    def test_an_image_that_cannot_show_a_defect_is_named(self, make, says):
        problem = image_problem(image_stats(make(_plate())), *LIMITS)
        assert problem is not None and says in problem and "camera.image_check" in problem

    def test_each_limit_can_be_turned_off(self):
        dark = ImageStats(mean_grey=5.0, saturated=1.0, texture=0.0)
        assert image_problem(dark, 0.0, 1.0, 0.0) is None
        assert "too dark" in image_problem(dark, 20.0, 1.0, 0.0)
        assert "washed out" in image_problem(dark, 0.0, 0.9, 0.0)
        assert "no texture" in image_problem(dark, 0.0, 1.0, 0.7)
