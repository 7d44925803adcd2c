"""Whether a rectified pair's calibration can be a camera's: the bounds every reader of one applies.

A calibration is read from a sequence's ``calib.yaml``, a ZED's ``SN<serial>.conf`` or a camera plugin,
and one that no camera has does not fail loudly later: a principal point far outside the image makes
the surface's normal all but parallel to the image plane and every deviation about 0 mm (every plate
passes), and a baseline given in metres makes every plate lie outside the searched distances. This
module imports nothing from the rest of stereo-inspect, so it can be tried alone.
"""
from __future__ import annotations

import math
import numbers

# The horizontal field of view of a rectified pinhole camera lies between these: a narrower one is a
# telescope, a wider one is no longer a pinhole picture (a fisheye is rectified to less).
FIELD_OF_VIEW_DEG = (0.25, 170.0)
BASELINE_MM = (1.0, 10_000.0)  # under 1 mm: metres written for millimetres, more likely than such a camera


def _finite(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)


def calibration_problem(focal_px, baseline_mm, cx, cy, width, height, doffs=0.0) -> str | None:
    """What makes these values no camera's, in words naming the value, or None.

    focal_px: px; baseline_mm: mm; (cx, cy): the left eye's principal point, px; width, height: the
    images' size, px; doffs: the principal points' horizontal offset between the eyes, px."""
    for name, value in (("width", width), ("height", height)):
        if not (_finite(value) and value > 0 and float(value).is_integer()):
            return f"{name} must be a whole number of pixels above 0 (got {value!r})"
    for name, value in (("focal_px", focal_px), ("baseline_mm", baseline_mm), ("cx", cx), ("cy", cy),
                        ("doffs", doffs)):
        if not _finite(value):
            return f"{name} must be a finite number (got {value!r})"
    narrow, wide = FIELD_OF_VIEW_DEG
    f_low = width / (2 * math.tan(math.radians(wide) / 2))
    f_high = width / (2 * math.tan(math.radians(narrow) / 2))
    if not f_low <= focal_px <= f_high:
        return (f"focal_px {focal_px:.6g} is no camera's for a {width} px wide image: a field of view of "
                f"{narrow:g}-{wide:g} degrees is {f_low:.0f}-{f_high:.0f} px")
    low, high = BASELINE_MM
    if not low <= baseline_mm <= high:
        hint = " (metres written for millimetres?)" if 0 < baseline_mm < low else ""
        return f"baseline_mm {baseline_mm:.6g} lies outside {low:g}-{high:g} mm{hint}"
    # a rectified principal point lies in or near the image: rectification moves it by a fraction of it
    if not -width <= cx <= 2 * width:
        return f"cx {cx:.6g} lies far outside the {width} px wide image (at most one image width beyond its edges)"
    if not -height <= cy <= 2 * height:
        return f"cy {cy:.6g} lies far outside the {height} px high image (at most one image height beyond its edges)"
    if abs(doffs) >= width:
        # the principal points' offset between the eyes is a fraction of the image, never the whole of it
        return f"doffs must lie within the image's width, {width} px (got {doffs!r})"
    return None
