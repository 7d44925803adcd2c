"""core.plate_view: where a frame without defects shows the plate, on rendered plates of known distance."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from synthetic_pairs import calib_for, render

from core.plate_view import GRID, MIN_SIDE_PX, PATCH_COLUMNS, PATCH_ROWS, patch_pixels, plate_elsewhere

CALIB = calib_for(320, 192)
FB = CALIB.focal_px * CALIB.baseline_mm


def searched(near_mm: float, far_mm: float) -> tuple[float, float]:
    return FB / far_mm, FB / near_mm


@pytest.fixture(scope="module")
def plate_at_400():
    left, right, _ = render(CALIB, 400.0, tilt_deg=5.0)
    return left, right


class TestPatchPixels:
    def test_a_grid_of_patches_right_of_the_searched_columns_centre_rows_first(self):
        patches = patch_pixels((192, 320), hi=140.0)
        assert len(patches) == GRID[0] * GRID[1]
        for u, v in patches:
            assert u.shape == v.shape == ((PATCH_ROWS // 2) * (PATCH_COLUMNS // 2),)
            assert u.min() >= 140 and u.max() < 320 and v.min() >= 0 and v.max() < 192
        tops = [int(v.min()) for _, v in patches]
        assert len(set(tops)) == GRID[0] and min(tops) == 0 and max(tops) == 192 - PATCH_ROWS
        middle = sorted(set(tops))[GRID[0] // 2]
        assert tops[:GRID[1]] == [middle] * GRID[1]  # the middle row first

    def test_columns_start_at_half_the_width_at_most(self):
        (u, _), *_ = patch_pixels((192, 320), hi=1000.0)
        assert u.min() == 160

    @pytest.mark.parametrize("shape, hi", [((MIN_SIDE_PX - 1, 320), 0.0), ((192, 2 * MIN_SIDE_PX - 2), 100.0)])
    def test_a_frame_too_small_to_tell_has_none(self, shape, hi):
        assert patch_pixels(shape, hi) == []


class TestPlateElsewhere:
    def test_a_plate_within_the_searched_range_is_where_it_belongs(self, plate_at_400):
        assert plate_elsewhere(*plate_at_400, CALIB, searched(300, 600)) is None

    @pytest.mark.parametrize("near, far", [(200, 300), (500, 800)])
    def test_a_plate_nearer_or_farther_than_the_range_is_said_to_be_at_its_distance(self, plate_at_400, near, far):
        found = plate_elsewhere(*plate_at_400, CALIB, searched(near, far))
        assert found is not None and not found.swapped
        assert found.distance_mm == pytest.approx(400, abs=12)  # whole pixels of disparity: 3.8 mm each at 400 mm
        text = found.describe(searched(near, far))
        assert "outside the" in text and "the plate lies outside the working distance" in text

    def test_a_plate_tilted_towards_the_camera_is_found_as_well(self):
        # 355-458 mm from its top to its bottom row: the disparity moves by 0.14 px a row
        left, right, _ = render(CALIB, 400.0, tilt_deg=25.0)
        assert plate_elsewhere(left, right, CALIB, searched(300, 600)) is None
        found = plate_elsewhere(left, right, CALIB, searched(200, 300))
        assert found is not None and not found.swapped and 355 <= found.distance_mm <= 458
        assert plate_elsewhere(right, left, CALIB, searched(300, 600)).swapped

    def test_eyes_swapped_are_said_to_be_so(self, plate_at_400):
        left, right = plate_at_400
        found = plate_elsewhere(right, left, CALIB, searched(300, 600))
        assert found is not None and found.swapped and found.distance_mm == pytest.approx(400, abs=12)
        assert "right eye's image as the left" in found.describe(searched(300, 600))

    def test_eyes_swapped_at_a_disparity_of_no_distance_are_said_without_one(self, plate_at_400):
        # a range reaching 0 px with doffs cancelling the disparity found: a division by zero made the part's
        # plate check fail (an ERROR saying nothing of the camera)
        left, right = plate_at_400
        calib = replace(CALIB, doffs=-105.0)
        found = plate_elsewhere(right, left, calib, (0.0, 120.0))
        assert found is not None and found.swapped and found.disparity == 105.0 and found.distance_mm == math.inf

    def test_images_without_texture_to_match_say_nothing(self):
        rng = np.random.default_rng(0)
        left, right = (np.clip(rng.normal(128, 2, (192, 320, 3)), 0, 255).astype(np.uint8) for _ in range(2))
        assert plate_elsewhere(left, right, CALIB, searched(200, 300)) is None

    @pytest.mark.parametrize("other", ["another plate", "noise"])
    def test_images_of_two_scenes_are_said_to_match_nowhere(self, plate_at_400, other):
        # a damaged image, or one eye's image from another moment: the part passed as if its plate were in place
        left, _ = plate_at_400
        right = (render(CALIB, 400.0, seed=7)[1] if other == "another plate" else
                 np.random.default_rng(0).integers(0, 256, left.shape, dtype=np.uint8))
        found = plate_elsewhere(left, right, CALIB, searched(300, 600))
        assert found is not None and found.unmatched >= 3 and not found.swapped and math.isnan(found.distance_mm)
        assert "do not show one scene" in found.describe(searched(300, 600))

    @pytest.mark.parametrize("rows, in_place", [(1, True), (3, False), (-5, False), (8, False)])
    def test_eyes_rows_apart_are_said_to_be_so_where_their_texture_no_longer_overlaps(self, plate_at_400, rows,
                                                                                     in_place):
        # a rectification that does not fit the camera: this fine texture still matches a row off; further off it
        # matches nowhere with the rows together, and within the range with them as far apart as the camera has them
        left, right = plate_at_400
        found = plate_elsewhere(left, np.roll(right, rows, axis=0), CALIB, searched(300, 600))
        if in_place:
            assert found is None
            return
        assert found is not None and found.rows_apart == rows and not found.unmatched and not found.swapped
        assert found.describe(searched(300, 600)).startswith(
            f"the left and right images match within the 70-140 px the stereo search covers only with the right eye's "
            f"rows {rows:+d} px from the left eye's")

    def test_rows_further_apart_than_tried_or_another_scene_stay_unmatched(self, plate_at_400):
        left, right = plate_at_400
        for other in (np.roll(right, 12, axis=0), render(CALIB, 400.0, seed=7)[1]):
            found = plate_elsewhere(left, other, CALIB, searched(300, 600))
            assert found is not None and found.unmatched >= 3 and not found.rows_apart

    def test_a_frame_too_small_to_tell_is_not_judged(self, plate_at_400):
        left, right = plate_at_400
        assert plate_elsewhere(left[:MIN_SIDE_PX - 1], right[:MIN_SIDE_PX - 1], CALIB, searched(200, 300)) is None

    def test_the_pair_must_be_two_colour_images_of_one_size(self, plate_at_400):
        left, right = plate_at_400
        with pytest.raises(ValueError, match="must be the same HxWx3"):
            plate_elsewhere(left, right[:100], CALIB, searched(300, 600))
