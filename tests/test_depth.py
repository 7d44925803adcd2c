"""Depth per defect against exact geometry."""
from __future__ import annotations

import dataclasses
import json
import math
import os
import pathlib
import subprocess
import sys
import textwrap

import cv2
import numpy as np
import pytest
from conftest import ROOT
from synthetic_pairs import Groove, Pit, calib_for, render

from core import band_scan, box_reach, depth, depth_numba, surface_fit, uncertainty_budget
from core.depth import DepthRule, fit_plane_robust, measure_defect, ring_mask
from core.decision import judge_defect
from core.recipe import load_recipe
from core.types import Calibration, Detection, Status

CALIB = calib_for(320, 192)
BOX = (135.0, 71.0, 185.0, 121.0)


def _measure(disparity, box=BOX, **rule):
    return measure_defect(disparity, Detection("pit", 0.9, box), CALIB, DepthRule(**rule))


@pytest.mark.parametrize("tilt", [0.0, 8.0])
def test_flat_plate_distance_and_zero_deviation(tilt):
    _, _, disparity = render(CALIB, 400.0, tilt)
    m = _measure(disparity)
    assert m.distance_mm == pytest.approx(400.0, abs=0.5)
    assert abs(m.deviation_mm) < 0.01
    assert m.valid_fraction == 1.0
    # Z^2 / (f B) * noise
    assert m.depth_resolution_mm == pytest.approx(400.0**2 / (350.06 * 120) * 0.25, rel=0.01)


@pytest.mark.parametrize("depth", [2.0, -1.5])
def test_pit_centre_deviation_matches_design_depth_on_tilted_plate(depth):
    _, _, disparity = render(CALIB, 420.0, 6.0, [Pit(160, 96, 25.0, depth)])
    # A small region at the cap's centre sees (almost) its full depth; sign: + below, - raised.
    m = _measure(disparity, box=(157.0, 93.0, 163.0, 99.0), inner_fraction=1.0, ring_gap_px=30)
    assert m.deviation_mm == pytest.approx(depth, rel=0.03)


def test_inner_roi_sees_more_of_the_pit_than_the_whole_box():
    _, _, disparity = render(CALIB, 400.0, 0.0, [Pit(160, 96, 25.0, 3.0)])
    inner, whole = _measure(disparity), _measure(disparity, inner_fraction=1.0)
    assert 0 < whole.deviation_mm < inner.deviation_mm < 3.0


def test_too_few_valid_pixels_means_unavailable():
    _, _, disparity = render(CALIB, 400.0)
    disparity[60:130, 120:200] = np.nan
    disparity[96, 160] = 105.0
    m = _measure(disparity)
    assert m.distance_mm is None and m.deviation_mm is None
    assert "depth unavailable" in m.note and m.valid_fraction < 0.1


def test_a_region_without_one_valid_pixel_is_unavailable_whatever_share_the_recipe_allows():
    m = _measure(np.full((192, 320), np.nan, np.float32), min_valid_fraction=0.0)
    assert m.distance_mm is None and m.deviation_mm is None and "0% of the region valid" in m.note


def test_zero_and_inf_count_as_invalid():
    _, _, disparity = render(CALIB, 400.0)
    disparity[71:121, 135:160] = 0.0
    disparity[71:121, 160:182] = np.inf
    m = _measure(disparity, inner_fraction=1.0)
    assert m.valid_fraction == pytest.approx(3 / 50, abs=0.01)
    assert m.distance_mm is None


def test_no_surface_ring_gives_distance_without_deviation():
    _, _, disparity = render(CALIB, 400.0)
    ring = ring_mask(disparity.shape, BOX, 3, 12)
    disparity[ring] = np.nan
    m = _measure(disparity)
    assert m.distance_mm == pytest.approx(400.0, abs=0.5)
    assert m.deviation_mm is None and "deviation unavailable" in m.note


def test_plane_fit_ignores_outliers():
    rng = np.random.default_rng(1)
    u, v = rng.uniform(0, 100, 400), rng.uniform(0, 100, 400)
    d = 0.02 * u - 0.03 * v + 50 + rng.normal(0, 0.05, 400)
    d[:60] += rng.uniform(5, 20, 60)  # another defect in the ring
    plane = fit_plane_robust(u, v, d)
    assert plane.a == pytest.approx(0.02, abs=0.002)
    assert plane.b == pytest.approx(-0.03, abs=0.002)
    assert plane.c == pytest.approx(50, abs=0.1)


class TestInlierCounts:
    def test_counts_what_numpy_counts_on_the_tolerance_too(self):
        rng = np.random.default_rng(2)
        u, v = rng.uniform(0, 200, 900), rng.uniform(0, 80, 900)
        planes = rng.normal(0, [0.05, 0.05, 1.0], (64, 3)) + [0.0, 0.0, 60.0]
        d = 0.01 * u - 0.02 * v + 60 + rng.normal(0, 0.7, 900)
        # points exactly on a hypothesis's tolerance: both counts must agree on them as well
        d[:20] = planes[0, 0] * u[:20] + planes[0, 1] * v[:20] + planes[0, 2] - 1.0
        expected = (np.abs(planes[:, :1] * u + planes[:, 1:2] * v + planes[:, 2:3] - d) <= 1.0).sum(axis=1)
        assert np.array_equal(depth_numba.inlier_counts(planes, u, v, d, 1.0), expected)

    def test_shapes_are_checked(self):
        with pytest.raises(ValueError, match="planes"):
            depth_numba.inlier_counts(np.zeros((4, 2)), np.zeros(3), np.zeros(3), np.zeros(3), 1.0)
        with pytest.raises(ValueError, match="must be"):
            depth_numba.inlier_counts(np.zeros((4, 3)), np.zeros(3), np.zeros(2), np.zeros(3), 1.0)


class TestWarmUp:
    def test_compiles_what_a_measurement_runs(self):
        # in a process of its own: here other tests may have compiled every signature already
        script = textwrap.dedent("""
            import json
            import numpy as np
            from synthetic_pairs import step_pair
            from core import band_scan, band_scan_numba, box_reach, box_reach_numba, depth, depth_numba
            from core import surface_fit as sf, surface_fit_numba as sfn
            from test_surface_fit import PLANE, _regions
            kernels = (sfn._system, sfn._offset_costs, sfn.robust_scale, sfn._spline_coefficients,
                       sfn._sample_rows, depth_numba._inlier_counts, sfn._ring_cell_offsets, sfn._cell_steps,
                       sfn._tukey_offset, sfn._gauss_newton, sfn._jacobian_rows, box_reach_numba._copy_readings,
                       sfn._plane_consensus, band_scan_numba._best_band)
            depth.warm_up()
            before = [len(k.signatures) for k in kernels]
            left, right, _ = step_pair(plane=PLANE, step_px=-0.3, seed=0)
            fit = sf.fit_surface(left, right, *_regions(), PLANE, -0.3)
            assert fit is not None
            offsets, sds, centres, _ = sf.cell_offsets(left, right, fit, _regions()[1])
            sf.robust_offset(offsets, sds, fit.delta, areas=np.ones(len(offsets)))
            box_reach.moved_regions(offsets, sds, np.ones(len(offsets)), centres, (74, 55, 86, 65), (24, 18))
            band_scan.central_band(offsets, sds, centres, (80.0, 60.0))
            sf.interior_variance(left, right, fit, _regions()[1], None, (68, 51, 92, 69), 1.0)
            u, v = np.meshgrid(np.arange(60.0), np.arange(40.0))
            assert depth.fit_plane_robust(u.ravel(), v.ravel(), 0.1 * u.ravel() + 50) is not None
            print(json.dumps([before, [len(k.signatures) for k in kernels]]))
        """)
        tests = pathlib.Path(__file__).parent
        out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True,
                             env={**os.environ, "PYTHONPATH": os.pathsep.join([str(tests), str(tests.parent)])})
        before, after = json.loads(out.stdout)
        # every kernel compiled by the warm-up, and nothing more by a measurement: each once (the kernels that
        # read two or three splines compile the sampler with them)
        assert before == after == [1] * 14, out.stdout


def test_area_in_square_mm():
    _, _, disparity = render(CALIB, 400.0)
    m = _measure(disparity)
    mm_per_px = 400.0 / 350.06
    assert m.area_mm2 == pytest.approx(50 * 50 * mm_per_px**2, rel=0.01)


def test_box_on_a_step_has_no_deviation():
    """A box on the plate's edge: half its ring is the belt 30 mm behind. No single surface."""
    _, _, disparity = render(CALIB, 400.0)
    far = CALIB.focal_px * CALIB.baseline_mm / 430.0
    disparity[:, 160:] = far
    m = _measure(disparity, box=(140.0, 71.0, 180.0, 121.0))
    assert m.deviation_mm is None and "not one plane" in m.note
    assert m.distance_mm is not None


def test_box_filling_the_image_has_no_deviation():
    _, _, disparity = render(CALIB, 400.0, 5.0)
    m = _measure(disparity, box=(2.0, 0.0, 320.0, 186.0))
    assert m.distance_mm is not None and m.deviation_mm is None
    assert m.note == "deviation unavailable: only its bottom side is in view (top, left, right outside the image)", m.note


def test_box_in_a_corner_is_measured_from_two_sides():
    _, _, disparity = render(CALIB, 400.0, 5.0, [Pit(20, 20, 24.0, 2.0)])
    m = _measure(disparity, box=(0.0, 0.0, 40.0, 40.0))
    assert m.deviation_mm is not None and 0.5 < m.deviation_mm < 2.0


# -- method: surface (the images themselves) ------------------------------------------------------

def _grey(image):
    from core.surface_fit import to_grey

    return to_grey(image)


def _surface(left, right, disparity, box=BOX, **rule):
    return measure_defect(disparity, Detection("pit", 0.9, box), CALIB, DepthRule(**rule), (_grey(left), _grey(right)))


@pytest.mark.parametrize("tilt", [0.0, 8.0])
def test_surface_method_on_a_flat_plate_from_a_whole_pixel_backend(tilt):
    left, right, disparity = render(CALIB, 400.0, tilt)
    coarse = np.round(disparity)  # a matcher that knows the disparity to a pixel only
    m = _surface(left, right, coarse)
    assert m.method == "surface" and m.note == ""
    assert m.deviation_sigma_mm < 0.1 and abs(m.deviation_mm) <= 3 * m.deviation_sigma_mm
    assert m.distance_mm == pytest.approx(400.0, abs=3 * m.distance_sigma_mm + 0.05)
    reference = _measure(coarse)
    assert reference.method == "disparity" and abs(reference.distance_mm - 400) > abs(m.distance_mm - 400)


def _faint_beyond(radius_mm: float):
    return lambda local: np.where(np.hypot(local[..., 0], local[..., 1]) > radius_mm, 0.15, 1.0)


class TestRingWidth:
    """The ring is widened where its texture is faint against the region's, before the fit (``depth.ring_width``)."""

    def test_a_ring_as_textured_as_its_region_keeps_its_width(self):
        left, _, _ = render(CALIB, 420.0, 6.0, [Pit(160, 96, 25.0, 1.5, floor=0.8)])
        assert depth.ring_width(_grey(left), BOX, DepthRule()) == 12

    def test_a_ring_fainter_than_its_region_is_widened(self):
        # the plate's texture at 0.15 of its contrast from 30 mm around the pit: the whole ring (from 28 px, 34 mm)
        left, _, _ = render(CALIB, 420.0, 6.0, [Pit(160, 96, 25.0, 1.5, floor=0.8)], contrast=_faint_beyond(30.0))
        grey = _grey(left)
        assert depth.ring_width(grey, BOX, DepthRule()) == 20
        assert depth.ring_width(grey, BOX, DepthRule(faint_ring_width_px=28)) == 28
        # a faint width no wider than the ring never narrows it, and the map alone never widens it
        assert depth.ring_width(grey, BOX, DepthRule(ring_width_px=16, faint_ring_width_px=8)) == 16
        assert depth.ring_width(grey, BOX, DepthRule(method="disparity")) == 12

    def test_the_region_s_texture_is_what_the_ring_is_compared_with(self):
        # the same faint ring around a region as faint as it is: nothing to gain, the ring kept
        left, _, _ = render(CALIB, 420.0, 6.0, [Pit(160, 96, 25.0, 1.5, floor=0.8)], contrast=lambda local: np.full(
            local.shape[:-1], 0.15))
        assert depth.ring_width(_grey(left), BOX, DepthRule()) == 12

    def test_shapes_are_checked(self):
        with pytest.raises(ValueError, match="HxW"):
            depth.ring_width(np.zeros((192, 320, 3), np.float32), BOX, DepthRule())

    def test_the_widened_ring_scatters_less_and_its_uncertainty_says_so(self):
        """Over noisy renders of a pit on a plate whose texture fades beyond it, the measurement with the widened
        ring scatters less than with the ring kept at its width, reports a smaller uncertainty, and keeps the true
        deviation within twice it."""
        kept, widened = [], []
        for seed in range(12):
            noise = np.random.default_rng(seed)
            left, right, disparity = render(CALIB, 420.0, 6.0, [Pit(160, 96, 25.0, 1.5, floor=0.8)], seed=seed,
                                            contrast=_faint_beyond(30.0))
            pair = tuple(np.clip(image[..., 0] + noise.normal(0, 2.0, image.shape[:2]), 0, 255).astype(np.float32)
                         for image in (left, right))
            blurred = cv2.blur(np.round(disparity * 4) / 4, (9, 9))
            for out, width in ((kept, 12), (widened, 20)):
                m = measure_defect(blurred, Detection("pit", 0.9, BOX), CALIB, DepthRule(faint_ring_width_px=width),
                                   pair)
                assert m.method == "surface", m.note
                out.append((m.deviation_mm, m.deviation_sigma_mm))
        kept, widened = np.array(kept), np.array(widened)
        assert np.std(widened[:, 0]) < 0.7 * np.std(kept[:, 0])
        assert np.median(widened[:, 1]) < np.median(kept[:, 1])
        assert np.mean(np.abs(widened[:, 0] - 1.5) <= 2 * widened[:, 1]) >= 0.9


def test_the_matcher_s_noise_in_the_ring_does_not_move_the_surface_fit():
    # a crop of the matcher's map differs from the full frame's by noise where the texture is faint: ring pixels
    # it puts more than its tolerance off the plane in one map and not the other. The fit reads the images over
    # the whole ring (its cells leave out what lies on another surface), so such pixels change nothing; left out
    # of the ring they moved a defect on faint lens-blurred plates by 0.05 mm
    left, right, disparity = render(CALIB, 420.0, 6.0, [Pit(160, 96, 25.0, 1.5)])
    noisy = disparity.copy()
    ring = ring_mask(disparity.shape, BOX, 3, 12)
    rng = np.random.default_rng(3)
    flip = ring & (rng.uniform(size=disparity.shape) < 0.05)
    noisy[flip] += rng.choice([-1.5, 1.5], size=int(flip.sum()))  # beyond the 1 px tolerance
    a, b = _surface(left, right, disparity), _surface(left, right, noisy)
    assert a.method == b.method == "surface"
    assert b.deviation_mm == pytest.approx(a.deviation_mm, abs=1e-4)
    assert b.deviation_sigma_mm == pytest.approx(a.deviation_sigma_mm, rel=1e-3)


def test_surface_method_measures_a_pit_that_the_backend_blurs():
    left, right, disparity = render(CALIB, 420.0, 6.0, [Pit(160, 96, 25.0, 3.0)])
    truth = _measure(disparity)  # the platform's definition on the exact disparity
    blurred = cv2.blur(np.round(disparity * 4) / 4, (9, 9))  # a quarter-pixel matcher with 9x9 windows
    m = _surface(left, right, blurred)
    assert abs(m.deviation_mm - truth.deviation_mm) <= 3 * m.deviation_sigma_mm + 0.05
    assert abs(m.deviation_mm - truth.deviation_mm) < abs(_measure(blurred).deviation_mm - truth.deviation_mm)


def test_a_flat_bottomed_pit_keeps_an_uncertainty_near_what_its_pixels_allow(monkeypatch):
    """The wall a region may hold unseen widens the deviation's uncertainty by half a pixel's share of it
    (``WALL_PX``): on a pit whose region lies wholly on its flat floor that allowance is there, but it does not
    swamp what the fit itself can tell."""
    left, right, disparity = render(CALIB, 420.0, 6.0, [Pit(160, 96, 25.0, 1.5, floor=0.8)])
    blurred = cv2.blur(np.round(disparity * 4) / 4, (9, 9))
    m = _surface(left, right, blurred)
    assert abs(m.deviation_mm - 1.5) <= 2 * m.deviation_sigma_mm
    monkeypatch.setattr(depth, "WALL_PX", 0.0)
    without = _surface(left, right, blurred)
    assert without.deviation_mm == m.deviation_mm
    assert without.deviation_sigma_mm < m.deviation_sigma_mm < 1.5 * without.deviation_sigma_mm


def test_the_cells_and_the_joint_fit_together_scatter_less_than_the_cells_alone(monkeypatch):
    """The defect's offset is the mean of its cells' robust offset and the joint fit's own (``FIT_SHARE``):
    over noisy renders of one pit, the deviation it gives scatters less than the cells' alone."""
    pairs = []
    for seed in range(48):
        noise = np.random.default_rng(seed)
        left, right, disparity = render(CALIB, 420.0, 6.0, [Pit(160, 96, 25.0, 1.5, floor=0.8)], seed=seed)
        noisy = tuple(np.clip(image[..., 0] * gain + noise.normal(0, 6.0, image.shape[:2]), 0, 255).astype(np.float32)
                      for image, gain in ((left, 1.0), (right, 1.05)))
        pairs.append((noisy, cv2.blur(np.round(disparity * 4) / 4, (9, 9))))

    def spread(share: float) -> float:
        monkeypatch.setattr(depth, "FIT_SHARE", share)
        return float(np.std([measure_defect(blurred, Detection("pit", 0.9, BOX), CALIB, DepthRule(), pair).deviation_mm
                             for pair, blurred in pairs]))

    assert depth.FIT_SHARE == 0.5
    assert spread(0.5) < 0.98 * spread(0.0)  # 0.95 of it


def _groove_and_box(angle_deg: float, width_mm: float, depth_mm: float = 2.0, shading: float = 0.0):
    """A pair with a straight groove across the middle at 420 mm, the groove's box (its footprint's upright
    bounding box, as a detector gives it) and its truth: its mean depth where the box's region lies on it.
    ``shading``: its walls lit from one side (``render``)."""
    left, right, disparity = render(CALIB, 420.0, 0.0, [Groove(160, 96, angle_deg, 70.0, width_mm, depth_mm)],
                                    shading=shading)
    plate = CALIB.focal_px * CALIB.baseline_mm / 420.0
    v, u = np.nonzero(disparity < plate - 1e-3)
    box = (float(u.min()), float(v.min()), float(u.max() + 1), float(v.max() + 1))
    x0, y0, x1, y1 = (int(round(c)) for c in depth.roi_box(box, DepthRule()))
    region = disparity[y0:y1, x0:x1]
    on = region < plate - 1e-3
    return left, right, disparity, box, float(np.mean(CALIB.focal_px * CALIB.baseline_mm / region[on] - 420.0))


@pytest.mark.parametrize("angle, width", [(40.0, 6.0), (130.0, 10.0), (25.0, 10.0)])
def test_a_groove_across_its_box_is_measured_along_it(angle, width):
    """Most of the box's region is the surface beside a turned groove: the region alone reads it at half its
    depth or less, and proves it inside a limit it lies beyond (docs/depth-conditions.md)."""
    left, right, disparity, box, truth = _groove_and_box(angle, width)
    m = _surface(left, right, disparity, box)
    assert "along a groove" in m.note
    # the band found runs the groove's way (angles from the rows, modulo a half turn)
    assert abs((m.groove_angle_deg - angle + 90.0) % 180.0 - 90.0) <= 15.0
    assert abs(m.deviation_mm - truth) <= 3 * m.deviation_sigma_mm + 0.05
    assert m.deviation_mm + 2 * m.deviation_sigma_mm > 1.0  # never proven inside a 1 mm limit


def test_a_band_too_faint_to_call_a_groove_widens_the_uncertainty_to_take_it_in(monkeypatch):
    left, right, disparity, box, truth = _groove_and_box(40.0, 6.0)
    monkeypatch.setattr(depth, "GROOVE_Z", np.inf)  # never sure enough to measure along it
    monkeypatch.setattr(depth, "_band_along_edges", lambda *args: None)  # nor looked for along the image's edges
    widened = _surface(left, right, disparity, box)
    monkeypatch.setattr(depth, "BAND_Z", np.inf)
    region = _surface(left, right, disparity, box)
    assert widened.note == region.note == "" and widened.deviation_mm == region.deviation_mm
    assert truth - region.deviation_mm > 3 * region.deviation_sigma_mm  # the region alone reads it short
    assert widened.deviation_sigma_mm > 1.5 * region.deviation_sigma_mm
    assert widened.deviation_mm + 2 * widened.deviation_sigma_mm > 1.0
    assert _largest(widened).kind == "band" and _largest(widened).cause.startswith("a band across the region, which ")
    assert _largest(region).kind != "band"


def test_a_band_along_the_walls_the_image_shows_widens_the_uncertainty_where_the_cells_alone_do_not(monkeypatch):
    left, right, disparity, box, truth = _groove_and_box(130.0, 10.0, shading=1.0)
    monkeypatch.setattr(depth, "GROOVE_Z", np.inf)
    monkeypatch.setattr(depth, "BAND_Z", np.inf)  # the scan of every angle says nothing
    along_edges = _surface(left, right, disparity, box)
    monkeypatch.setattr(depth, "_band_along_edges", lambda *args: None)
    region = _surface(left, right, disparity, box)
    assert along_edges.deviation_mm == region.deviation_mm  # the value stays the region's
    assert truth - region.deviation_mm > 3 * region.deviation_sigma_mm
    assert along_edges.deviation_sigma_mm > 1.5 * region.deviation_sigma_mm
    assert along_edges.deviation_mm + 2 * along_edges.deviation_sigma_mm > 1.0
    assert _largest(along_edges).kind == "along_edges"
    assert _largest(along_edges).cause.startswith("a band along the region's edges, which reads ")


def test_a_round_pit_s_edges_run_every_way_and_add_nothing(monkeypatch):
    left, right, disparity = render(CALIB, 400.0, 4.0, [Pit(160, 96, 25.0, 2.0)])
    looked = _surface(left, right, disparity)
    monkeypatch.setattr(depth, "_band_along_edges", lambda *args: None)
    assert _surface(left, right, disparity) == looked


@pytest.mark.parametrize("angle_deg", [120.0, 330.0])
def test_a_box_half_its_size_off_its_pit_is_not_proven_shallow(monkeypatch, angle_deg):
    # a flat-bottomed pit 14 px across; its box moved by half its size reads the plate beside it and little of
    # the pit, which the uncertainty must cover: the region moved back onto the pit reads it
    left, right, disparity = render(CALIB, 400.0, 0.0, [Pit(160, 96, 8.0, 2.0, floor=0.8)])
    r = CALIB.focal_px * 8.0 / 400.0
    true_box = (160 - r, 96 - r, 160 + r, 96 + r)
    truth = _surface(left, right, disparity, box=true_box).deviation_mm
    assert truth == pytest.approx(2.0, abs=0.15)
    a = math.radians(angle_deg)
    dx, dy = r * math.cos(a), r * math.sin(a)
    off = (true_box[0] + dx, true_box[1] + dy, true_box[2] + dx, true_box[3] + dy)
    m = _surface(left, right, disparity, box=off)
    assert m.deviation_mm < 0.5 * truth and abs(m.deviation_mm - truth) <= 2 * m.deviation_sigma_mm
    # and a rule that cannot decide says so: the region moved back towards the pit, and what it reads there
    cause = _largest(m).cause
    assert _largest(m).kind == "moved" and cause.startswith("the region moved ")
    assert cause.endswith(" mm: the box may not hold its defect")
    back = ("up", "right") if angle_deg == 120.0 else ("down", "left")
    assert all(f" px {way}" in cause for way in back), cause
    reads = float(cause.split("which reads ")[1].split(" mm")[0])
    assert reads > 0.5 * truth > m.deviation_mm  # the copy on the pit reads it, the region does not
    monkeypatch.setattr(depth, "_farthest_moved", lambda *args: None)
    alone = _surface(left, right, disparity, box=off)
    assert alone.deviation_mm == m.deviation_mm and abs(alone.deviation_mm - truth) > 2 * alone.deviation_sigma_mm
    assert _largest(alone).kind != "moved"


def _largest(m):
    return uncertainty_budget.largest(m.uncertainty_parts)[0]


@pytest.mark.parametrize("scene", ["flat plate", "pit", "groove", "box off its pit"])
def test_the_uncertainty_s_parts_add_up_to_its_variance(scene):
    """``uncertainty_parts`` is an account of deviation_sigma_mm: the surface around the box first, every term
    that adds to it after, none of them empty."""
    if scene == "groove":
        left, right, disparity, box, _ = _groove_and_box(40.0, 6.0)
    else:
        pits = [] if scene == "flat plate" else [Pit(160, 96, 8.0 if scene == "box off its pit" else 25.0, 2.0,
                                                     floor=0.8)]
        left, right, disparity = render(CALIB, 400.0, 3.0, pits)
        box = (150.0, 100.0, 178.0, 128.0) if scene == "box off its pit" else BOX
    m = _surface(left, right, disparity, box)
    assert m.method == "surface" and m.deviation_sigma_mm > 0
    assert sum(p.variance_mm2 for p in m.uncertainty_parts) == pytest.approx(m.deviation_sigma_mm ** 2, rel=1e-9)
    assert (m.uncertainty_parts[0].kind, m.uncertainty_parts[0].cause) == ("surface", depth.RING_CAUSE)
    assert all(p.variance_mm2 > 0 and p.kind in uncertainty_budget.KINDS for p in m.uncertainty_parts)
    assert len({p.kind for p in m.uncertainty_parts}) == len(m.uncertainty_parts)


def test_the_backend_s_map_alone_gives_no_account_of_its_uncertainty():
    left, right, disparity = render(CALIB, 400.0, 3.0, [Pit(160, 96, 25.0, 2.0)])
    assert _measure(disparity).uncertainty_parts == ()


def _band(offset: float, variance: float, z: float) -> band_scan.Band:
    return band_scan.Band(45.0, 4.0, 0.0, np.ones(8, dtype=bool), offset, 0.0, variance, z)


def _patch(delta: float, variance: float) -> surface_fit.RobustOffset:
    return surface_fit.RobustOffset(delta, variance, 6, 6.0, 1.0)


def _parts_variance(*args) -> float:
    """The variance ``depth._widest_part`` adds for the part it finds, 0 for none."""
    part = depth._widest_part(*args)
    return 0.0 if part is None else part.variance


class TestPartsVariance:
    def test_none_adds_nothing(self):
        assert _parts_variance(-0.2, None, None, None) == 0.0

    def test_a_band_counts_from_band_z_less_its_own_noise(self):
        assert _parts_variance(-0.1, _band(-0.5, 0.01, depth.BAND_Z), None, None) == pytest.approx(0.15)
        assert _parts_variance(-0.1, _band(-0.5, 0.01, 0.9 * depth.BAND_Z), None, None) == 0.0

    def test_the_band_along_the_edges_counts_however_faint(self):
        assert _parts_variance(-0.1, None, _band(-0.5, 0.01, 0.1), None) == pytest.approx(0.15)

    def test_the_central_patch_counts_where_it_stands_clearly_further_from_the_surface(self):
        # a box twice a pit's size: the region reads mostly the surface around it, its centre the pit
        assert _parts_variance(-0.01, None, None, _patch(-0.5, 0.0081)) == pytest.approx(0.49 ** 2 - 0.0081)
        # within PATCH_Z of its own noise of the region: chance, on a region that is all floor
        sd = 0.49 / (0.95 * depth.PATCH_Z)
        assert _parts_variance(-0.01, None, None, _patch(-0.5, sd * sd)) == 0.0
        # nearer the surface than the region: the region's own reading is the further off, and stands
        assert _parts_variance(-0.5, None, None, _patch(-0.01, 0.0001)) == 0.0
        # further off, but the region reads more than half of it: a round pit's deeper centre, not a region that
        # is mostly the surface around its defect
        assert _parts_variance(-0.3, None, None, _patch(-0.5, 0.0001)) == 0.0
        assert _parts_variance(-0.2, None, None, _patch(-0.5, 0.0001)) == pytest.approx(0.09 - 0.0001)
        # a raised defect is further from the surface too
        assert _parts_variance(0.01, None, None, _patch(0.5, 0.0081)) > 0.2

    def test_the_region_moved_counts_from_moved_from_z_in_full_from_moved_z_and_only_farther_from_the_surface(self):
        # a box a third off its pit: the region reads -0.1, the region moved back onto the pit -0.4
        moved = box_reach.MovedRegion(0.35, 180.0, -0.4, 0.01)
        assert _parts_variance(-0.1, None, None, None, moved) == pytest.approx(0.09 - 0.01)
        for z in (0.95 * depth.MOVED_FROM_Z, 1.0 * depth.MOVED_FROM_Z):
            sd = 0.3 / z
            assert _parts_variance(-0.1, None, None, None, box_reach.MovedRegion(0.35, 180.0, -0.4, sd * sd)) \
                == pytest.approx(0.0, abs=1e-12)
        # halfway between, half of what it adds
        sd = 0.3 / ((depth.MOVED_FROM_Z + depth.MOVED_Z) / 2)
        assert _parts_variance(-0.1, None, None, None, box_reach.MovedRegion(0.35, 180.0, -0.4, sd * sd)) \
            == pytest.approx(0.5 * (0.09 - sd * sd))
        # the region's own noise counts in the difference: 0.3 / sqrt(0.06), 1.2 standard deviations
        assert _parts_variance(-0.1, None, None, None, moved, 0.05) == 0.0
        # nearer the surface than the region: a box on its defect reads it deepest
        assert _parts_variance(-0.4, None, None, None, box_reach.MovedRegion(0.35, 0.0, -0.1, 0.0001)) == 0.0

    def test_of_several_parts_the_one_further_off(self):
        assert _parts_variance(-0.1, _band(-0.3, 0.0, depth.BAND_Z), _band(-0.4, 0.0, 0.1),
                                     _patch(-0.6, 0.0001)) == pytest.approx(0.25 - 0.0001)


class TestMovedShare:
    def test_none_below_moved_from_z_all_from_moved_z_in_proportion_between(self):
        assert depth.moved_share(-3.0) == depth.moved_share(depth.MOVED_FROM_Z) == 0.0
        assert depth.moved_share(depth.MOVED_Z) == depth.moved_share(9.0) == 1.0
        lo, hi = depth.MOVED_FROM_Z, depth.MOVED_Z
        assert depth.moved_share(lo + 0.25 * (hi - lo)) == pytest.approx(0.25)

    def test_it_has_no_step_a_reading_near_the_threshold_could_fall_either_side_of(self):
        z = np.linspace(0.0, 4.0, 4001)
        shares = np.array([depth.moved_share(float(x)) for x in z])
        assert np.all(np.diff(shares) >= 0) and np.max(np.diff(shares)) < 0.01


class TestWidestPart:
    def test_none_where_no_part_adds_any(self):
        assert depth._widest_part(-0.2, None, None, None) is None
        assert depth._widest_part(-0.5, None, None, _patch(-0.01, 0.0001)) is None

    def test_names_the_part_its_offset_and_what_it_adds(self):
        moved = box_reach.MovedRegion(0.35, 180.0, -0.4, 0.01)
        assert depth._widest_part(-0.1, None, None, None, moved) == depth._Part("moved", -0.4, pytest.approx(0.08))
        assert depth._widest_part(-0.1, None, _band(-0.5, 0.01, 0.1), None).kind == "along_edges"

    def test_of_several_the_one_further_off(self):
        part = depth._widest_part(-0.1, _band(-0.3, 0.0, depth.BAND_Z), _band(-0.4, 0.0, 0.1), _patch(-0.6, 0.0001))
        assert (part.kind, part.offset) == ("patch", -0.6)
        part = depth._widest_part(-0.1, _band(-0.7, 0.0, depth.BAND_Z), _band(-0.4, 0.0, 0.1), _patch(-0.6, 0.0001))
        assert part.kind == "band"


class TestUnsharedVariance:
    def test_below_the_noise_s_share_it_adds_nothing(self):
        ratio = math.exp(0.9 * depth.UNSHARED_MIN_LOG)
        assert depth.unshared_variance(-0.4, ratio) == depth.unshared_variance(-0.4, 1 / ratio) == 0.0

    def test_beyond_it_twice_the_log_ratio_of_the_offset_either_way(self):
        assert depth.unshared_variance(-0.4, math.exp(0.2)) == pytest.approx((0.4 * 0.4) ** 2)
        assert depth.unshared_variance(0.4, math.exp(-0.2)) == pytest.approx((0.4 * 0.4) ** 2)
        assert depth.unshared_variance(0.0, math.exp(0.5)) == 0.0

    def test_a_ratio_that_is_no_number_adds_nothing(self):
        assert depth.unshared_variance(-0.4, float("nan")) == 0.0

    def test_texture_in_one_eye_alone_counts_as_the_largest_share(self):
        largest = (2 * depth.UNSHARED_MAX_LOG * 0.4) ** 2
        assert depth.unshared_variance(-0.4, 0.0) == depth.unshared_variance(-0.4, math.inf) == largest
        assert depth.unshared_variance(-0.4, math.exp(5 * depth.UNSHARED_MAX_LOG)) == largest


def test_a_region_one_eye_sees_otherwise_than_the_other_is_known_less_well(monkeypatch):
    """A pit whose region the right eye sees with 0.7 of the left's contrast (as a wall's sheen does): its
    uncertainty takes in the share of the offset that may be pulled; a pit both eyes see alike keeps its own."""
    left, right, disparity = render(CALIB, 420.0, 6.0, [Pit(160, 96, 25.0, 1.5, floor=0.8)])
    blurred = cv2.blur(np.round(disparity * 4) / 4, (9, 9))
    x0, y0, x1, y1 = (int(round(c)) for c in depth.roi_box(BOX, DepthRule()))
    d = int(np.median(disparity[y0:y1, x0:x1]))
    sheen = right.astype(np.float32)
    read = sheen[y0:y1, x0 - d - 2:x1 - d + 2]
    read[:] = read.mean() + 0.7 * (read - read.mean())
    sheen = np.clip(sheen, 0, 255).astype(np.uint8)
    alike, otherwise = _surface(left, right, blurred), _surface(left, sheen, blurred)
    monkeypatch.setattr(depth, "UNSHARED_MIN_LOG", math.inf)
    assert _surface(left, right, blurred) == alike
    without = _surface(left, sheen, blurred)
    assert without.deviation_mm == otherwise.deviation_mm
    pulled = 2 * math.log(1.3) * abs(otherwise.deviation_mm)  # the ratio is 1.3 or more: 1 / 0.7 less the noise's pull
    assert otherwise.deviation_sigma_mm > without.deviation_sigma_mm + 0.5 * pulled


def test_a_groove_s_region_takes_the_eyes_rows_offset_from_the_ring_alone(monkeypatch):
    """A groove across its box at HD720 (tests/fixtures/surface_fit/README.md): fitted to the whole region, which
    holds the groove and the plate beside it, the eyes' rows offset came out a quarter of a pixel, and along the
    groove's slanted walls that read the 2.344 mm groove 0.29 mm short, six of its sigma."""
    data = np.load(ROOT / "tests" / "fixtures" / "surface_fit" / "groove_hd.npz")
    left, right = data["left"].astype(np.float32), data["right"].astype(np.float32)
    disparity = data["disparity"].astype(np.float32) / 256
    disparity[disparity == 0] = np.nan
    x0, y0 = (float(v) for v in data["origin"])
    calib = Calibration(666.7809523809524, 120.0, 639.5 - x0, 359.5 - y0, left.shape[1], left.shape[0],
                        float(data["doffs"]))
    box = tuple(float(v) for v in data["box"])

    def measured(rule=DepthRule(faint_ring_width_px=12)):  # the ring it was found with (the faint one is wider)
        return measure_defect(disparity, Detection("inclusion", 1.0, box), calib, rule, (left, right))

    for m in (measured(), measured(DepthRule())):
        assert "along a groove" in m.note
        assert abs(m.deviation_mm - 2.344) <= 2 * m.deviation_sigma_mm
    fit = surface_fit.fit_defect
    monkeypatch.setattr(surface_fit, "fit_defect", lambda start, rows_from_ring=False: fit(start))
    whole = measured()
    assert 2.344 - whole.deviation_mm > 4 * whole.deviation_sigma_mm


def test_a_narrow_pit_whose_walls_each_eye_sees_otherwise_is_not_proven_inside_its_limit(monkeypatch):
    """A 2.18 mm depression 12 x 20 px on a polished plate (tests/fixtures/surface_fit/README.md): its walls'
    sheen, which one eye sees broad and the other narrow, pulls the offset to under a third of the depth. The
    region's contrast differs between the eyes, and the uncertainty that takes that in leaves the pit undecided
    at the demo's 1 mm limit by a margin, where the fit's own (0.67 +- 0.18 mm) only just failed to prove it inside."""
    data = np.load(ROOT / "tests" / "fixtures" / "surface_fit" / "sheen_walls.npz")
    left, right = data["left"].astype(np.float32), data["right"].astype(np.float32)
    disparity = data["disparity"].astype(np.float32) / 256
    disparity[disparity == 0] = np.nan
    x0, y0 = (float(v) for v in data["origin"])
    calib = Calibration(350.06, 120.0, 335.5 - x0, 187.5 - y0, left.shape[1], left.shape[0])
    box = tuple(float(v) for v in data["box"])
    decision = load_recipe(ROOT / "recipes" / "steel_plate.yaml").recipe.decision

    def measured():
        return measure_defect(disparity, Detection("crazing", 1.0, box), calib, DepthRule(), (left, right))

    m = measured()
    assert m.deviation_mm < 0.4 * 2.183
    status, reasons = judge_defect(m, decision)
    assert status == Status.REJECT and "straddles" in reasons[0]
    monkeypatch.setattr(depth, "UNSHARED_MIN_LOG", math.inf)
    own = measured()
    assert own.deviation_mm == m.deviation_mm and own.deviation_sigma_mm < 0.65 * m.deviation_sigma_mm
    assert 2.183 - own.deviation_mm > 8 * own.deviation_sigma_mm  # a precision the pit's walls do not allow


def test_surface_method_without_the_pair_is_the_reference():
    left, right, disparity = render(CALIB, 400.0, 4.0, [Pit(160, 96, 25.0, 2.0)])
    assert measure_defect(disparity, Detection("pit", 0.9, BOX), CALIB, DepthRule()) == _measure(disparity)
    assert _surface(left, right, disparity, method="disparity") == _measure(disparity)


def test_a_region_the_right_camera_does_not_see_has_no_deviation_and_no_distance():
    left, right, disparity = render(CALIB, 400.0, 0.0)  # disparity ~105 px
    m = _surface(left, right, np.round(disparity), box=(30.0, 70.0, 70.0, 110.0))
    assert m.deviation_mm is None and "right camera does not see the region" in m.note
    # the backend's value there is its hole filling, which no image vouches for: a rule on the distance or the
    # area cannot decide on it either
    assert m.distance_mm is None and m.area_mm2 is None and m.uncertainty("distance_mm") is None


def test_surface_method_checks_the_pair_against_the_map():
    left, right, disparity = render(CALIB, 400.0)
    with pytest.raises(ValueError, match="differ"):
        measure_defect(disparity, Detection("pit", 0.9, BOX), CALIB, DepthRule(), (_grey(left)[:, 1:], _grey(right)))


def test_a_pair_that_does_not_match_at_any_surface_has_no_deviation():
    """Where the right image is not the left one's view (a plate outside the search range looks like this to
    the fit: whatever it settles on, the two patches are unrelated), the fit finds nothing to vouch for;
    the backend's map does not stand in."""
    left, right, disparity = render(CALIB, 400.0, 4.0, [Pit(160, 96, 25.0, 2.0)])
    other, _, _ = render(CALIB, 400.0, 4.0, seed=5)  # another plate's texture
    m = measure_defect(disparity, Detection("pit", 0.9, BOX), CALIB, DepthRule(), (_grey(left), _grey(other)),
                       searched=(80.0, 130.0))
    assert m.deviation_mm is None and m.deviation_sigma_mm is None and m.method == "surface"
    assert "do not match" in m.note or "did not settle" in m.note
    assert "matches the images at" not in m.note  # nowhere: no surface to point to
    good = _surface(left, right, disparity)
    assert good.deviation_mm is not None and good.note == ""


@pytest.mark.parametrize("backend_says", [
    "the range's end",  # a matcher that keeps its best within the range (torch_sgm): 84 px, 500 mm
    "nothing",  # one that leaves it unmatched (opencv_sgbm's uniqueness)
])
def test_a_plate_beyond_the_searched_range_is_named_where_it_lies(backend_says):
    """A plate at 700 mm under a recipe that searches 350-500 mm (78-126 px with a margin): the fit cannot
    start from the backend's map, and the note says where the plate is."""
    left, right, disparity = render(CALIB, 700.0, 3.0, [Pit(160, 96, 25.0, 2.0)])
    value = CALIB.focal_px * CALIB.baseline_mm / 500.0 if backend_says == "the range's end" else np.nan
    backend = np.full_like(disparity, value)
    pair = (_grey(left), _grey(right))
    m = measure_defect(backend, Detection("pit", 0.9, BOX), CALIB, DepthRule(), pair, searched=(78.0, 126.0))
    assert m.deviation_mm is None
    assert m.note.endswith("; the surface around the box matches the images at 60 px of disparity (700 mm), outside "
                           "the 78-126 px the stereo search covers: the plate lies outside the working distance"), m.note
    # the map's 500 mm is no distance to decide on either: a rule on it is an ERROR, not a PASS
    assert m.distance_mm is None and m.distance_sigma_mm is None and m.area_mm2 is None
    assert m.surface_elsewhere_mm == pytest.approx(700.0, abs=12)  # whole pixels of disparity
    # a search range that held it: the fit's own reasons alone
    held = measure_defect(backend, Detection("pit", 0.9, BOX), CALIB, DepthRule(), pair, searched=(40.0, 126.0))
    assert "matches the images at" not in held.note and held.surface_elsewhere_mm is None


def test_a_fit_that_settles_outside_the_searched_range_is_no_measurement():
    """The search range is where the recipe says the plate is: a surface fitted beyond it is a texture matched
    at another shift (a faint plate's ring near the left edge, fitted from the backend's hole filling at 831 mm
    on a plate at 437 mm, read a 0.79 mm scratch as a 221 mm bump). Here the backend's map is right and the fit
    settles at the plate's 105 px, which a range of 40-90 px does not hold."""
    left, right, disparity = render(CALIB, 400.0, 3.0, [Pit(160, 96, 25.0, 2.0)])
    pair = (_grey(left), _grey(right))
    m = measure_defect(disparity, Detection("pit", 0.9, BOX), CALIB, DepthRule(), pair, searched=(40.0, 90.0))
    assert m.deviation_mm is None and m.deviation_sigma_mm is None and m.method == "surface"
    assert m.note.startswith("deviation unavailable: the surface fit put the surface around the box at 105 px of "
                             "disparity (400 mm), outside the 40-90 px the stereo search covers (the working "
                             "distance)"), m.note
    # and where the images put the plate, which the scan of the ring finds at the same place
    assert "matches the images at 105 px" in m.note and m.distance_mm is None
    # a range that holds it: measured as without one
    held = measure_defect(disparity, Detection("pit", 0.9, BOX), CALIB, DepthRule(), pair, searched=(78.0, 126.0))
    assert held == _surface(left, right, disparity) and held.deviation_mm > 1.0 and held.note == ""


@pytest.mark.parametrize("rows", [3, -2])
def test_eyes_whose_rows_lie_further_apart_than_rectification_leaves_them_are_named(rows):
    """A calibration file that is not the camera's leaves the right eye's rows whole pixels off the left's. The
    fit measures that offset (``e``) to a few hundredths of a pixel, but the model is one of a rectified pair:
    beyond ``rectified_within_px`` no deviation, and the note and ``rows_apart_px`` say by how much."""
    left, right, disparity = render(CALIB, 400.0, 3.0, [Pit(160, 96, 25.0, 2.0)])
    m = _surface(left, np.roll(right, rows, axis=0), disparity)
    assert m.deviation_mm is None and m.deviation_sigma_mm is None and m.method == "surface"
    assert m.rows_apart_px == pytest.approx(rows, abs=0.05)
    assert f"the right eye's rows lie {rows:+.1f} px from the left eye's around the box, where a rectified camera " \
           f"leaves them within 1.5 px" in m.note, m.note
    # a row apart: within what rectification leaves, measured as the pair without it (the fit models the offset)
    one = _surface(left, np.roll(right, 1, axis=0), disparity)
    assert one.rows_apart_px is None and one.deviation_mm == pytest.approx(_surface(left, right, disparity).deviation_mm,
                                                                           abs=0.1)


@pytest.mark.parametrize("width, within", [(320, 1.5), (672, 1.5), (1280, 1.5 * 1280 / 672), (2208, 1.5 * 2208 / 672)])
def test_the_rows_a_rectified_camera_leaves_apart_grow_with_its_resolution(width, within):
    # a calibration's error is an angle: at 2K the same camera's rows lie 3.3 times as many pixels apart as at WVGA
    from core.depth import rectified_within_px

    assert rectified_within_px(width) == pytest.approx(within)


def test_a_plate_beyond_the_search_near_the_left_edge_is_named_too():
    """Near the left edge the backend's wrong 500 mm puts the region out of the right camera's view (at 84 px
    of disparity; the plate's 60 px would show it): that is said, and so is where the images put the plate,
    and the map's distance goes with it."""
    left, right, _ = render(CALIB, 700.0, 3.0, [Pit(80, 90, 10.0, 2.0)])
    backend = np.full((CALIB.height, CALIB.width), CALIB.focal_px * CALIB.baseline_mm / 500.0, np.float32)
    m = measure_defect(backend, Detection("pit", 0.9, (60.0, 70.0, 100.0, 110.0)), CALIB, DepthRule(),
                       (_grey(left), _grey(right)), searched=(78.0, 126.0))
    assert m.note.startswith("deviation unavailable: the right camera does not see the region (21% of it in its "
                             "view); the surface around the box matches the images at 60 px of disparity (700 mm)"), m.note
    assert m.distance_mm is None and m.surface_elsewhere_mm == pytest.approx(700.0, abs=12)


def test_a_camera_delivering_its_eyes_swapped_is_named():
    """The left image is the right eye's (a camera wired or configured the other way round): nothing matches
    at a positive disparity, and the note says the images match with the eyes exchanged."""
    left, right, disparity = render(CALIB, 400.0, 3.0, [Pit(160, 96, 25.0, 2.0)])
    backend = np.full_like(disparity, np.nan)  # what a matcher leaves of such a pair: nothing it vouches for
    m = measure_defect(backend, Detection("pit", 0.9, BOX), CALIB, DepthRule(), (_grey(right), _grey(left)),
                       searched=(78.0, 126.0))
    assert m.deviation_mm is None and m.distance_mm is None and m.eyes_swapped
    assert "matches the images only with the left and right images swapped, at 105 px of disparity (within the " \
           "78-126 px the stereo search covers)" in m.note, m.note
    # the eyes as they should be: nothing of the kind
    good = _surface(left, right, disparity)
    assert good.deviation_mm is not None and not good.eyes_swapped
    # swapped, but the plate's disparity outside the search: no claim (a chance peak is no evidence)
    far = measure_defect(backend, Detection("pit", 0.9, BOX), CALIB, DepthRule(), (_grey(right), _grey(left)),
                         searched=(20.0, 60.0))
    assert not far.eyes_swapped and "swapped" not in far.note


def test_the_backends_map_alone_says_so_too_where_the_plate_lies_outside_the_search():
    """``method: disparity`` decides on the map, which keeps a plate beyond the range at the range's end: flat,
    so the 2 mm pit reads 0 ± its resolution, proven inside any limit wider than twice that. With the search
    range given, the images say where the plate is."""
    left, right, _ = render(CALIB, 700.0, 3.0, [Pit(160, 96, 25.0, 2.0)])
    at_range_end = np.full((CALIB.height, CALIB.width), CALIB.focal_px * CALIB.baseline_mm / 500.0, np.float32)
    pair, rule = (_grey(left), _grey(right)), DepthRule(method="disparity")
    blind = measure_defect(at_range_end, Detection("pit", 0.9, BOX), CALIB, rule, pair)
    assert blind.deviation_mm == pytest.approx(0.0, abs=0.01)  # what it decided on before
    m = measure_defect(at_range_end, Detection("pit", 0.9, BOX), CALIB, rule, pair, searched=(78.0, 126.0))
    assert m.deviation_mm is None and m.deviation_sigma_mm is None and m.distance_mm is None
    assert m.note.startswith("deviation unavailable: the surface around the box matches the images at 60 px"), m.note
    # inside the range the map alone is measured as before
    left, right, disparity = render(CALIB, 400.0, 3.0, [Pit(160, 96, 25.0, 2.0)])
    inside = measure_defect(disparity, Detection("pit", 0.9, BOX), CALIB, rule, (_grey(left), _grey(right)),
                            searched=(78.0, 126.0))
    assert inside == measure_defect(disparity, Detection("pit", 0.9, BOX), CALIB, rule)


def test_a_region_with_no_interior_has_no_deviation():
    """A box so small that its inner region has no pixel a pixel inside its border: nothing of its own to
    measure, so no deviation (and no infinite uncertainty in the store or on the page)."""
    left, right, disparity = render(CALIB, 420.0, 4.0, [Pit(160, 96, 3.0, 1.5)])
    m = _surface(left, right, disparity, box=(158.0, 94.0, 162.0, 98.0))
    assert m.deviation_mm is None and m.deviation_sigma_mm is None and "no interior" in m.note
    assert m.distance_mm is not None


def test_a_recipes_plane_tolerance_counts_in_the_matchers_pixels():
    """At stereo.scale 0.25 the matcher knows its disparity to about 4 of the frame's pixels: the tolerance
    that sorts the ring's pixels onto the surface or off it is 4 of them, not 1 (crops and the whole frame
    then keep the same ring pixels)."""
    demo = load_recipe(ROOT / "recipes" / "steel_plate.yaml")
    assert demo.recipe.stereo.scale == 0.25
    assert DepthRule.from_recipe(demo.recipe).plane_tolerance_px == pytest.approx(4.0)
    full = load_recipe(ROOT / "recipes" / "steel_plate.yaml", overrides=["stereo.scale=1", "depth.plane_tolerance_px=1.5"])
    assert DepthRule.from_recipe(full.recipe).plane_tolerance_px == pytest.approx(1.5)
    assert DepthRule.from_recipe(demo.recipe, method="disparity").method == "disparity"


def test_a_band_that_reads_nearer_the_surface_than_the_region_is_not_taken(monkeypatch):
    """Measuring along a groove may only find a defect deeper than its region reads it: a band of cells nearer the
    surface than the region's own estimate is no groove to read instead."""
    left, right, disparity, box, truth = _groove_and_box(40.0, 6.0)
    along = _surface(left, right, disparity, box)
    assert "along a groove" in along.note
    found = depth.band_scan.central_band

    def shallow(offsets, sds, centres, centre, angles_deg=None):
        band = found(offsets, sds, centres, centre, angles_deg)
        # the same band, its cells now the ones off it: the surface beside the groove
        return dataclasses.replace(band, cells=~band.cells & np.isfinite(sds))

    monkeypatch.setattr(depth.band_scan, "central_band", shallow)
    region = _surface(left, right, disparity, box)
    assert region.note == "" and region.groove_angle_deg is None and abs(region.deviation_mm) < abs(along.deviation_mm)
    monkeypatch.setattr(depth, "GROOVE_Z", np.inf)
    monkeypatch.setattr(depth, "BAND_Z", np.inf)
    assert _surface(left, right, disparity, box).deviation_mm == region.deviation_mm
