"""Can the camera resolve a rule's limit at the recipe's working distance? (``inspect validate``)

A deviation measured at distance Z has a standard uncertainty of about ``Z^2 / (f * B) * s`` with
``s`` the disparity uncertainty the surface fit reaches (``depth.planning_sigma_px``). A rule on
``deviation_mm`` or ``distance_mm`` is resolved when its guard band (``decision.coverage_factor``
times that) is at most half the limit: then a defect half again as deep as the limit is proven out
and one half as deep is proven in. Otherwise the warning says what would resolve it: a closer
distance, a resolution with a longer focal length (HD720 doubles the ZED's WVGA focal length), or a
longer baseline.
"""
from __future__ import annotations

import math

from core.recipe.loader import LoadedRecipe
from core.types import Calibration

RESOLVED_SHARE = 0.5  # the guard band may take at most this share of the limit
DEPTH_QUANTITIES = ("deviation_mm", "distance_mm")


def far_distance_mm(loaded: LoadedRecipe, calib: Calibration) -> tuple[float, str] | None:
    """The farthest distance the recipe inspects at and where it comes from; None if unbounded."""
    stereo = loaded.recipe.stereo
    if stereo.working_distance_mm is not None:
        return float(stereo.working_distance_mm[1]), "the far end of stereo.working_distance_mm"
    low = (stereo.min_disparity or 0.0) + calib.doffs
    if low <= 0:
        return None
    return calib.focal_px * calib.baseline_mm / low, "stereo.min_disparity"


def depth_uncertainty_mm(z_mm: float, calib: Calibration, sigma_px: float) -> float:
    return z_mm**2 / (calib.focal_px * calib.baseline_mm) * sigma_px


def resolution_warnings(loaded: LoadedRecipe, calib: Calibration) -> list[str]:
    """One line per rule whose limit the working distance cannot resolve (``file:line: key: warning: ...``)."""
    recipe = loaded.recipe
    far = far_distance_mm(loaded, calib)
    if far is None:
        return []
    z, source = far
    k = recipe.decision.coverage_factor
    s = recipe.depth.planning_sigma_px
    fb = calib.focal_px * calib.baseline_mm
    warnings = []
    for index, rule in enumerate(recipe.decision.rules):
        if rule.quantity not in DEPTH_QUANTITIES or rule.threshold == 0 or k == 0:
            continue
        limit = abs(rule.threshold) if rule.quantity == "deviation_mm" else abs(rule.threshold - z)
        if limit == 0:
            continue
        sigma = depth_uncertainty_mm(z, calib, s)
        band = k * sigma
        allowed = RESOLVED_SHARE * limit
        if band <= allowed:
            continue
        closer = math.sqrt(allowed * fb / (k * s))
        focal = k * s * z * z / (allowed * calib.baseline_mm)
        baseline = k * s * z * z / (allowed * calib.focal_px)
        key = ("decision", "rules", index)
        warnings.append(
            f"{loaded.where(key)}: decision.rules.{index}: warning: rule '{rule.describe()}': at {z:.0f} mm ({source}) "
            f"{rule.quantity} is known to ±{band:.2f} mm ({k:g} x {sigma:.2f} mm, {s:g} px of disparity), more than half its "
            f"{limit:g} mm limit; resolved at {closer:.0f} mm or closer, with a {focal / calib.focal_px:.1f}x longer focal "
            f"length ({focal:.0f} px; HD720 doubles WVGA's) or a {baseline:.0f} mm baseline")
    return warnings
