"""``core.error_parts``: a deviation's error split into the ring's, the region's estimate's and its extent's."""
from __future__ import annotations

import numpy as np
import pytest

from core.depth import DepthRule, Plane
from core.error_parts import ErrorParts, error_parts
from core.types import Calibration

CALIB = Calibration(700.0, 120.0, 159.5, 119.5, 320, 240)
FB = CALIB.focal_px * CALIB.baseline_mm
PLATE_PX = 60.0  # a plate facing the camera: the deviation is the difference of the distances
PIT_PX = 0.4
BOX = (100.0, 100.0, 140.0, 130.0)  # the pit's own footprint, its walls vertical
TOLERANCE = 0.01


def truth(plate=lambda u, v: PLATE_PX + 0 * u, crossing: bool = False) -> np.ndarray:
    v, u = np.mgrid[0:240, 0:320].astype(np.float64)
    d = plate(u, v)
    d[100:130, 100:140] -= PIT_PX
    if crossing:
        d[80:95, 150:170] += 2.0  # another defect across the ring
    d[:, :20] = np.nan  # unknown where the left eye alone looks
    return d


def z(d: float) -> float:
    return FB / d


TRUE_DEVIATION = z(PLATE_PX - PIT_PX) - z(PLATE_PX)  # 19.2 mm at 1,400 mm


def parts(deviation, region_px=PLATE_PX - PIT_PX, true_deviation=TRUE_DEVIATION, box=BOX, d=None) -> ErrorParts:
    found = error_parts(deviation, z(region_px), true_deviation, truth() if d is None else d, CALIB, box, DepthRule(),
                        TOLERANCE)
    assert found is not None
    total = found.ring_mm + found.region_mm + found.extent_mm
    assert total == pytest.approx(deviation - true_deviation, abs=1e-9)  # the parts always sum to the error
    return found


class TestErrorParts:
    def test_an_exact_measurement_has_no_error_in_any_part(self):
        found = parts(TRUE_DEVIATION)
        assert (found.ring_mm, found.region_mm, found.extent_mm) == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)

    def test_a_deviation_off_with_the_regions_distance_right_is_the_rings_error(self):
        found = parts(TRUE_DEVIATION + 0.2)
        assert found.ring_mm == pytest.approx(0.2, abs=1e-9)
        assert (found.region_mm, found.extent_mm) == pytest.approx((0.0, 0.0), abs=1e-9)

    def test_a_region_read_nearer_against_the_true_ring_is_the_regions_estimate(self):
        region = PLATE_PX - PIT_PX + 0.05
        found = parts(z(region) - z(PLATE_PX), region_px=region)
        assert found.region_mm == pytest.approx(z(region) - z(PLATE_PX - PIT_PX), abs=1e-9)
        assert found.region_mm < -1.0  # 0.05 px at 1.4 m: 1.2 mm
        assert (found.ring_mm, found.extent_mm) == pytest.approx((0.0, 0.0), abs=1e-9)

    def test_a_box_larger_than_its_pit_holds_the_plate_too_the_regions_extent(self):
        large = (80.0, 85.0, 160.0, 145.0)  # twice the pit: its region, the central 60 %, 48 x 36 px
        share = (40 * 30) / (48 * 36)
        mean = PLATE_PX - PIT_PX * share
        found = parts(z(mean) - z(PLATE_PX), region_px=mean, box=large)
        assert found.extent_mm == pytest.approx(z(mean) - z(PLATE_PX - PIT_PX), rel=1e-9)
        assert found.extent_mm < -0.25 * TRUE_DEVIATION
        assert (found.ring_mm, found.region_mm) == pytest.approx((0.0, 0.0), abs=1e-9)

    def test_the_rings_true_plane_is_its_consensus_on_a_tilted_plate_with_another_defect_across_it(self):
        def plate(u, v):
            return 60.0 + 0.05 * u - 0.02 * v

        d = truth(plate, crossing=True)
        u0, v0 = 119.5, 114.5  # the region's centre: the central 60 % of the box, by area
        c = plate(u0, v0)
        for ring_error_px in (0.0, 0.1):
            region = c - PIT_PX
            # a deviation read against a ring c + ring_error_px: the region's distance is the truth
            n = Plane(0.05, -0.02, c + ring_error_px - 0.05 * u0 + 0.02 * v0).normal_length(CALIB)
            deviation = FB * ((c + ring_error_px) / region - 1.0) / n
            found = parts(deviation, region_px=region, true_deviation=deviation - 0.3 if ring_error_px else 1.0, d=d)
            assert found.region_mm == pytest.approx(0.0, abs=1e-9)
            if ring_error_px:
                assert found.ring_mm > 1.0  # 0.1 px of the ring's plane is millimetres at this distance
                assert found.ring_mm + found.extent_mm == pytest.approx(0.3, abs=1e-9)
            else:
                assert found.ring_mm == pytest.approx(0.0, abs=1e-6)

    def test_no_parts_where_the_truth_knows_no_ring_or_too_little_of_the_region(self):
        unknown = np.full((240, 320), np.nan)
        assert error_parts(1.0, 1400.0, 1.0, unknown, CALIB, BOX, DepthRule(), TOLERANCE) is None
        d = truth()
        d[100:130, 100:125] = np.nan  # more than half the region
        assert error_parts(1.0, 1400.0, 1.0, d, CALIB, BOX, DepthRule(), TOLERANCE) is None

    def test_the_truth_must_be_one_image(self):
        with pytest.raises(ValueError, match="HxW"):
            error_parts(1.0, 1400.0, 1.0, np.zeros((240, 320, 3)), CALIB, BOX, DepthRule(), TOLERANCE)
