"""Disparity only where depth will read it: around the detector's boxes (``stereo.region: defects``).

``core/depth.py`` reads a detection's box and a ring around it (``ring_gap_px + ring_width_px``, or
``faint_ring_width_px`` where the surface fit widens the ring).
That *needed* rectangle, grown by ``roi_margin_px`` so the matcher sees the same context as on the
full frame (its block, census and filter windows, and enough of every SGM path to settle), is
matched on a crop of both images. The crop reaches ``max_disp + SEARCH_SLACK_PX`` further to the
left: the right-image pixels a left pixel may match lie up to ``max_disp`` to its left, and a
matcher leaves the first columns of its input unmatched (OpenCV: ``minDisparity + numDisparities``,
with the width rounded up to a multiple of 16). Left and right are cropped at the same columns, so
disparities need no correction.

The returned map has the frame's full size; only the needed rectangles hold disparities, the rest is
NaN (invalid), so a box read anywhere else finds no depth rather than a wrong one.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from core.depth import DepthRule
from core.types import StereoFrame

SEARCH_SLACK_PX = 16

Rect = tuple[int, int, int, int]  # x0, y0, x1, y1; x1 and y1 exclusive


def needed_rect(box: tuple[float, float, float, float], rule: DepthRule, shape: tuple[int, int]) -> Rect:
    """The pixels ``measure_defect`` reads for this box: the box and its ring, clipped to the image."""
    h, w = shape
    grow = rule.ring_gap_px + rule.widest_ring_px
    x0, y0, x1, y1 = box
    return (max(0, math.floor(x0) - grow), max(0, math.floor(y0) - grow),
            min(w, math.ceil(x1) + grow), min(h, math.ceil(y1) + grow))


def crop_rect(needed: Rect, margin: int, max_disp: float, shape: tuple[int, int], grid: int = 1) -> Rect:
    """The columns and rows matched for a needed rectangle: grown by ``margin`` on every side and by
    the search range (``max_disp + SEARCH_SLACK_PX``) to the left, and never narrower than that range
    plus the margin. With ``grid`` > 1 its corners lie on multiples of ``grid`` (or the image's edge),
    so that a crop shrunk by 1 / ``grid`` is made of the same pixel blocks as the shrunk frame."""
    h, w = shape
    x0, y0, x1, y1 = needed
    reach = math.ceil(max_disp) + SEARCH_SLACK_PX
    cx0, cx1 = max(0, x0 - margin - reach), min(w, x1 + margin)
    # Near the left edge the crop would be narrower than the search range, which a matcher may refuse
    # (OpenCV does); widen it to the right. Those pixels have no match on the full frame either.
    narrowest = min(w, reach + max(margin, SEARCH_SLACK_PX))
    if cx1 - cx0 < narrowest:
        cx1 = min(w, cx0 + narrowest)
        cx0 = max(0, cx1 - narrowest)
    cy0, cy1 = max(0, y0 - margin), min(h, y1 + margin)
    return (cx0 // grid * grid, cy0 // grid * grid, min(w, -(-cx1 // grid) * grid), min(h, -(-cy1 // grid) * grid))


def _overlap(a: Rect, b: Rect) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def _union(a: Rect, b: Rect) -> Rect:
    return (min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3]))


def plan(boxes: Sequence[tuple[float, float, float, float]], rule: DepthRule, margin: int, max_disp: float,
         shape: tuple[int, int], grid: int = 1) -> list[tuple[Rect, list[Rect]]]:
    """Crops to match (``crop_rect``), each with the needed rectangles it serves. Crops that overlap are
    merged (a pixel is matched once), repeatedly until none overlap."""
    groups = [(crop_rect(n, margin, max_disp, shape, grid), [n]) for n in (needed_rect(b, rule, shape) for b in boxes)]
    merged = True
    while merged:
        merged = False
        for i in range(len(groups)):
            for j in range(i + 1, len(groups)):
                if _overlap(groups[i][0], groups[j][0]):
                    groups[i] = (_union(groups[i][0], groups[j][0]), groups[i][1] + groups[j][1])
                    del groups[j]
                    merged = True
                    break
            if merged:
                break
    return groups


def crop_frame(frame: StereoFrame, rect: Rect) -> StereoFrame:
    """Both images cut at the same rows and columns. The calibration is the frame's (crops are read
    only for disparities, which a common crop leaves unchanged)."""
    x0, y0, x1, y1 = rect
    return StereoFrame(frame.frame_id, frame.index, frame.left[y0:y1, x0:x1], frame.right[y0:y1, x0:x1],
                       frame.calib, frame.timestamp, frame.source, frame.meta)


def disparity_around(match: Callable[[StereoFrame], np.ndarray], frame: StereoFrame,
                     boxes: Sequence[tuple[float, float, float, float]], rule: DepthRule, margin: int,
                     max_disp: float, scale: float = 1.0) -> np.ndarray:
    """Full-size HxW float32 disparity, NaN except in the needed rectangles of ``boxes``.

    ``match(frame)`` is the full-frame computation (``core.engine.compute_disparity`` with its range and
    scale bound), here called on crops; where it shrinks the pair by a whole factor (``scale`` 1/2,
    1/4, ...) the crops lie on that factor's grid."""
    shape = frame.left.shape[:2]
    out = np.full(shape, np.nan, dtype=np.float32)
    factor = round(1.0 / scale)
    grid = factor if abs(factor * scale - 1.0) < 1e-6 else 1
    for crop, needed in plan(boxes, rule, margin, max_disp, shape, grid):
        disparity = match(crop_frame(frame, crop))
        for x0, y0, x1, y1 in needed:
            out[y0:y1, x0:x1] = disparity[y0 - crop[1]: y1 - crop[1], x0 - crop[0]: x1 - crop[0]]
    return out
