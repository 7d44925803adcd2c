"""A box that does not hold its defect: the region moved towards where the defect lies.

A detector's box may lie a third of its size off its defect and still overlap it by half (IoU 0.5, a hit in a
detector's own evaluation). Its region, the box's central part, then holds the plate beside the defect and
its wall, and reads the defect short; its ring lies on the defect on one side, which the ring's fit leaves
out as another surface where it stands out of its noise. Moved towards the defect by that share of the box,
the region reads it. So the region is moved every way by a few shares of the box, each copy read from the
cells over the box grown by as much (``surface_fit.cell_offsets``), and the copy that reads farthest from the
surface beyond the region's own reading is the candidate: the part of the surroundings that may be the defect
(``core.depth._widest_part`` widens the uncertainty to take it in). Where the box holds its defect, every
copy holds more of its walls and of the plate than the region does and reads nearer the surface.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core import box_reach_numba, surface_fit, surface_fit_numba

# how far the region is moved, as shares of the box's width and height: a box half its size off its defect
# overlaps it by a third (IoU 0.33), which a detector's evaluation counts a miss
SHARES = (0.2, 0.35, 0.5)
ANGLES_DEG = tuple(np.arange(0.0, 360.0, 22.5))
MIN_CELLS = 3  # in a moved region: fewer read a glint as much as a floor
CANDIDATES = 4  # the moved regions read robustly by each ranking (their cells' mean, their median)
COPIES = [(share, float(angle)) for share in SHARES for angle in ANGLES_DEG]  # (share, angle) of every moved region
# each copy's share and direction, from which its move is computed as moved_box computes it
COPIES_SHARE = np.array([share for share, _ in COPIES])
COPIES_COS = np.array([np.cos(np.deg2rad(angle)) for _, angle in COPIES])
COPIES_SIN = np.array([np.sin(np.deg2rad(angle)) for _, angle in COPIES])


@dataclass(frozen=True)
class MovedRegion:
    """The region moved by ``share`` of the box towards ``angle_deg`` (degrees from the image's rows, v down):
    the offset of its cells (px, ``surface_fit.robust_offset`` by area) and that offset's variance (px^2)."""

    share: float
    angle_deg: float
    offset: float
    variance: float

    def z(self, region: float, region_variance: float = 0.0) -> float:
        """How many standard deviations of the difference this reads farther from the surface than ``region`` (px)
        does, ``region_variance`` (px^2) that reading's variance."""
        return float((abs(self.offset) - abs(region)) / np.sqrt(self.variance + region_variance))


def moved_box(box: tuple[float, float, float, float], size: tuple[float, float], share: float, angle_deg: float
              ) -> tuple[float, float, float, float]:
    """``box`` (x0, y0, x1, y1) moved by ``share`` of ``size`` (the detection's width, height) towards
    ``angle_deg``."""
    a = np.deg2rad(angle_deg)
    dx, dy = share * size[0] * np.cos(a), share * size[1] * np.sin(a)
    return (box[0] + dx, box[1] + dy, box[2] + dx, box[3] + dy)


def copy_edges(box: tuple[float, float, float, float], size: tuple[float, float]) -> np.ndarray:
    """(M, 4): ``box`` (x0, y0, x1, y1) moved as each of COPIES, the same numbers ``moved_box`` gives, at once."""
    dx, dy = COPIES_SHARE * size[0] * COPIES_COS, COPIES_SHARE * size[1] * COPIES_SIN
    return np.stack([box[0] + dx, box[1] + dy, box[2] + dx, box[3] + dy], axis=1)


def reach(box: tuple[float, float, float, float], size: tuple[float, float]) -> tuple[float, float, float, float]:
    """What the region ``box`` (x0, y0, x1, y1) covers moved by every share of SHARES: grown by the largest share
    of ``size`` (the detection's width, height) on every side."""
    gx, gy = max(SHARES) * size[0], max(SHARES) * size[1]
    return (box[0] - gx, box[1] - gy, box[2] + gx, box[3] + gy)


def moved_regions(offsets: np.ndarray, sds: np.ndarray, areas: np.ndarray, centres: np.ndarray,
                  box: tuple[float, float, float, float], size: tuple[float, float], region: float = 0.0
                  ) -> list[MovedRegion]:
    """The region ``box`` (x0, y0, x1, y1) moved by each share of SHARES of ``size`` (the detection's width,
    height) towards each angle of ANGLES_DEG, each with MIN_CELLS or more usable cells inside it: the CANDIDATES
    whose cells' area-weighted mean reads farthest beyond ``region`` (px) from the surface in its standard
    deviations and the CANDIDATES whose cells' area-weighted median does, no two of them holding the same cells, each
    read as the robust offset of its cells by area (a Tukey mean for every copy was most of a defect's depth time; a
    glint's cell, which pulls a mean, is cut there).

    offsets, sds: (K,) the cells' offsets and standard deviations (px, inf where a cell has no gradient), as
    ``surface_fit.cell_offsets`` gives them over ``reach(box, size)``; areas: (K,) their areas
    (``surface_fit.cell_areas``); centres: (K, 2) their (u, v)."""
    if offsets.shape != sds.shape or offsets.shape != areas.shape or offsets.ndim != 1 \
            or centres.shape != (offsets.size, 2):
        raise ValueError(f"moved_regions: offsets {offsets.shape}, sds {sds.shape} and areas {areas.shape} must be "
                         f"(K,), centres {centres.shape} (K, 2)")
    usable = np.isfinite(sds) & (sds > 0) & np.isfinite(offsets) & (areas > 0)
    edges = copy_edges(box, size)
    # the two middle cells' mean where the area divides evenly between them, so that pits and bumps rank alike;
    # the mean's standard deviation: a scale to rank by, the reading is robust
    inside, counts, mean, median, sd = box_reach_numba.copy_readings(offsets, sds, areas, usable, centres, edges)
    enough = counts >= MIN_CELLS
    # ranked by the mean and by the median: a cell over a pit that a wall's sheen reads as a bump takes the mean of
    # the copy on the pit back to the surface (a pit half a box off read 0.60 mm for 2.13 mm and passed), and where
    # half a copy's cells lie on the pit the median may stand nearer than the robust reading does
    # each copy's cells, to tell copies holding the same apart
    held = [row.tobytes() for row in np.packbits(inside, axis=1)]
    picks: list[int] = []
    for centre in (mean, median):
        screen = np.where(enough, (np.abs(centre) - abs(region)) / np.maximum(sd, 1e-12), -np.inf)
        picks += [i for i in _distinct(screen, held) if held[i] not in {held[j] for j in picks}]
    found = []
    for i in picks:
        keep = inside[i]
        read = surface_fit.robust_offset(offsets[keep], sds[keep], surface_fit_numba.median(offsets[keep]),
                                         areas=areas[keep])
        if np.isfinite(read.variance) and read.variance > 0:
            found.append(MovedRegion(COPIES[i][0], COPIES[i][1], read.delta, read.variance))
    return found


def _distinct(screen: np.ndarray, held: list[bytes]) -> list[int]:
    """The CANDIDATES copies of highest ``screen`` (M,), -inf for none, whose cells (``held``, one key per copy) are
    not those of a copy ranked before them: a small box's copies moved a few pixels often hold the same cells, which
    read once each would fill every candidate's place and leave the copy on the defect unread."""
    chosen: list[int] = []
    for i in np.argsort(-screen):
        if len(chosen) == CANDIDATES or not np.isfinite(screen[i]):
            break
        if held[i] not in {held[j] for j in chosen}:
            chosen.append(int(i))
    return chosen


def farthest(moved: list[MovedRegion], region: float, region_variance: float = 0.0) -> MovedRegion | None:
    """Of ``moved``, the one that stands farthest beyond the region's offset ``region`` (px) from the surface, in
    standard deviations of their difference (``MovedRegion.z``, ``region_variance`` the region's, px^2); None where
    there is none."""
    return max(moved, key=lambda m: m.z(region, region_variance), default=None)

