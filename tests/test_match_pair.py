"""``core.engine.match_pair``: the backend is not given the left columns whose match would lie left of
the right image."""
from __future__ import annotations

import numpy as np
import pytest
from synthetic_pairs import calib_for, render

from core.contracts import PluginContext
from core.engine import match_pair
from core.registry import default_registry


class Recording:
    """A backend that keeps what it was given and answers its range's lower end everywhere."""

    def __init__(self):
        self.calls = []

    def compute(self, left, right, min_disp, max_disp):
        self.calls.append((left.copy(), right.copy(), min_disp, max_disp))
        return np.full(left.shape[:2], min_disp + 0.25, dtype=np.float32)


class TestMatchPair:
    def test_the_backend_gets_the_columns_that_can_match_and_a_range_from_zero(self):
        rng = np.random.default_rng(0)
        left, right = (rng.integers(0, 255, (20, 100, 3), dtype=np.uint8) for _ in range(2))
        backend = Recording()
        out = match_pair(backend, left, right, 30.6, 50.0)
        given_left, given_right, lo, hi = backend.calls[0]
        np.testing.assert_array_equal(given_left, left[:, 30:])
        np.testing.assert_array_equal(given_right, right[:, :70])
        assert (lo, hi) == pytest.approx((0.6, 20.0))
        assert out.shape == (20, 100) and out.dtype == np.float32
        assert np.isnan(out[:, :30]).all()
        np.testing.assert_allclose(out[:, 30:], 30.85)

    def test_no_match_markers_stay_no_match_after_the_shift(self):
        class Markers:
            def compute(self, left, right, min_disp, max_disp):
                out = np.full(left.shape[:2], 5.5, np.float32)
                out[0], out[1], out[2] = -1.0, 0.0, np.nan  # three ways of saying "no match"
                return out

        left = right = np.zeros((4, 100, 3), np.uint8)
        out = match_pair(Markers(), left, right, 30.0, 50.0)
        assert np.isnan(out[:3]).all() and np.all(out[3, 30:] == 35.5)

    def test_a_range_from_zero_or_below_is_passed_as_it_is(self):
        left = right = np.zeros((8, 40, 3), np.uint8)
        backend = Recording()
        match_pair(backend, left, right, -2.0, 16.0)
        assert backend.calls[0][0].shape == (8, 40, 3) and backend.calls[0][2:] == (-2.0, 16.0)

    def test_a_range_beyond_the_image_leaves_one_column(self):
        left = right = np.zeros((8, 40, 3), np.uint8)
        backend = Recording()
        out = match_pair(backend, left, right, 64.0, 80.0)
        assert backend.calls[0][0].shape == (8, 1, 3)
        assert np.isnan(out[:, :39]).all()

    def test_a_real_backend_finds_the_same_disparities(self):
        calib = calib_for(320, 120)
        left, right, truth = render(calib, 420.0, tilt_deg=10.0, seed=3)
        lo, hi = float(np.floor(truth.min())) - 6, float(np.ceil(truth.max())) + 6
        sgbm = default_registry().get("stereo", "opencv_sgbm").spec.factory({}, PluginContext())
        shifted = match_pair(sgbm, left, right, lo, hi)
        whole = sgbm.compute(left, right, lo, hi)
        both = np.isfinite(shifted) & np.isfinite(whole)
        assert both[:, int(hi) + 8:].mean() > 0.9
        assert np.abs(shifted - truth)[both].mean() < 0.25
        assert np.abs(shifted - whole)[both].mean() < 0.05
