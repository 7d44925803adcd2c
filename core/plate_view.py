"""Where a frame's images show the plate, for a frame in which the detector found nothing.

A part with a defect is measured, and a plate outside the working distance (or a camera delivering its eyes
the other way round) is told from the images around the defect (``core.depth``). A part without one had
nothing measured: a camera knocked on its mount, a recipe loaded at the wrong station or a fixture at another
height would pass every plate the detector finds nothing on, inspected where the recipe does not expect it.
Patches of the frame, each correlated with the right image at every horizontal shift (``core.surface_scan``),
show where the plate really is; only a surface seen, and seen only outside the searched disparities, says the
plate is elsewhere: texture too faint to match says nothing either way. Texture plain in both images that
matches at no shift at all says the two images do not show one scene (a damaged image, one eye's image from
another moment), and a part whose images cannot be checked is not passed either.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from core.surface_fit import high_pass, to_grey
from core.surface_scan import MIN_PEAK, correlations, distinct_best, scan_correlations, scan_surface
from core.types import Calibration

GRID = (5, 3)  # rows x columns of patches over the part of the frame the right camera sees
# a patch's rows and columns: few rows, as a plate tilted towards the camera (by 35 degrees at WVGA) moves about
# 2 px of disparity over 16 of them, which a correlation at whole pixels still finds; wide, for the pixels a
# correlation needs
PATCH_ROWS, PATCH_COLUMNS = 16, 96
MIN_SIDE_PX = 96  # a frame with fewer rows, or fewer columns right of the searched disparities, is not checked
BAND_PX = 32  # rows above and below a patch high-passed with it: beyond 3 of the high-pass's sigma
ENOUGH_PATCHES = 3  # patches matching outside the range, where none matched inside: enough to say where
TOLERANCE_PX = 1.0  # a surface this close to the searched range counts as in it (the scan's whole pixels)
# grey levels of high-passed detail, in both images, above which a patch of one scene must match: sensor noise is
# about 1, the faintest plates measured show 3-4, and each of their frames matched in most patches
TEXTURED = 3.0
MAX_ROWS_APART = 8  # rows between the eyes tried where the patches match nowhere with them together (BAND_PX above and
# below each patch hold them)


@dataclass(frozen=True)
class PlateElsewhere:
    """The plate as the images show it where the backend did not search: at ``disparity`` px (without doffs),
    ``distance_mm``; or, with ``swapped``, within the searched range but only with the eyes exchanged; or, with
    ``unmatched`` (disparity and distance NaN), nowhere: that many textured patches match at no shift."""

    disparity: float
    distance_mm: float
    swapped: bool = False
    unmatched: int = 0
    rows_apart: int = 0  # the patches match within the range only with the right eye's rows this far from the left's

    def describe(self, searched: tuple[float, float]) -> str:
        lo, hi = searched
        if self.rows_apart:
            return (f"the left and right images match within the {lo:.0f}-{hi:.0f} px the stereo search covers only with "
                    f"the right eye's rows {self.rows_apart:+d} px from the left eye's, where a rectified camera leaves "
                    f"them within a pixel or two: the camera's calibration file is not this camera's, or the camera has "
                    f"changed since it was calibrated")
        if self.unmatched:
            return (f"the left and right images match at no shift in any of {self.unmatched} textured patches: they do "
                    f"not show one scene (a damaged image, or one eye's image from another moment)")
        if self.swapped:
            return (f"the images match only with the left and right images swapped, at {self.disparity:.0f} px of "
                    f"disparity (within the {lo:.0f}-{hi:.0f} px the stereo search covers): the camera delivers its "
                    f"right eye's image as the left")
        return (f"the images show the plate at {self.disparity:.0f} px of disparity ({self.distance_mm:.0f} mm), "
                f"outside the {lo:.0f}-{hi:.0f} px the stereo search covers: the plate lies outside the working "
                f"distance")


def patch_pixels(shape: tuple[int, int], hi: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """The (u, v) pixels (every other one in both directions) of each patch of ``GRID`` over the columns
    from ``hi`` (the right camera sees a plate at the searched disparities there) to the right border, centre
    rows first; none for a frame smaller than MIN_SIDE_PX."""
    h, w = shape
    x0 = int(min(max(hi, 0.0), w / 2))
    if min(h, w - x0) < MIN_SIDE_PX:
        return []
    rows, cols = GRID
    ys = np.linspace(0, h - PATCH_ROWS, rows).round().astype(int)
    xs = np.linspace(x0, w - PATCH_COLUMNS, cols).round().astype(int)
    order = sorted(((y, x) for y in ys for x in xs), key=lambda p: abs(p[0] + PATCH_ROWS / 2 - h / 2))
    vv, uu = np.mgrid[0:PATCH_ROWS:2, 0:PATCH_COLUMNS:2]
    return [((uu + x).ravel(), (vv + y).ravel()) for y, x in order]


def plate_elsewhere(left: np.ndarray, right: np.ndarray, calib: Calibration,
                    searched: tuple[float, float]) -> PlateElsewhere | None:
    """Where the HxWx3 uint8 BGR pair shows the plate, if only outside ``searched`` (lo, hi: px of disparity
    without doffs, the backend's range) or only with its eyes swapped; None where a patch matches within the
    range, or none shows a surface at all."""
    if left.shape != right.shape or left.ndim != 3:
        raise ValueError(f"plate_elsewhere: left {left.shape} and right {right.shape} must be the same HxWx3")
    lo, hi = searched
    within = np.arange(math.floor(lo - TOLERANCE_PX), math.ceil(hi + TOLERANCE_PX) + 1)
    patches = _Patches(left, right, hi)
    # the searched shifts first, in every patch: a plate where it belongs matches there (a tilted one in some
    # patches only), and nothing else need be tried
    if any(np.max(correlations(*patch, within)) >= MIN_PEAK for patch in patches):
        return None
    # a left image that is the right eye's: its pixels match to their right, as the mirrored pair's to the left
    for patch in _Patches(left[:, ::-1], right[:, ::-1], hi):
        if np.max(correlations(*patch, within)) >= MIN_PEAK:
            found = scan_surface(*patch)  # distinctly there, not a repeating texture's echo
            if found is not None and lo - TOLERANCE_PX <= found.disparity <= hi + TOLERANCE_PX:
                return PlateElsewhere(found.disparity, _distance_mm(found.disparity, calib), swapped=True)
    outside, unmatched = [], 0
    for patch in patches:
        scores = scan_correlations(*patch)
        found = distinct_best(scores)  # a distinct match: outside the range, which matched nowhere
        if found is not None and found.disparity + calib.doffs > 0:
            outside.append(found.disparity)
            if len(outside) == ENOUGH_PATCHES:
                break
        elif found is None and _textured(*patch) and not np.max(scores, initial=-np.inf) >= MIN_PEAK:
            unmatched += 1  # no shift matches, distinct or not (a repeating texture matches at several)
    if outside:
        d = float(np.median(outside))
        return PlateElsewhere(d, _distance_mm(d, calib))
    if unmatched >= ENOUGH_PATCHES:
        rows = _rows_apart(patches, within)
        if rows is not None:
            return PlateElsewhere(math.nan, math.nan, rows_apart=rows)
        return PlateElsewhere(math.nan, math.nan, unmatched=unmatched)
    return None


def _rows_apart(patches: "_Patches", within: np.ndarray) -> int | None:
    """The whole rows (1 to MAX_ROWS_APART either way) by which the right eye's rows would have to lie from the
    left eye's for ENOUGH_PATCHES textured patches to match within the searched shifts, where none did with the
    rows together; None where no such offset is shared. A camera whose calibration file is another camera's
    looks so, where images of two moments match at no offset."""
    votes: dict[int, int] = {}
    for left, right, u, v in patches:
        if not _textured(left, right, u, v):
            continue
        best, at = MIN_PEAK, None
        for rows in range(-MAX_ROWS_APART, MAX_ROWS_APART + 1):
            keep = (v + rows >= 0) & (v + rows < right.shape[0])
            if rows == 0 or keep.sum() < keep.size // 2:
                continue
            # the right band read ``rows`` further down: the left band and the pixels cut to the rows both have
            top, bottom = max(0, -rows), right.shape[0] - max(0, rows)
            r = float(np.max(correlations(left[top:bottom], right[top + rows:bottom + rows], u[keep],
                                          v[keep] - top, within)))
            if r >= best:
                best, at = r, rows
        if at is not None:
            votes[at] = votes.get(at, 0) + 1
            if votes[at] == ENOUGH_PATCHES:
                return at
    return None


def _textured(left: np.ndarray, right: np.ndarray, u: np.ndarray, v: np.ndarray) -> bool:
    """Whether the patch's pixels hold TEXTURED grey levels of detail or more in both high-passed bands."""
    return bool(left[v, u].std() >= TEXTURED and right[v, u].std() >= TEXTURED)


def _distance_mm(disparity: float, calib: Calibration) -> float:
    """The distance of a surface at ``disparity`` px (without doffs); infinite at or beyond none (a range that
    reaches 0 px, or a negative doffs)."""
    d = disparity + calib.doffs
    return calib.focal_px * calib.baseline_mm / d if d > 0 else math.inf


class _Patches:
    """Each patch of ``patch_pixels`` of the HxWx3 pair as (left band, right band, u, v in the band): the rows
    about it of both images in grey, high-passed (the eyes' exposures and their sheen differ), made when first
    asked for and kept for the patches beside it and the next pass over them."""

    def __init__(self, left: np.ndarray, right: np.ndarray, hi: float):
        self.left, self.right = left, right
        self.pixels = patch_pixels(left.shape[:2], hi)
        self.bands: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    def __iter__(self):
        for u, v in self.pixels:
            rows = max(0, int(v.min()) - BAND_PX), min(self.left.shape[0], int(v.max()) + BAND_PX + 1)
            if rows not in self.bands:
                top, bottom = rows
                self.bands[rows] = (high_pass(to_grey(self.left[top:bottom])),
                                    high_pass(to_grey(self.right[top:bottom])))
            yield *self.bands[rows], u, v - rows[0]
