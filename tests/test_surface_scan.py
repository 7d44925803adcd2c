"""core.surface_scan: where a surface matches, over every disparity."""
from __future__ import annotations

import numpy as np
import pytest
from synthetic_pairs import step_pair

from core.surface_scan import MAX_PIXELS, correlations, scan_surface


def ring(x0: int, y0: int, x1: int, y1: int, width: int = 8) -> tuple[np.ndarray, np.ndarray]:
    v, u = np.mgrid[y0 - width:y1 + width, x0 - width:x1 + width]
    outside = (u < x0) | (u >= x1) | (v < y0) | (v >= y1)
    return u[outside].ravel(), v[outside].ravel()


class TestScanSurface:
    @pytest.mark.parametrize("shift", [5.0, 37.0, 61.0])
    def test_finds_the_whole_pixel_shift_of_a_textured_plane(self, shift):
        left, right, _ = step_pair(width=240, height=100, plane=(0.0, 0.0, shift), step_box=None)
        found = scan_surface(left, right, *ring(150, 35, 200, 65))
        assert found is not None and found.disparity == shift and found.correlation > 0.8

    def test_a_ring_of_many_thousand_pixels_is_read_in_part_and_found_all_the_same(self):
        left, right, _ = step_pair(width=420, height=300, plane=(0.0, 0.0, 44.0), step_box=None)
        u, v = ring(150, 60, 350, 240, width=12)
        assert u.size > 4 * MAX_PIXELS
        found = scan_surface(left, right, u, v)
        assert found is not None and found.disparity == 44.0

    def test_a_gently_slanted_plane_is_found_at_its_mean(self):
        left, right, _ = step_pair(width=240, height=100, plane=(0.0, 0.02, 30.0), step_box=None)
        found = scan_surface(left, right, *ring(150, 35, 200, 65))
        assert found is not None and abs(found.disparity - 31.0) <= 1.0  # 30 + 0.02 * 50, the ring's mean row

    def test_unrelated_images_have_no_distinct_best(self):
        left, _, _ = step_pair(width=240, height=100, seed=1, step_box=None)
        right, _, _ = step_pair(width=240, height=100, seed=2, step_box=None)
        assert scan_surface(left, right, *ring(150, 35, 200, 65)) is None

    def test_a_shift_beyond_the_scan_gives_no_best_among_the_wrong_ones(self):
        left, right, _ = step_pair(width=240, height=100, plane=(0.0, 0.0, 61.0), step_box=None)
        assert scan_surface(left, right, *ring(150, 35, 200, 65), max_disparity=50) is None

    def test_shapes_are_checked(self):
        left = np.zeros((10, 20), np.float32)
        with pytest.raises(ValueError, match="same HxW"):
            scan_surface(left, left[:, 1:], np.array([1]), np.array([1]))
        with pytest.raises(ValueError, match="same \\(N,\\)"):
            scan_surface(left, left, np.array([1, 2]), np.array([1]))
        assert scan_surface(left, left, np.array([], int), np.array([], int)) is None


class TestCorrelations:
    def test_peaks_at_the_shift_and_scores_only_the_shifts_asked_for(self):
        left, right, _ = step_pair(width=240, height=100, plane=(0.0, 0.0, 37.0), step_box=None)
        u, v = ring(150, 35, 200, 65)
        d = np.arange(30, 45)
        r = correlations(left, right, u, v, d)
        assert r.shape == d.shape and d[np.argmax(r)] == 37 and r.max() > 0.8

    def test_a_shift_that_takes_most_pixels_out_of_the_image_is_not_scored(self):
        left, right, _ = step_pair(width=240, height=100, plane=(0.0, 0.0, 5.0), step_box=None)
        u, v = ring(150, 35, 200, 65)
        r = correlations(left, right, u, v, np.array([5, 190, -100]))
        assert r[0] > 0.8 and np.isneginf(r[1]) and np.isneginf(r[2])
