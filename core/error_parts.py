"""Where a measured deviation's error comes from, read from the frame's true disparity (``inspect eval depth``).

A deviation is the disparity of the defect's region against the plane of the ring around its box. With the
frame's true disparity its error splits into three parts that sum to it exactly:

- **the ring**: the measured deviation against the one that the measured region's disparity makes with the
  ring's true plane, i.e. the error of the fitted plane at the region's centre;
- **the region's estimate**: that deviation against the one of the region's true mean disparity (each pixel
  by its area in the region), i.e. what the fit read on the region other than its surface: noise, and what
  each eye sees differently there, such as a wall's sheen;
- **the region's extent**: that one against the labelled deviation, i.e. what the region holds besides the
  defect's floor: the walls, or the plate beside a box that is off its defect.

A set whose errors lie in the region's estimate calls for texture or a closer camera; in its extent, for
boxes that fit their defects; in the ring, for a plate that is one plane around them.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.depth import DepthRule, Plane, _clip_box, fit_plane_robust, region_weights, ring_pixels, roi_box
from core.types import Calibration

KNOWN_SHARE = 0.5  # of the region's area the truth must know, or its mean is no mean of the region


@dataclass(frozen=True)
class ErrorParts:
    """The parts of one deviation's error (mm, measured less true), summing to it."""

    ring_mm: float
    region_mm: float
    extent_mm: float


def true_ring_plane(true_disparity: np.ndarray, box: tuple[float, float, float, float], rule: DepthRule,
                    tolerance: float) -> Plane | None:
    """The plane of ``true_disparity`` (HxW px, NaN unknown) over the ``rule``'s ring around ``box``: the consensus
    of its known pixels within ``tolerance`` px, as the ring may cross another defect; None where they define none."""
    u, v = ring_pixels(true_disparity.shape, box, rule.ring_gap_px, rule.ring_width_px)
    d = true_disparity[v, u].astype(np.float64)
    known = np.isfinite(d) & (d > 0)
    return fit_plane_robust(u[known].astype(np.float64), v[known].astype(np.float64), d[known], tolerance=tolerance)


def error_parts(deviation_mm: float, distance_mm: float, true_deviation_mm: float, true_disparity: np.ndarray,
                calib: Calibration, box: tuple[float, float, float, float], rule: DepthRule,
                plane_tolerance_px: float) -> ErrorParts | None:
    """The parts of ``deviation_mm - true_deviation_mm`` for a defect measured in ``box`` (x0, y0, x1, y1) at
    ``distance_mm`` (the region's own distance), from the frame's ``true_disparity`` (HxW px without doffs, NaN
    unknown) and the ``rule``'s ring and region. The ring's true plane is the consensus of its known pixels within
    ``plane_tolerance_px`` (the ring may cross another defect). None where the ring has no such plane, or the
    truth knows less than ``KNOWN_SHARE`` of the region."""
    if true_disparity.ndim != 2:
        raise ValueError(f"error_parts: true_disparity {true_disparity.shape} must be HxW")
    shape = true_disparity.shape
    plane = true_ring_plane(true_disparity, box, rule, plane_tolerance_px)
    if plane is None:
        return None
    inner = roi_box(box, rule)
    uu, vv, weights = region_weights(inner, _clip_box(inner, shape))
    truth = true_disparity[vv, uu].astype(np.float64)
    seen = np.isfinite(truth) & (weights > 0)
    if weights.sum() <= 0 or weights[seen].sum() < KNOWN_SHARE * weights.sum():
        return None
    # the fit's centre: the region's, each pixel by its area
    u0, v0 = np.average(uu, weights=weights), np.average(vv, weights=weights)
    surface = Plane(plane.a, plane.b, plane.c + calib.doffs)  # with doffs, as the depth stage reads disparities
    c = float(surface(u0, v0))
    mean = float(np.average(truth[seen], weights=weights[seen])) + calib.doffs
    fb = calib.focal_px * calib.baseline_mm
    n = surface.normal_length(calib)

    def deviation(region: float) -> float:  # core.depth's: f B (c / d - 1) / |n|
        return fb * (c / region - 1.0) / n

    at_measured, at_mean = deviation(fb / distance_mm), deviation(mean)
    return ErrorParts(deviation_mm - at_measured, at_measured - at_mean, at_mean - true_deviation_mm)
