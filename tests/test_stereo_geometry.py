"""``drivers.stereo_geometry``: whether a calibration can be a camera's."""
from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.stereo_geometry import calibration_problem

# (focal_px, baseline_mm, cx, cy, width, height, doffs)
ZED_WVGA = (350.06, 120.0, 335.5, 187.5, 672, 376, 0.0)


class TestCalibrationProblem:
    @pytest.mark.parametrize("values", [
        ZED_WVGA,
        (1400.0, 120.0, 1104.0, 621.0, 2208, 1242, 0.0),  # a ZED at 2K
        (1038.0, 63.0, 640.0, 360.0, 1280, 720, 0.0),  # a ZED Mini at HD720
        (1429.0, 193.0, 412.0, 210.0, 741, 497, 33.0),  # a Middlebury quarter-size scene, doffs and all
        (350, 120, 335, 187, np.int64(672), np.int32(376), 0),  # integers, numpy's too
        (350.0, 120.0, -100.0, 500.0, 672, 376, 0.0),  # a principal point a little outside a cropped image
    ])
    def test_cameras_pass(self, values):
        assert calibration_problem(*values) is None

    @pytest.mark.parametrize("index, value, says", [
        (0, 1e300, "focal_px 1e+300 is no camera's for a 672 px wide image: a field of view of 0.25-170 degrees is 29-154011 px"),
        (0, 20.0, "focal_px 20 is no camera's"),
        (1, 0.12, "baseline_mm 0.12 lies outside 1-10000 mm (metres written for millimetres?)"),
        (1, 1e6, "baseline_mm 1e+06 lies outside 1-10000 mm"),
        (2, 1e30, "cx 1e+30 lies far outside the 672 px wide image"),
        (2, -700.0, "cx -700 lies far outside"),
        (3, 800.0, "cy 800 lies far outside the 376 px high image"),
        (4, 672.5, "width must be a whole number of pixels above 0 (got 672.5)"),
        (5, 0, "height must be a whole number of pixels above 0 (got 0)"),
        (6, -672.0, "doffs must lie within the image's width, 672 px (got -672.0)"),
        (0, math.nan, "focal_px must be a finite number (got nan)"),
        (2, math.inf, "cx must be a finite number (got inf)"),
        (1, True, "baseline_mm must be a finite number (got True)"),
        (3, "187.5", "cy must be a finite number (got '187.5')"),
    ])
    def test_the_value_no_camera_has_is_named(self, index, value, says):
        values = list(ZED_WVGA)
        values[index] = value
        problem = calibration_problem(*values)
        assert problem is not None and problem.startswith(says), problem

    def test_the_baseline_is_not_said_to_be_in_metres_when_too_long(self):
        values = list(ZED_WVGA)
        values[1] = 20_000.0
        assert "metres" not in calibration_problem(*values)
