"""Depth per defect: distance, deviation from the surrounding surface, and their uncertainties.

Two methods (the recipe's ``depth.method``):

- ``surface`` (the default): the surrounding surface and the defect's offset from it are fitted to
  the grey levels of the rectified pair (``core.surface_fit``), starting from the backend's disparity.
  Every pixel of the ring and of the region contributes, so the deviation is good to a few hundredths
  of a disparity pixel where a per-pixel matcher is off by tenths; its uncertainty comes from the fit.
- ``disparity``: the backend's disparity map alone, the reference the first is compared against.
  Distance follows the seed: the median of the valid disparities inside the defect's region,
  ``Z = f*B / (median(d) + doffs)``; a plane is fitted robustly to the valid disparities in a ring
  around the box, and the defect's pixels are measured against it along the plane's 3D normal. Its
  uncertainty is the expected resolution ``Z^2 / (f*B) * disparity_noise_px`` (times sqrt 2 for the
  deviation, a difference of two surfaces).

Both methods share the checks that make a deviation meaningful: enough valid disparities in the
region, a ring around the box on one surface (``worst_side_of``).

Why fit in disparity space: a 3D plane seen by a rectified pinhole pair is exactly a plane in
(u, v, d), so the fit is linear. From ``a*u + b*v + c = d + doffs = f*B/Z`` it follows that
``a*f*X + b*f*Y + (a*cx + b*cy + c)*Z = f*B``, whose normal is ``n = (a*f, b*f, a*cx + b*cy + c)``.
A point seen at pixel (u, v) with disparity d lies at signed distance
``f*B*(d_plane/d - 1) / |n|`` from that plane (positive = farther from the camera = below the surface).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any, Literal

import numpy as np

from core import band_scan, box_reach, depth_numba, surface_fit, uncertainty_budget
from core.surface_scan import scan_surface
from core.types import Calibration, DefectMeasurement, Detection, StereoFrame, UncertaintyPart


@dataclass(frozen=True)
class DepthRule:
    """How a box becomes a measurement region (the recipe's ``depth`` section)."""

    # the central share of the box's width and height taken as the defect: detector boxes include the
    # defect's walls and a margin of intact surface, which would pull it towards zero (1: the whole box)
    inner_fraction: float = 0.6
    ring_gap_px: int = 3
    ring_width_px: int = 12
    # the ring's width where its texture is faint against the region's (``ring_width``; method ``surface``)
    faint_ring_width_px: int = 20
    min_valid_fraction: float = 0.10
    min_ring_points: int = 30
    # On every side of the box (top, bottom, left, right) at least this share of the ring must lie
    # on the fitted plane; otherwise the surroundings are not one surface (a plate edge, the belt)
    # and a deviation from "the" surface would be meaningless. Checked per side because a plane
    # slanted across a step can fit most of the ring while missing whole sides of it.
    min_plane_inliers: float = 0.6
    plane_tolerance_px: float = 1.0
    disparity_noise_px: float = 0.25
    method: Literal["surface", "disparity"] = "surface"

    @property
    def widest_ring_px(self) -> int:
        """The widest ring a measurement may read: ``faint_ring_width_px`` where the surface fit may widen the ring
        to it (``ring_width``), else ``ring_width_px``."""
        return max(self.ring_width_px, self.faint_ring_width_px) if self.method == "surface" else self.ring_width_px

    @classmethod
    def from_section(cls, section: Any, **changes: Any) -> DepthRule:
        """The rule of a recipe's ``depth`` section (its keys that are not measurement settings left out)."""
        values = section.model_dump() if hasattr(section, "model_dump") else dict(section)
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in {**values, **changes}.items() if k in names})

    @classmethod
    def from_recipe(cls, recipe: Any, **changes: Any) -> DepthRule:
        """The rule of a recipe: its ``depth`` section, with ``plane_tolerance_px`` counted in the matcher's
        pixels (``stereo.scale``): a matcher working at a quarter of the resolution knows its disparity to
        about a pixel of its own, 4 of the frame's, and a tolerance finer than that sorts its noise: the
        crops and the whole frame judged other ring pixels off the plane (0.05 mm apart at HD720 while the
        surface fit still left such pixels out)."""
        scale = min(1.0, float(recipe.stereo.scale))
        return cls.from_section(recipe.depth, **{"plane_tolerance_px": recipe.depth.plane_tolerance_px / scale,
                                                 **changes})


@dataclass(frozen=True)
class Plane:
    """Disparity plane ``d + doffs = a*u + b*v + c``."""

    a: float
    b: float
    c: float

    def __call__(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return self.a * u + self.b * v + self.c

    def normal_length(self, calib: Calibration) -> float:
        f = calib.focal_px
        return float(np.sqrt((self.a * f) ** 2 + (self.b * f) ** 2 + (self.a * calib.cx + self.b * calib.cy + self.c) ** 2))


def _clip_box(box: tuple[float, float, float, float], shape: tuple[int, int]) -> tuple[int, int, int, int]:
    h, w = shape
    x0, y0, x1, y1 = box
    return (
        int(np.clip(np.floor(x0), 0, w)),
        int(np.clip(np.floor(y0), 0, h)),
        int(np.clip(np.ceil(x1), 0, w)),
        int(np.clip(np.ceil(y1), 0, h)),
    )


def roi_box(box: tuple[float, float, float, float], rule: DepthRule) -> tuple[float, float, float, float]:
    """The region of ``box`` (x0, y0, x1, y1) measured as the defect: its central ``rule.inner_fraction``."""
    x0, y0, x1, y1 = box
    shrink = (1.0 - rule.inner_fraction) / 2.0
    dx, dy = (x1 - x0) * shrink, (y1 - y0) * shrink
    return (x0 + dx, y0 + dy, x1 - dx, y1 - dy)


def valid_mask(disparity: np.ndarray, doffs: float = 0.0) -> np.ndarray:
    """Usable disparities: finite and in front of the camera (zero is "no match" for many matchers)."""
    return np.isfinite(disparity) & (disparity + doffs > 0) & (disparity != 0)


def ring_mask(shape: tuple[int, int], box: tuple[float, float, float, float], gap: int, width: int) -> np.ndarray:
    """Pixels between the box grown by ``gap`` and the box grown by ``gap + width`` (HxW bool)."""
    mask = np.zeros(shape, dtype=bool)
    (x0, y0), window = _ring_window(shape, box, gap, width)
    mask[y0 : y0 + window.shape[0], x0 : x0 + window.shape[1]] = window
    return mask


def ring_pixels(shape: tuple[int, int], box: tuple[float, float, float, float], gap: int, width: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """``ring_mask``'s pixels as (u, v), 1-D, in row-major order (as ``np.nonzero`` gives them), found
    without a full-size mask: a frame's defects each cost a pass over the whole image otherwise."""
    (x0, y0), window = _ring_window(shape, box, gap, width)
    v, u = np.nonzero(window)
    return u + x0, v + y0


def _ring_window(shape, box, gap, width) -> tuple[tuple[int, int], np.ndarray]:
    """The ring's bounding rectangle's top-left corner and its mask there."""
    h, w = shape
    x0, y0, x1, y1 = _clip_box(box, shape)
    outer = (max(x0 - gap - width, 0), max(y0 - gap - width, 0), min(x1 + gap + width, w), min(y1 + gap + width, h))
    inner = (max(x0 - gap, 0), max(y0 - gap, 0), min(x1 + gap, w), min(y1 + gap, h))
    window = np.ones((max(outer[3] - outer[1], 0), max(outer[2] - outer[0], 0)), dtype=bool)
    window[inner[1] - outer[1] : inner[3] - outer[1], inner[0] - outer[0] : inner[2] - outer[0]] = False
    return (outer[0], outer[1]), window


SCORED_POINTS = 1024
# a ring with less than this share of its region's gradient energy is widened (``ring_width``): over every
# evaluation group 1.5 proved 36 more good defects and 24 more beyond the limit, and lost 7 and 15 (research log)
FAINT_RING_RATIO = 1.5
FIT_SHARE = 0.5  # of the joint fit's offset in the defect's, the cells' the rest
INTERIOR_MARGIN_PX = 1.0  # a region's interior: its pixels at least this far inside its border
WALL_PX = 0.5  # px of the defect's wall a region may hold unseen: what the evaluation sets' regions read short, median
# |ln| of a region's contrast ratio between the eyes (``surface_fit.contrast_ratio``) below which it is the noise's:
# 0.03-0.1 at the 90th percentile of the evaluation groups
UNSHARED_MIN_LOG = 0.1
UNSHARED_MAX_LOG = 1.0  # and beyond which the region is one eye's alone (0.74 at most on the evaluation groups)
# the eyes' rows at WVGA (672 columns): a ZED's factory calibration leaves a few tenths of a pixel. An error of the
# calibration is an angle, so a wider image of the same camera has its rows proportionally further apart
RECTIFIED_WITHIN_PX = 1.5
RECTIFIED_AT_WIDTH = 672


def rectified_within_px(width: int) -> float:
    """How far apart (px) the eyes' rows may lie in a rectified image ``width`` columns wide."""
    return RECTIFIED_WITHIN_PX * max(1.0, width / RECTIFIED_AT_WIDTH)
SCAN_MARGIN_PX = 32  # rows above and below the ring high-passed with it: beyond 3 of the high-pass's sigma
# A band of the region's cells standing this many standard deviations beyond the rest is the defect (a groove
# across its box); on the nine evaluation sets, whose regions lie on their defects' floors, the best band stands
# 3.1 at the 95th percentile, 4.5 at most
GROOVE_Z = 5.0
# from this many, the band may be the defect: the uncertainty widens to take it in. Chance reaches it on 6 % of
# those floors, and 2 on a third of them (docs/research-log.md: what widening from 2 cost for what it caught)
BAND_Z = 3.0
# from this many of its standard deviations off, a region's central part that reads more than twice its offset may
# be the defect in a box larger than it, and the uncertainty widens to take it in (``_widest_part``)
PATCH_Z = 2.0
# from this many standard deviations of their difference beyond the region's offset, the region moved towards where a
# box's surroundings read farther from the surface may be the defect, the box off it (``box_reach``), and the
# uncertainty widens to take it in; from MOVED_FROM_Z, by a share of that growing in proportion (``moved_share``): a
# step at MOVED_Z made a reading's uncertainty jump fourfold between copies a few hundredths of a standard deviation
# apart, and a clear-cut defect in a box a third off passed or not as the fit's last digits fell (docs/research-log.md)
MOVED_Z = 2.0
MOVED_FROM_Z = 1.5
# the pixels whose cells the moved regions read, at most: a WVGA box 80 px wide reaches 128 x 128
MOVED_MAX_PIXELS = 128 * 128


def fit_plane_robust(
    u: np.ndarray, v: np.ndarray, d: np.ndarray, tolerance: float = 1.0, trials: int = 128, seed: int = 0
) -> Plane | None:
    """Plane through (u, v, d) by RANSAC (points within ``tolerance`` px count), refined by least
    squares on its inliers. Deterministic (fixed seed). None when no plane can be defined.

    Why not a MAD-trimmed least squares: with two surfaces in the ring (a plate edge) the residuals
    are bimodal, the MAD is half the step, and every point passes as an inlier of a blended plane.
    """
    n = d.size
    if n < 3:
        return None
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, n, size=(trials, 3))
    # hypotheses are scored on a fixed sample of the points (all of them refine the winner below)
    scored = np.sort(rng.choice(n, SCORED_POINTS, replace=False)) if n > SCORED_POINTS else slice(None)
    systems = np.stack([u[picks], v[picks], np.ones((trials, 3))], axis=-1)
    solvable = np.abs(np.linalg.det(systems)) > 1e-6
    if not solvable.any():
        return None
    candidates = np.linalg.solve(systems[solvable], d[picks][solvable][..., None])[..., 0]
    # Compiled, not ``candidates @ design.T``: a matrix product goes to the multi-threaded BLAS, whose
    # threads keep spinning after it returns and slow the detector running next (docs/research-log.md).
    best = candidates[np.argmax(depth_numba.inlier_counts(candidates, u[scored], v[scored], d[scored], tolerance))]
    keep = np.abs(best[0] * u + best[1] * v + best[2] - d) <= tolerance
    coeffs = None
    for _ in range(3):
        if keep.sum() < 3:
            break
        coeffs = _least_squares_plane(u[keep], v[keep], d[keep])
        if coeffs is None:
            return None
        new_keep = np.abs(coeffs[0] * u + coeffs[1] * v + coeffs[2] - d) <= tolerance
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    if coeffs is None:
        return None
    return Plane(*map(float, coeffs))


def warm_up() -> None:
    """Load the compiled kernels of a measurement (the ring plane's consensus, the surface fit's, the moved
    regions', the band scan's) before the first part rather than during it (numba compiles each in seconds where
    its cache is empty)."""
    u = np.arange(8.0)
    fit_plane_robust(u, u % 3, u)
    surface_fit.warm_up()
    v, u = np.mgrid[2:24:4, 2:24:4]
    centres = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)
    offsets, sds = np.random.default_rng(0).normal(0.0, 0.1, u.size), np.full(u.size, 0.1)
    box_reach.moved_regions(offsets, sds, np.full(u.size, 16.0), centres, (8.0, 8.0, 16.0, 16.0), (8.0, 8.0))
    band_scan.central_band(offsets, sds, centres, (12.0, 12.0))


def _least_squares_plane(u: np.ndarray, v: np.ndarray, d: np.ndarray) -> np.ndarray | None:
    """(a, b, c) minimising sum (a*u + b*v + c - d)^2, from the 3x3 normal equations in coordinates
    centred on the points' mean (well conditioned, and nothing for the threaded BLAS).
    None when the points do not define a plane (fewer than three, or all on one line)."""
    mu, mv, md = u.mean(), v.mean(), d.mean()
    du, dv, dd = u - mu, v - mv, d - md
    suu, suv, svv = float(np.sum(du * du)), float(np.sum(du * dv)), float(np.sum(dv * dv))
    det = suu * svv - suv * suv
    if det <= 1e-9 * max(suu * svv, 1e-300):
        return None
    sud, svd = float(np.sum(du * dd)), float(np.sum(dv * dd))
    a = (sud * svv - svd * suv) / det
    b = (svd * suu - sud * suv) / det
    return np.array([a, b, md - a * mu - b * mv])


def worst_side_of(on_plane: np.ndarray, u: np.ndarray, v: np.ndarray, box: tuple[int, int, int, int]) -> tuple[str, float]:
    """How the worst side of the box's ring fits one surface (a phrase for the note) and the share of it that
    fits, from each ring pixel's verdict (``on_plane``, bool) whatever decided it. Fewer than two sides in view
    count as not fitting."""
    x0, y0, x1, y1 = box
    top, bottom = v < y0, v >= y1
    sides = {"top": top, "bottom": bottom, "left": ~top & ~bottom & (u < x0), "right": ~top & ~bottom & (u >= x1)}
    shares = {name: float(on_plane[m].mean()) for name, m in sides.items() if m.sum() >= 10}
    if len(shares) < 2:
        # A box filling the image sees its surroundings on one side only: a plane fitted to a
        # single strip is free to tilt along it. Two sides (a corner, or top and bottom) suffice.
        missing = [name for name in sides if name not in shares]
        return f"only its {next(iter(shares), 'no')} side is in view ({', '.join(missing)} outside the image)", 0.0
    name = min(shares, key=shares.get)
    return f"only {shares[name]:.0%} of its {name} side fits", shares[name]


def ring_width(left: np.ndarray, box: tuple[float, float, float, float], rule: DepthRule) -> int:
    """The ring's width (px) for ``box`` on the HxW grey ``left`` image: ``rule.widest_ring_px`` (the faint ring's,
    for ``method: surface``) where the left image's horizontal gradient energy over the ring of
    ``rule.ring_width_px`` is below ``FAINT_RING_RATIO`` times the region's, else ``rule.ring_width_px``.

    Why: the deviation is the region's disparity less the ring's plane, and each is known to
    ``sigma * sqrt(2 / sum I_x^2)`` over its pixels. Where the ring's texture is the fainter, its plane leads the
    uncertainty and more ring pays; where it is not, a wider ring only reaches further from the defect, where the
    plate may no longer be the defect's plane, and costs fit time. Decided from the image before the fit, as a
    second fit to find out costs more than the wider ring (docs/research-log.md)."""
    if left.ndim != 2:
        raise ValueError(f"ring_width: left {left.shape} must be HxW grey")
    wide = rule.widest_ring_px
    if wide == rule.ring_width_px:
        return wide
    shape = left.shape
    ring_u, ring_v = ring_pixels(shape, box, rule.ring_gap_px, rule.ring_width_px)
    x0, y0, x1, y1 = _clip_box(roi_box(box, rule), shape)
    region_v, region_u = np.mgrid[y0:y1, x0:x1]
    ring, region = (_gradient_energy(left, u.ravel(), v.ravel())
                    for u, v in ((ring_u, ring_v), (region_u, region_v)))
    return wide if ring < FAINT_RING_RATIO * region else rule.ring_width_px


def _gradient_energy(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> float:
    """Sum over the pixels (u, v) (1-D) of the squared central difference along the row (the image's edge
    repeated beyond it)."""
    last = image.shape[1] - 1
    step = (image[v, np.minimum(u + 1, last)].astype(np.float64) - image[v, np.maximum(u - 1, 0)]) / 2.0
    return float(np.dot(step, step))


def region_weights(box: tuple[float, float, float, float], clipped: tuple[int, int, int, int]
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pixels of the integer rectangle ``clipped`` with each one's area inside the float ``box``:
    (u, v, weight), 1-D. A narrow box cut to whole pixels would take in a share of the defect's walls."""
    x0, y0, x1, y1 = clipped
    vv, uu = np.mgrid[y0:y1, x0:x1]
    uu, vv = uu.ravel(), vv.ravel()
    fx0, fy0, fx1, fy1 = box
    wx = np.clip(np.minimum(uu + 1, fx1) - np.maximum(uu, fx0), 0.0, 1.0)
    wy = np.clip(np.minimum(vv + 1, fy1) - np.maximum(vv, fy0), 0.0, 1.0)
    return uu, vv, wx * wy


def measure_defect(
    disparity: np.ndarray, detection: Detection, calib: Calibration, rule: DepthRule = DepthRule(),
    pair: tuple[np.ndarray, np.ndarray] | None = None, searched: tuple[float, float] | None = None,
) -> DefectMeasurement:
    """Distance and deviation of one detection, with their standard uncertainties.

    disparity: HxW float, NaN/inf/0 = invalid. pair: the rectified (left, right) HxW float32 grey
    images (``surface_fit.to_grey``), needed by ``method: surface``; without it the backend's
    disparity alone is used (``method: disparity``). searched: the disparities (lo, hi, px) the backend
    searched; where given with the pair, a plate the images show outside them is said to be so, and not
    measured (the surface fit's measurements, which the images vouch for, are not checked again)."""
    shape = disparity.shape
    if pair is not None and (pair[0].shape != shape or pair[1].shape != shape):
        raise ValueError(f"measure_defect: images {pair[0].shape} / {pair[1].shape} and disparity {shape} differ")
    surface = rule.method == "surface" and pair is not None
    if surface:
        rule = replace(rule, ring_width_px=ring_width(pair[0], detection.box, rule))
    inner = roi_box(detection.box, rule)
    x0, y0, x1, y1 = _clip_box(inner, shape)
    region = disparity[y0:y1, x0:x1]
    total = region.size
    valid = valid_mask(region, calib.doffs)
    valid_fraction = float(valid.sum() / total) if total else 0.0
    if valid_fraction < rule.min_valid_fraction or not valid.any():  # none at all (or no region), whatever allowed
        m = DefectMeasurement(
            detection, None, None, valid_fraction, None, None,
            note=f"depth unavailable: {valid_fraction:.0%} of the region valid, {rule.min_valid_fraction:.0%} needed",
        )
        return _outside_search(m, pair, ring_pixels(shape, detection.box, rule.ring_gap_px, rule.ring_width_px),
                               calib, searched)

    fb = calib.focal_px * calib.baseline_mm
    d_defect = region[valid].astype(np.float64) + calib.doffs
    distance = fb / float(np.median(d_defect))
    resolution = distance**2 / fb * rule.disparity_noise_px
    bw, bh = detection.width, detection.height
    area = bw * bh * (distance / calib.focal_px) ** 2

    ring_all = ring_pixels(shape, detection.box, rule.ring_gap_px, rule.ring_width_px)
    d_ring = disparity[ring_all[1], ring_all[0]]
    matched = valid_mask(d_ring, calib.doffs)
    ru, rv, d_ring = ring_all[0][matched], ring_all[1][matched], d_ring[matched]
    plane = None
    if ru.size >= rule.min_ring_points:
        plane = fit_plane_robust(
            ru.astype(np.float64), rv.astype(np.float64), d_ring.astype(np.float64) + calib.doffs,
            tolerance=rule.plane_tolerance_px,
        )
    if plane is None:
        m = DefectMeasurement(
            detection, distance, None, valid_fraction, resolution, area,
            note=f"deviation unavailable: {ru.size} valid surface points around the box, {rule.min_ring_points} needed",
            distance_sigma_mm=resolution,
        )
        return _outside_search(m, pair, ring_all, calib, searched)
    on_plane = np.abs(plane(ru.astype(np.float64), rv.astype(np.float64)) - (d_ring + calib.doffs)) \
        <= rule.plane_tolerance_px
    how, share = worst_side_of(on_plane, ru, rv, _clip_box(detection.box, shape))
    # the surface fit judges the ring from the images itself (below); the backend's judgement only where
    # the ring is not in view, or for the reference
    if share < rule.min_plane_inliers and (not surface or "outside the image" in how):
        m = DefectMeasurement(
            detection, distance, None, valid_fraction, resolution, area,
            note=f"deviation unavailable: {how}" if "outside the image" in how else
            f"deviation unavailable: the surface around the box is not one plane ({how}, {rule.min_plane_inliers:.0%} needed)",
            distance_sigma_mm=resolution,
        )
        return _outside_search(m, pair, ring_all, calib, searched)
    vv, uu = np.nonzero(valid)
    d_plane = plane((uu + x0).astype(np.float64), (vv + y0).astype(np.float64))
    deviation = fb * (d_plane / d_defect - 1.0) / plane.normal_length(calib)
    reference = DefectMeasurement(detection, distance, float(np.median(deviation)), valid_fraction, resolution, area,
                                  distance_sigma_mm=resolution, deviation_sigma_mm=float(np.sqrt(2.0) * resolution))
    if not surface:
        # the map alone: nothing in it tells a plate outside the searched range, which it keeps at the range's
        # end (flat: any defect proven inside a wide enough limit), from one within it; the images do
        return _outside_search(reference, pair, ring_all, calib, searched)
    backend_agrees = np.zeros_like(matched)
    backend_agrees[matched] = on_plane
    return _surface_measurement(pair, disparity, detection, calib, rule, plane, ring_all, backend_agrees, inner,
                                (x0, y0, x1, y1), d_plane - d_defect, reference, searched)


def _in_right_view(u: np.ndarray, v: np.ndarray, plane: tuple[float, float, float]) -> np.ndarray:
    """Whether the right image holds each pixel (u, v) (1-D) on the disparity plane ``plane`` ((a, b, c), px without
    doffs): its match two columns or more inside the image's left edge."""
    return u - (plane[0] * u + plane[1] * v + plane[2]) >= 2


def _surface_measurement(pair, disparity, detection, calib, rule, plane, ring_all, backend_agrees, inner, clipped,
                         offsets, reference: DefectMeasurement, searched: tuple[float, float] | None
                         ) -> DefectMeasurement:
    """``method: surface``: the ring's plane and the defect's offset fitted to the images, from the backend's
    plane and median offset. No deviation where the fit does not settle or the images do not match at it.
    ring_all: the ring's pixels (u, v); backend_agrees: (ring pixels,) bool, those the backend matched within
    its tolerance of its plane."""
    # the whole ring goes to the fit, whose cells leave out what lies on another surface (the belt, a
    # neighbouring defect) from the images themselves. Left out where the backend put it off its plane, the ring
    # was the matcher's noise's to choose on faint texture: a crop's map and the full frame's chose otherwise
    ring_u, ring_v = ring_all
    uu, vv, weights = region_weights(inner, clipped)
    shift = (plane.a, plane.b, plane.c - calib.doffs)  # the plane of disparities without doffs
    seen = _in_right_view(uu, vv, shift)
    if np.sum(weights * seen) < 0.5 * np.sum(weights):
        # the backend's disparities there are its hole filling: no measurement of either kind, nor a distance
        # (its filling put such regions 0.6-0.9 % of Z off, 2-4 times the uncertainty it would carry); or its
        # map is wrong there, as for a plate beyond the searched range, which the images then tell
        unseen = _without_distance(_unavailable(reference, f"the right camera does not see the region "
                                                f"({np.sum(weights * seen) / np.sum(weights):.0%} of it in its view)"))
        return _outside_search(unseen, pair, ring_all, calib, searched)
    start = -float(np.median(offsets))
    left, right = pair
    ring_fit = surface_fit.fit_ring(left, right, (ring_u, ring_v), (uu, vv), shift, start, weights)
    fit = None if ring_fit is None else surface_fit.fit_defect(ring_fit)
    why = _not_vouched_for(fit, calib, searched)
    if why is not None:
        return _outside_search(_unavailable(reference, why), pair, ring_all, calib, searched)
    rows, limit = float(fit.params[surface_fit.E]), rectified_within_px(disparity.shape[1])
    if abs(rows) > limit:
        # what the fit measured holds for a rectified pair; beyond that, a defect on faint texture was read at
        # 0.01 +- 0.37 mm for a true 1.62 mm (docs/research-log.md)
        return replace(_unavailable(reference, f"the right eye's rows lie {rows:+.1f} px from the left eye's around the "
                                    f"box, where a rectified camera leaves them within {limit:.1f} px: "
                                    f"the camera's calibration file is not this camera's, or the camera has changed "
                                    f"since it was calibrated"), rows_apart_px=rows)
    # another surface is one that both the backend (beyond its tolerance) and the fit's cells reject: a
    # sheen upsets only the cells, the crop's edge only the backend's map there.
    # A side the right camera does not see (left of its view) is out of view, not off the plane: the
    # images can say nothing of it, as of a side beyond the image's border.
    in_view = _in_right_view(ring_u, ring_v, shift)
    how, share = worst_side_of((backend_agrees | (fit.ring_weights > 0.5))[in_view], ring_u[in_view],
                               ring_v[in_view], _clip_box(detection.box, disparity.shape))
    if share < rule.min_plane_inliers:
        return _unavailable(reference, f"the surface around the box is not one plane ({how} in the images, "
                            f"{rule.min_plane_inliers:.0%} needed)")
    interior = surface_fit.interior_variance(left, right, fit, (uu, vv), weights, inner, INTERIOR_MARGIN_PX,
                                             fit.images)
    if not np.isfinite(interior):
        return _unavailable(reference, f"the region ({inner[2] - inner[0]:.0f} x {inner[3] - inner[1]:.0f} px) has no "
                            f"interior with a texture of its own to measure")
    reading = _read_region(left, right, ring_fit, fit, (uu, vv), weights, inner, ring_all, interior)
    c = reading.fit.c + calib.doffs  # the surrounding surface's disparity at the region's centre
    d, var_d, budget = _region_disparity(reading, c)
    var_d, budget, part, moved = _widened(reading, c, d, var_d, budget, (left, right), (uu, vv), weights, ring_all,
                                          inner, detection, shift)
    if d <= 0 or c <= 0:
        return _unavailable(reference, "the surface fit gave no disparity in front of the camera")
    return _surface_in_mm(reading, c, d, var_d, budget, part, moved, detection, calib, reference)


def _not_vouched_for(fit: surface_fit.SurfaceFit | None, calib: Calibration, searched: tuple[float, float] | None
                     ) -> str | None:
    """Why a surface fit's reading is no measurement: it did not settle, the images do not match at it, or it settled
    outside the disparities the backend searched (``searched``); None where it is one."""
    # no fallback to the backend's map: where the images cannot be fitted, its value is not one to vouch for
    if fit is None:
        return "the surface fit did not settle"
    if not fit.matches:
        return (f"the images do not match at the fitted surface (residuals {fit.residual_sigma:.1f} grey levels "
                f"against a texture of {fit.signal_sigma:.1f}, the right eye's gain {fit.params[4]:.2f} on the surface "
                f"and {fit.params[4] + fit.params[8]:.2f} on the defect): too little texture, the plate outside the "
                f"stereo search range (working distance), or the matcher far off on the defect")
    return _settled_outside(fit, calib, searched)


@dataclass(frozen=True)
class _RegionReading:
    """The region's cells read at a fit (``_read_region``): ``fit`` the fit they were read at (a groove's refit where
    that reads it farther); each cell's offset (px), standard deviation, centre (u, v) and area; ``settled_sds``
    the standard deviations of the cells that settled, inf for the others (of the first reading: what the region's
    parts are scanned on where there is no groove); the band across the region and the band along its edges
    (``band_scan.Band`` or None); whether it is read along a groove, the cells then the band's alone; the cells'
    robust offset; the region's width (px, the band's where a groove) and its interior's variance (px^2)."""

    fit: surface_fit.SurfaceFit
    offsets_px: np.ndarray
    sds: np.ndarray
    centres: np.ndarray
    areas: np.ndarray
    settled_sds: np.ndarray
    band: band_scan.Band | None
    along_edges: band_scan.Band | None
    groove: bool
    cells: surface_fit.RobustOffset
    width: float
    interior: float


def _middle(inner: tuple[float, float, float, float]) -> tuple[float, float]:
    """The region's centre in pixel coordinates (a pixel's centre at its index)."""
    return (inner[0] + inner[2]) / 2 - 0.5, (inner[1] + inner[3]) / 2 - 0.5


def _read_region(left: np.ndarray, right: np.ndarray, ring_fit: surface_fit.RingFit, fit: surface_fit.SurfaceFit,
                 region: tuple[np.ndarray, np.ndarray], weights: np.ndarray, inner: tuple[float, float, float, float],
                 ring: tuple[np.ndarray, np.ndarray], interior: float) -> _RegionReading:
    """The region's pixels ``region`` (u, v) with their ``weights`` read cell by cell at ``fit``, and where a band of
    cells across the region reads a groove farther from the surface than the whole region does, the groove's cells
    alone, at a refit with the eyes' rows offset from ``ring_fit`` alone where that reads it farther still.
    ``interior``: the region's interior variance (px^2) at ``fit``."""
    uu, vv = region
    images = fit.images  # the high-passed window the fit read
    offsets_px, sds, centres, settled = surface_fit.cell_offsets(left, right, fit, (uu, vv), weights, images=images)
    areas = surface_fit.cell_areas((uu, vv), weights)
    # a band only of cells that settled: on a scratch's repeating lines, cells that did not swing a pixel or more off
    # together, and as a band would read a groove where there is none
    middle = _middle(inner)
    settled_sds = np.where(settled, sds, np.inf)
    band = band_scan.central_band(offsets_px, settled_sds, centres, middle)
    along_edges = _band_along_edges(images, (uu, vv), ring, offsets_px, settled_sds, centres, middle)
    # the offset searched a pixel and a half either way: a band beyond that is a glint's, not the groove's
    groove = band is not None and abs(band.z) >= GROOVE_Z and abs(band.offset - fit.delta) <= surface_fit.SEARCH_PX
    width = min(inner[2] - inner[0], inner[3] - inner[1])
    cells = surface_fit.robust_offset(offsets_px, sds, fit.delta)
    if groove:
        along = surface_fit.robust_offset(offsets_px[band.cells], sds[band.cells], fit.delta)
        # read along the groove where that lies farther from the surface than the region reads it, never nearer
        groove = abs(along.delta) > abs(cells.delta)
    if groove:
        # the region holds the groove and the surface beside it, which one offset does not model: the eyes'
        # rows offset is then the ring's alone (a 2.34 mm groove at HD720 read 2.06 +- 0.05 mm with it fitted
        # to the whole, 2.33 +- 0.05 mm with the ring's; docs/research-log.md)
        refit = surface_fit.fit_defect(ring_fit, rows_from_ring=True)
        if refit is not None and refit.matches:
            # the same cells (their centres and the band's are the pixels'), read again at the refit
            refit_offsets, refit_sds, _, _ = surface_fit.cell_offsets(left, right, refit, (uu, vv), weights,
                                                                      images=refit.images)
            on_band = surface_fit.robust_offset(refit_offsets[band.cells], refit_sds[band.cells], refit.delta)
            if abs(on_band.delta) > abs(surface_fit.robust_offset(refit_offsets, refit_sds, refit.delta).delta):
                fit, offsets_px, sds, along = refit, refit_offsets, refit_sds, on_band
                interior = surface_fit.interior_variance(left, right, fit, (uu, vv), weights, inner,
                                                         INTERIOR_MARGIN_PX, fit.images)
        offsets_px, sds, centres, areas = offsets_px[band.cells], sds[band.cells], centres[band.cells], areas[band.cells]
        width = min(width, 2 * band.half_width_px)
        cells = along
    return _RegionReading(fit, offsets_px, sds, centres, areas, settled_sds, band, along_edges, groove, cells, width,
                          interior)


def _region_disparity(reading: _RegionReading, c: float) -> tuple[float, float, list[tuple[str, str, float]]]:
    """The region's disparity (px) from ``reading`` with the surface's ``c`` at its centre, its variance (px^2) and
    that variance as the budget's terms (kind, cause, variance)."""
    cells, fit = reading.cells, reading.fit
    if np.isfinite(cells.variance):
        # The cells' Tukey mean weighs each cell by its information, the joint fit each pixel by its residual
        # with the defect's exposure free: their errors are partly their own, and their mean is nearer the
        # truth than either on nearly every group of evaluation sets (docs/research-log.md). The cells'
        # variance stays: their scatter is what shows a region holding more than one surface. A groove is
        # read on its band alone.
        offset = cells.delta if reading.groove else (1 - FIT_SHARE) * cells.delta + FIT_SHARE * fit.delta
        return c + offset, cells.variance, _cells_budget(cells)
    cov = fit.covariance
    var_d = cov[0, 0] + cov[3, 3] + 2 * cov[0, 3]
    return c + fit.delta, var_d, [("noise", NOISE_CAUSE, var_d)]


def _widened(reading: _RegionReading, c: float, d: float, var_d: float, budget: list[tuple[str, str, float]],
             pair: tuple[np.ndarray, np.ndarray], region: tuple[np.ndarray, np.ndarray], weights: np.ndarray,
             ring: tuple[np.ndarray, np.ndarray], inner: tuple[float, float, float, float], detection: Detection,
             shift: tuple[float, float, float]
             ) -> tuple[float, list[tuple[str, str, float]], _Part | None, box_reach.MovedRegion | None]:
    """The region's variance ``var_d`` (px^2, its ``budget``'s terms) widened by what the cells' noise does not hold,
    each term with its cause: the defect's wall, contrast one eye alone sees, an uneven floor, the strongly textured
    cells, a part of the region or beyond it that may be the defect, and at least the interior's. Returns (the
    variance, its budget, that part or None, the region moved within its box that reads farthest or None)."""
    fit, cells, width = reading.fit, reading.cells, reading.width
    left, right = pair
    budget = list(budget)
    # The region may hold part of a pixel of the defect's wall that the fit cannot tell from its floor
    # (the wall facing the camera is seen broad, the other foreshortened): a share of WALL_PX / w of a region
    # w pixels across, and so of the offset (docs/research-log.md).
    wall = (WALL_PX * (d - c) / max(width, 1.0)) ** 2
    var_d += wall
    budget.append(("wall", f"the defect's wall, which a region {width:.0f} px across may hold", wall))
    # and what one eye sees of the region and the other does not (the walls' sheen, a wall one eye sees broad and the
    # other edge-on) may pull the offset by that share of it: a narrow pit's walls read 0.63 +- 0.17 mm for 2.18 mm
    if not reading.groove:
        unshared = unshared_variance(d - c, surface_fit.contrast_ratio(fit, ring, region, weights))
        var_d += unshared
        budget.append(("unshared", UNSHARED_CAUSE, unshared))
    # and a floor that is not flat over the region (the box cut through a wall) widens it by how much
    uneven = surface_fit.unevenness_variance(reading.offsets_px, reading.sds, reading.centres)
    var_d += uneven
    budget.append(("uneven", UNEVEN_CAUSE, uneven))
    # and by how much its strongly textured cells (the information weighs them) disagree with its area
    if np.isfinite(cells.variance):
        weighting = surface_fit.weighting_variance(reading.offsets_px, reading.sds, reading.areas, cells.delta)
        var_d += weighting
        budget.append(("weighting", WEIGHTING_CAUSE, weighting))
    # and a part of the region that may be the defect, too faint to measure on: a band across it, along its edges,
    # or its central part (``_widest_part``)
    part = moved = None
    if not reading.groove and np.isfinite(cells.variance):
        patch = band_scan.central_patch(reading.offsets_px, reading.settled_sds, reading.areas, reading.centres,
                                        _middle(inner), ((inner[2] - inner[0]) / 2, (inner[3] - inner[1]) / 2))
        moved = _farthest_moved(left, right, fit, inner, (detection.width, detection.height), shift, cells.delta,
                                cells.variance)
        part = _widest_part(cells.delta, reading.band, reading.along_edges, patch, moved, cells.variance)
        var_d += 0.0 if part is None else part.variance
    # and it is known no better than the region would be at its interior's information per pixel (the border
    # may be the walls' edges, strong gradients that each eye sees at another place)
    # (the interior's variance comes from the same residuals as the cells': their scatter scales it alike)
    at_interior = reading.interior * min(cells.birge, 1.0)
    if at_interior > var_d:
        var_d, budget, part = at_interior, [("interior", INTERIOR_CAUSE, at_interior)], None
    return var_d, budget, part, moved


def _surface_in_mm(reading: _RegionReading, c: float, d: float, var_d: float, budget: list[tuple[str, str, float]],
                   part: _Part | None, moved: box_reach.MovedRegion | None, detection: Detection, calib: Calibration,
                   reference: DefectMeasurement) -> DefectMeasurement:
    """The measurement in millimetres: the surface's disparity ``c`` and the region's ``d`` (px, both in front of the
    camera) with the region's variance ``var_d`` (px^2) and its ``budget``, the fit's covariance for the surface's;
    ``reference`` the backend's measurement of the same box."""
    fit = reading.fit
    cov = fit.covariance
    a, b = fit.slopes
    u0, v0 = fit.centre
    n = Plane(a, b, c - a * u0 - b * v0).normal_length(calib)
    fb = calib.focal_px * calib.baseline_mm
    # deviation = fb (c / d - 1) / |n|: c from the ring, d from the defect's own pixels
    deviation = fb * (c / d - 1.0) / n
    # mm^2 of deviation per px^2: of the ring's plane at the centre, and of the region's offset
    per_ring, per_region = (fb / (d * n)) ** 2, (fb * c / (d * d * n)) ** 2
    deviation_sigma = float(np.sqrt(per_ring * cov[0, 0] + per_region * var_d))
    distance = fb / d
    if part is not None:
        budget = budget + [(part.kind, _part_cause(part, moved, (detection.width, detection.height),
                                                   lambda offset: fb * (c / (c + offset) - 1.0) / n), part.variance)]
    parts = (UncertaintyPart("surface", RING_CAUSE, float(per_ring * cov[0, 0])),) + tuple(
        UncertaintyPart(kind, cause, float(per_region * v)) for kind, cause, v in budget if v > 0)
    groove, band = reading.groove, reading.band
    return DefectMeasurement(
        detection, float(distance), float(deviation), reference.valid_fraction, reference.depth_resolution_mm,
        reference.area_mm2 * (distance / reference.distance_mm) ** 2,
        distance_sigma_mm=float(fb / d**2 * np.sqrt(var_d)), deviation_sigma_mm=deviation_sigma, method="surface",
        note=f"measured along a groove across the box, {band.angle_deg:.0f} degrees from its rows" if groove else "",
        groove_angle_deg=float(band.angle_deg) if groove else None, uncertainty_parts=parts,
    )


# what makes each term of a surface measurement's variance, as a rule that cannot decide names it
RING_CAUSE = "placing the surface around the box"
NOISE_CAUSE = "the sensor's noise over the region's texture"
UNSHARED_CAUSE = ("contrast that one eye sees in the region and the other does not: a sheen on its walls, or a wall "
                  "one eye sees edge-on")
UNEVEN_CAUSE = "a floor that is not flat over the region: the box may cut through a wall"
WEIGHTING_CAUSE = "its strongly textured cells, which read it otherwise than the rest of it"
INTERIOR_CAUSE = "the region's interior, which has little texture of its own: its border's edges may be the walls'"


def _cells_budget(cells: surface_fit.RobustOffset) -> list[tuple[str, str, float]]:
    """The cells' variance (px^2) as the budget's terms (kind, cause, variance): their noise's, and where they scatter
    more than that says (a Birge ratio above 1), the excess."""
    if cells.birge <= 1.0:
        return [("noise", NOISE_CAUSE, cells.variance)]
    noise = cells.variance / cells.birge
    return [("noise", NOISE_CAUSE, noise),
            ("scatter", f"its cells, which scatter {cells.birge:.1f} times as much as their noise says: the region may "
                        f"hold more than one surface", cells.variance - noise)]


def _part_cause(part: _Part, moved: box_reach.MovedRegion | None, size: tuple[float, float], mm) -> str:
    """What ``part`` (``_widest_part``) is, in words, with its reading: ``mm(offset px)`` the deviation (mm) of an
    offset; size: the box's (w, h), by which ``moved`` was moved."""
    reads = f"which reads {mm(part.offset):.2f} mm"
    if part.kind == "moved":
        x0, y0, _, _ = box_reach.moved_box((0.0, 0.0, 0.0, 0.0), size, moved.share, moved.angle_deg)
        return (f"the region moved {uncertainty_budget.shift_words(x0, y0)}, {reads}: the box may not hold its "
                f"defect")
    return {"band": f"a band across the region, {reads}: a groove too faint to measure along",
            "along_edges": f"a band along the region's edges, {reads}: a groove along them",
            "patch": f"the region's centre, {reads}: a box larger than its defect"}[part.kind]


def unshared_variance(offset: float, ratio: float) -> float:
    """The variance (px^2) to add to a region's ``offset`` (px) whose contrast in the left eye over the right's is
    ``ratio`` times the ring's (``surface_fit.contrast_ratio``): ``(2 |ln ratio| * offset)^2``, the share of the
    region's gradient energy that one eye sees and the other does not, as a share of the offset it may pull;
    0 where ``|ln ratio|`` is below UNSHARED_MIN_LOG (the noise's) or the ratio is not a number (neither eye sees
    texture there); ``|ln ratio|`` no more than UNSHARED_MAX_LOG, which a ratio of 0 or infinity (texture in one
    eye alone) counts as."""
    if math.isnan(ratio):
        return 0.0
    share = min(abs(math.log(ratio)), UNSHARED_MAX_LOG) if 0 < ratio < math.inf else UNSHARED_MAX_LOG
    return (2.0 * share * offset) ** 2 if share >= UNSHARED_MIN_LOG else 0.0


@dataclass(frozen=True)
class _Part:
    """The part of a region that ``_widest_part`` widens its uncertainty for: which (``band``, ``along_edges``,
    ``patch`` or ``moved``), its offset (px) and the variance it adds (px^2)."""

    kind: str
    offset: float
    variance: float


def _widest_part(region: float, band: band_scan.Band | None, along_edges: band_scan.Band | None,
                 patch: surface_fit.RobustOffset | None, moved: box_reach.MovedRegion | None = None,
                 region_variance: float = 0.0) -> _Part | None:
    """The part of a region that may be the defect while the region (its offset ``region``, px) reads mostly the
    surface beside it, with the variance (px^2) to add to the region's for it: the square of how far that part's
    offset stands from the region's, less what the part's own noise puts in it (what is left is the defect's,
    unbiased); of several, the one further off (the first of equals); None where none adds any.

    The parts: the scan's ``band`` across the region where it stands BAND_Z or more beyond the rest (a groove too
    faint to measure along); ``along_edges``, the band along the region's edges where the left image shows them all
    one way, however faint (there the image, not the cells, says where a groove runs: a 1.52 mm groove at 632 mm
    read 0.44 +- 0.14 mm and passed, its band along the walls 1.4 sigma out); and the region's central ``patch``
    where the region reads less than half its offset, as a region that is mostly the surface around the defect
    does, and it stands PATCH_Z of its standard deviations or more further off (a box twice a narrow pit's size on
    a polished plate read 0.04 +- 0.36 mm for 2.06 mm and passed; a round pit's centre in a box that fits it is
    deeper than the region, but not twice as deep); and ``moved``, the region moved about within its box's size
    (``box_reach``), where it reads farther from the surface than the region by MOVED_FROM_Z or more standard
    deviations of their difference, ``region_variance`` (px^2) the region's own, by ``moved_share`` of what it adds (a
    box half a pit's size off it read 0.03 +- 0.48 mm for 1.40 mm and passed). docs/research-log.md has what each
    threshold cost and caught."""
    # (kind, offset, its variance, the share of what it adds that counts)
    parts = [(kind, b.offset, b.variance, 1.0) for kind, b in (
        ("band", band if band is not None and abs(band.z) >= BAND_Z else None), ("along_edges", along_edges))
        if b is not None]
    if patch is not None and abs(patch.delta) > 2 * abs(region) \
            and abs(patch.delta - region) >= PATCH_Z * np.sqrt(patch.variance):
        parts.append(("patch", patch.delta, patch.variance, 1.0))
    if moved is not None:
        counted = moved_share(moved.z(region, region_variance))
        if counted > 0:
            parts.append(("moved", moved.offset, moved.variance, counted))
    added = [_Part(kind, offset, share * max(0.0, (offset - region) ** 2 - variance))
             for kind, offset, variance, share in parts]
    widest = max(added, key=lambda p: p.variance, default=None)
    return widest if widest is not None and widest.variance > 0 else None


def moved_share(z: float) -> float:
    """The share of what the region moved within its box adds to the uncertainty where it reads ``z`` standard
    deviations of their difference farther from the surface than the region: 0 below MOVED_FROM_Z, all of it from
    MOVED_Z, in proportion between."""
    return min(1.0, max(0.0, (z - MOVED_FROM_Z) / (MOVED_Z - MOVED_FROM_Z)))


def _farthest_moved(left: np.ndarray, right: np.ndarray, fit: surface_fit.SurfaceFit,
                    inner: tuple[float, float, float, float], size: tuple[float, float],
                    shift: tuple[float, float, float], region: float, region_variance: float
                    ) -> box_reach.MovedRegion | None:
    """``box_reach.farthest`` of the region ``inner`` moved about within the box's size ``size`` (w, h), its cells
    read at the fit over the pixels in the image and in the right camera's view (``shift``: the ring plane's
    disparities, as (a, b, c) without doffs); region, region_variance: the region's own offset (px) and its
    variance (px^2)."""
    h, w = left.shape
    x0, y0, x1, y1 = _clip_box(box_reach.reach(inner, size), (h, w))
    # every pixel up to MOVED_MAX_PIXELS, beyond that every stride-th one each way in cells as many times wider: the
    # same cells' count and noise as a WVGA box's, where every pixel of a 2K box's reach added a third to the frame's
    # depth time (docs/research-log.md)
    stride = max(1, math.ceil(math.sqrt((x1 - x0) * (y1 - y0) / MOVED_MAX_PIXELS)))
    cell_px = surface_fit.CELL_PX * stride
    vv, uu = np.mgrid[y0:y1:stride, x0:x1:stride]
    uu, vv = uu.ravel(), vv.ravel()
    seen = _in_right_view(uu, vv, shift)
    uu, vv = uu[seen], vv[seen]
    if uu.size == 0:
        return None
    # the fit's own high-passed window where it holds the reach with the high-pass's own margin: a window of its own
    # costs a high-pass of it
    (wx, wy), (wh, ww) = fit.images.origin, fit.images.L.shape
    inset = surface_fit.WINDOW_MARGIN_PX - 3 * surface_fit.HIGH_PASS_SIGMA
    within = wx + inset <= x0 and x1 <= wx + ww - inset and wy + inset <= y0 and y1 <= wy + wh - inset
    offsets, sds, centres, settled = surface_fit.cell_offsets(left, right, fit, (uu, vv), cell_px=cell_px,
                                                              images=fit.images if within else None)
    areas = surface_fit.cell_areas((uu, vv), cell_px=cell_px)
    return box_reach.farthest(box_reach.moved_regions(offsets, np.where(settled, sds, np.inf), areas, centres,
                                                      inner, size, region), region, region_variance)


def _band_along_edges(images: surface_fit.DefectImages, region: tuple[np.ndarray, np.ndarray],
                      ring: tuple[np.ndarray, np.ndarray], offsets: np.ndarray, sds: np.ndarray, centres: np.ndarray,
                      middle: tuple[float, float]) -> band_scan.Band | None:
    """``band_scan.central_band`` about the direction of the region's edges in the left image, where they run one
    way (``band_scan.edge_direction``), else None. region, ring: (u, v) image pixels; the rest as there."""
    x0, y0 = images.origin
    edges = band_scan.edge_direction(images.L, (region[0] - x0, region[1] - y0), (ring[0] - x0, ring[1] - y0))
    if not edges.oriented:
        return None
    return band_scan.central_band(offsets, sds, centres, middle,
                                  angles_deg=edges.angle_deg + np.array(band_scan.EDGE_ANGLES_DEG))


def _settled_outside(fit: surface_fit.SurfaceFit, calib: Calibration, searched: tuple[float, float] | None) -> str | None:
    """Why a fit's surfaces (the ring's at the region's centre, the defect's) are none to measure on where one
    lies outside ``searched`` (lo, hi: px without doffs) by more than a pixel, else None. The search range is
    where the recipe says the plate is; a fit that settles beyond it has matched a texture at another shift
    (near the left edge, starting from the backend's hole filling, a ring fitted at 831 mm on a plate at 437 mm),
    not a plate the backend missed."""
    if searched is None:
        return None
    lo, hi = searched
    for what, d in (("the surface around the box", fit.c), ("the defect", fit.c + fit.delta)):
        if not lo - 1.0 <= d <= hi + 1.0:
            at = f" ({float(calib.distance_mm(d)):.0f} mm)" if d + calib.doffs > 0 else ""
            return (f"the surface fit put {what} at {d:.0f} px of disparity{at}, outside the {lo:.0f}-{hi:.0f} px the "
                    f"stereo search covers (the working distance)")
    return None


def _outside_search(m: DefectMeasurement, pair, ring: tuple[np.ndarray, np.ndarray], calib: Calibration,
                    searched: tuple[float, float] | None) -> DefectMeasurement:
    """``m``; where the images show the surface around the box (``core.surface_scan``, every shift tried) at
    a disparity outside ``searched`` (lo, hi: the backend's search range, px without doffs), the note says
    where, and what the map gave goes (its distance, the area from it, a deviation from it): it is that of
    a plate where there is none, and no rule may decide on it."""
    u, v = ring
    if searched is None or pair is None or u.size == 0:
        return m
    left, right = pair
    top, bottom = max(0, int(v.min()) - SCAN_MARGIN_PX), min(left.shape[0], int(v.max()) + SCAN_MARGIN_PX + 1)
    left, right = surface_fit.high_pass(left[top:bottom]), surface_fit.high_pass(right[top:bottom])
    found = scan_surface(left, right, u, v - top)
    lo, hi = searched
    if found is None or found.disparity + calib.doffs <= 0:
        return _eyes_swapped(m, left, right, (u, v - top), searched)
    if lo - 1.0 <= found.disparity <= hi + 1.0:
        return m
    z = float(calib.distance_mm(found.disparity))
    clause = (f"the surface around the box matches the images at {found.disparity:.0f} px of disparity "
              f"({z:.0f} mm), outside the {lo:.0f}-{hi:.0f} px the stereo search covers: the plate lies outside "
              f"the working distance")
    return _not_where_searched(m, clause, surface_elsewhere_mm=z)


def _eyes_swapped(m: DefectMeasurement, left: np.ndarray, right: np.ndarray, ring: tuple[np.ndarray, np.ndarray],
                  searched: tuple[float, float]) -> DefectMeasurement:
    """``m``; where the surface around the box matches nowhere as the images are given but, with them mirrored
    (a left pixel's match then lies to its right: the left image is the right eye's), at a disparity the
    backend searched, the note says so and what the map gave goes. left, right: the high-passed rows the ring
    (u, v) lies in."""
    u, v = ring
    found = scan_surface(left[:, ::-1], right[:, ::-1], left.shape[1] - 1 - u, v)
    lo, hi = searched
    # within the working distance, where the plate was meant to be: what a mere chance peak would not be
    if found is None or not lo - 1.0 <= found.disparity <= hi + 1.0:
        return m
    clause = (f"the surface around the box matches the images only with the left and right images swapped, at "
              f"{found.disparity:.0f} px of disparity (within the {lo:.0f}-{hi:.0f} px the stereo search covers): the "
              f"camera delivers its right eye's image as the left")
    return _not_where_searched(m, clause, eyes_swapped=True)


def _not_where_searched(m: DefectMeasurement, clause: str, **found: Any) -> DefectMeasurement:
    """``m`` with ``clause`` (where the images show the plate) ending its note and ``found`` set, without
    what the map gave (its distance, the area from it, a deviation from it): it is that of a plate where
    there is none, and no rule may decide on it."""
    note = f"{m.note}; {clause}" if m.deviation_mm is None else f"deviation unavailable: {clause}"
    return replace(_without_distance(m), note=note, deviation_mm=None, deviation_sigma_mm=None, **found)


def _without_distance(m: DefectMeasurement) -> DefectMeasurement:
    """``m`` without what depends on its distance (the distance, the area, the depth resolution): where the
    backend's map, the only source left, is not one to vouch for."""
    return replace(m, distance_mm=None, distance_sigma_mm=None, area_mm2=None, depth_resolution_mm=None)


def _unavailable(reference: DefectMeasurement, why: str) -> DefectMeasurement:
    """No deviation from either method: the reference's distance, saying ``why``."""
    return replace(reference, deviation_mm=None, deviation_sigma_mm=None, note=f"deviation unavailable: {why}",
                   method="surface")


def measure_frame(disparity: np.ndarray, detections: list[Detection], frame: StereoFrame,
                  rule: DepthRule = DepthRule(), searched: tuple[float, float] | None = None) -> list[DefectMeasurement]:
    """``measure_defect`` for every detection of a frame (its pair converted to grey once)."""
    if not detections:
        return []
    pair = None
    if rule.method == "surface" or searched is not None:  # the images: to fit, or to say the plate is elsewhere
        pair = (surface_fit.to_grey(frame.left), surface_fit.to_grey(frame.right))
    return [measure_defect(disparity, d, frame.calib, rule, pair, searched) for d in detections]
