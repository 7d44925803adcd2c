"""A groove or scratch that crosses its box: the band of the region's cells that stands off from the rest.

A detector's box is upright; a groove turned on the part runs across it, from corner to corner, and most
of the region measured as the defect is then the surface beside it. Each of the region's small cells
(``surface_fit.cell_offsets``) reads either the groove or the surface, too noisily to tell one alone, but
the cells along the groove, summed, do: a straight groove passes through the centre of the box around it,
so every band through the region's centre is tried, at every angle and a few widths, and the one whose
cells stand off the rest the most is the groove's candidate. Where the cells are too noisy for that, the
left image may still show which way the groove runs: its two walls are the region's strongest edges, all
one way (``edge_direction``), and the bands along them alone are worth a look. A box larger than its
defect holds the surface all round it, and its central part alone reads the defect (``central_patch``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core import band_scan_numba, surface_fit

ANGLE_STEP_DEG = 7.5
# from the one 4 px cell on the line to six cells: the evaluation sets' grooves are 5-33 px wide
HALF_WIDTHS_PX = (2.0, 4.0, 8.0, 12.0)
SHIFTS_PX = (-4.0, 0.0, 4.0)  # from the region's centre, a cell either way: the box's rounding and a groove's bend
MIN_CELLS = 6  # in the band and outside it: fewer are a glint or a corner, not a groove and its surface
REST_SDS = 3.0  # how far the rest may lie on the other side of the surface from the band, in its standard errors
# a region whose edges run one way: most of its gradient across one direction, and more of it, pixel for pixel,
# than the surface around the box has across the same direction (a texture's streaks run through both)
EDGE_COHERENCE = 0.5
EDGE_CONTRAST = 3.0
# the bands looked for about the edges' direction: the texture's own edges pull it by up to ten degrees
EDGE_ANGLES_DEG = tuple(np.arange(-15.0, 15.1, 2.5))
# the central part of a region: within this share of its half-widths of its centre, the defect in a box twice
# its size; fewer cells than PATCH_MIN_CELLS there read a glint as much as a floor
PATCH_SHARE = 0.5
PATCH_MIN_CELLS = 3


@dataclass(frozen=True)
class Band:
    """The band of cells that stands off the rest the most: its angle (degrees from the image's rows),
    half-width and shift from the region's centre (px), its cells (K,) bool, its and the rest's weighted
    mean offsets (px), the variance of its mean (px^2, the cells' scatter about the fit included where it
    exceeds their noise), and ``z``, how many standard deviations the band stands beyond a bowl and a plane
    fitted with it to all the cells."""

    angle_deg: float
    half_width_px: float
    shift_px: float
    cells: np.ndarray
    offset: float
    rest: float
    variance: float
    z: float


@dataclass(frozen=True)
class EdgeDirection:
    """Which way a region's edges run: ``angle_deg`` (degrees from the image's rows, as ``Band``'s), ``coherence``
    (0: every way alike, 1: every gradient across that way) and ``contrast`` (the region's gradient energy across
    that way per pixel, over the surface's around the box)."""

    angle_deg: float
    coherence: float
    contrast: float

    @property
    def oriented(self) -> bool:
        """Edges all one way and stronger than the surface's: a groove's walls, not a texture's streaks."""
        return self.coherence >= EDGE_COHERENCE and self.contrast >= EDGE_CONTRAST


def edge_direction(image: np.ndarray, region: tuple[np.ndarray, np.ndarray], ring: tuple[np.ndarray, np.ndarray]
                   ) -> EdgeDirection:
    """The direction of the region's edges from its structure tensor (the mean outer product of the image's
    gradient over its pixels), and how much stronger they are than the ring's across it.

    image: HxW float (the high-passed left window); region, ring: (u, v) integer pixel coordinates in it, 1-D
    arrays of equal length, not empty."""
    if image.ndim != 2:
        raise ValueError(f"edge_direction: image must be HxW, got {image.shape}")
    for name, (u, v) in (("region", region), ("ring", ring)):
        if u.shape != v.shape or u.ndim != 1 or u.size == 0:
            raise ValueError(f"edge_direction: {name} must be two non-empty 1-D arrays of equal length, got "
                             f"{u.shape} and {v.shape}")
    # the gradients of the part of the image the pixels lie in, a pixel around it for the central differences
    x0 = max(int(min(region[0].min(), ring[0].min())) - 1, 0)
    y0 = max(int(min(region[1].min(), ring[1].min())) - 1, 0)
    part = image[y0:int(max(region[1].max(), ring[1].max())) + 2, x0:int(max(region[0].max(), ring[0].max())) + 2]
    part = part.astype(np.float64)
    gx, gy = surface_fit.gradient_x(part), surface_fit.gradient_y(part)

    def tensor(u: np.ndarray, v: np.ndarray) -> np.ndarray:  # mean gx^2, gx gy, gy^2
        a, b = gx[v - y0, u - x0], gy[v - y0, u - x0]
        return np.array([np.mean(a * a), np.mean(a * b), np.mean(b * b)])

    inside, around = tensor(*region), tensor(*ring)
    across = 0.5 * np.arctan2(2 * inside[1], inside[0] - inside[2])  # the gradients' own direction
    coherence = np.hypot(inside[0] - inside[2], 2 * inside[1]) / max(inside[0] + inside[2], 1e-300)
    c, s = np.cos(across), np.sin(across)

    def energy(j: np.ndarray) -> float:
        return float(c * c * j[0] + 2 * c * s * j[1] + s * s * j[2])

    return EdgeDirection(float((np.rad2deg(across) + 90.0) % 180.0), float(coherence),
                         energy(inside) / max(energy(around), 1e-300))


def central_band(offsets: np.ndarray, sds: np.ndarray, centres: np.ndarray, centre: tuple[float, float],
                 angles_deg: np.ndarray | None = None) -> Band | None:
    """Of the straight bands through ``centre`` (every ANGLE_STEP_DEG, HALF_WIDTHS_PX wide, SHIFTS_PX off it)
    with MIN_CELLS cells or more both in and out, the one that stands furthest, in standard deviations, beyond
    the rest and a bowl and a plane fitted with it, away from 0 (the surface around the box): a groove reads
    farther from the surface than the surface beside it, where a glint or a wall may read anything, a round pit
    is as deep along every line through its centre, and a region across a pit's wall slopes. None without one.

    offsets, sds: (K,) the cells' offsets from the ring's plane and their standard deviations (px; cells
    with sd inf or 0 carry nothing); centres: (K, 2) their (u, v); centre: the region's (u, v); angles_deg: the
    bands' angles (degrees from the rows) where not every ANGLE_STEP_DEG."""
    if offsets.shape != sds.shape or offsets.ndim != 1 or centres.shape != (offsets.size, 2):
        raise ValueError(f"central_band: offsets {offsets.shape} and sds {sds.shape} must be (K,), "
                         f"centres {centres.shape} (K, 2)")
    ok = np.isfinite(sds) & (sds > 0) & np.isfinite(offsets)
    if ok.sum() < 2 * MIN_CELLS:
        return None
    x, w = offsets[ok], 1.0 / sds[ok] ** 2
    du, dv = centres[ok, 0] - centre[0], centres[ok, 1] - centre[1]
    # a bowl (a round pit seen through a box about its size) is deepest along every line through its centre, and a
    # region across a pit's wall slopes: the band is weighed against both
    surface = np.stack([np.ones_like(x), surface_fit.bowl(du, dv), du, dv], axis=1)  # (K, 4)
    angles = np.deg2rad(np.arange(0.0, 180.0, ANGLE_STEP_DEG) if angles_deg is None
                        else np.asarray(angles_deg, dtype=np.float64) % 180.0)
    # weighted least squares of offset = surface + step * in_band, per band. The surface's block S of the normal
    # equations is the same for every band, so each band's step and its variance come from the Schur complement
    # of that block (band_scan_numba). Sums are einsum's own loops: a matrix product would go to the threaded BLAS,
    # whose threads keep spinning after it and slow the detector (core/depth.py, fit_plane_robust)
    ws = surface * w[:, None]  # (K, 4)
    block = np.einsum("ki,kj->ij", ws, surface)
    r0 = np.einsum("ki,k->i", ws, x)
    diagonal = np.sqrt(np.maximum(np.diag(block), 1e-300))
    normalised = np.linalg.det(block / np.outer(diagonal, diagonal))
    if abs(normalised) <= 1e-9:
        return None
    inverse = np.linalg.inv(block)
    # the band must stand beyond the rest, away from the surface, and the rest lie on the band's side of the surface
    # or on it: the surface beside a groove, or its walls (cells that matched the texture a pixel off read as a band
    # beside cells that read as far the other way)
    widths, shifts = np.array(HALF_WIDTHS_PX), np.array(SHIFTS_PX)
    best, z, m_in, m_out, variance = band_scan_numba.best_band(x, w, surface, du, dv, angles, widths, shifts, inverse,
                                                               r0, inverse @ r0, normalised, MIN_CELLS, REST_SDS)
    if best < 0:
        return None
    a, h, s = np.unravel_index(best, (len(angles), len(widths), len(shifts)))
    across = -du * np.sin(angles)[a] + dv * np.cos(angles)[a]  # as the kernel's: the sines of all the angles at once
    cells = np.zeros(offsets.size, dtype=bool)
    cells[np.flatnonzero(ok)] = np.abs(across - shifts[s]) <= widths[h]
    return Band(float(np.rad2deg(angles[a])), float(widths[h]), float(shifts[s]), cells, m_in, m_out, variance, z)


def central_patch(offsets: np.ndarray, sds: np.ndarray, areas: np.ndarray, centres: np.ndarray,
                  centre: tuple[float, float], half_widths: tuple[float, float]) -> surface_fit.RobustOffset | None:
    """The offset of the region's central part: ``surface_fit.robust_offset`` of the cells whose centres lie within
    PATCH_SHARE of the region's half-widths of its centre, each by its share of the region (the information would
    weigh a glint's or a wall's cell over the floor's), or None with fewer than PATCH_MIN_CELLS of them. What the
    region would read if the defect were only that part of it, as in a box twice the defect's size.

    offsets, sds: (K,) as in ``central_band``; areas: (K,) the cells' shares of the region
    (``surface_fit.cell_areas``); centres: (K, 2) their (u, v); centre: the region's (u, v); half_widths: its
    half-widths along u and v (px)."""
    if offsets.shape != sds.shape or offsets.shape != areas.shape or offsets.ndim != 1 \
            or centres.shape != (offsets.size, 2):
        raise ValueError(f"central_patch: offsets {offsets.shape}, sds {sds.shape} and areas {areas.shape} must be "
                         f"(K,), centres {centres.shape} (K, 2)")
    inside = ((np.abs(centres[:, 0] - centre[0]) <= PATCH_SHARE * half_widths[0])
              & (np.abs(centres[:, 1] - centre[1]) <= PATCH_SHARE * half_widths[1])
              & np.isfinite(sds) & (sds > 0) & np.isfinite(offsets) & (areas > 0))
    if inside.sum() < PATCH_MIN_CELLS:
        return None
    start = float(np.median(offsets[inside]))
    return surface_fit.robust_offset(offsets[inside], sds[inside], start, areas=areas[inside])
