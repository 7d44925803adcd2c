"""Where the surface around a box matches, searched over every disparity: what to tell the operator when
a defect could not be measured.

The stereo backend searches only the recipe's working distance; a plate outside it (a part of another
thickness, a camera knocked on its mount) leaves the backend's map meaningless there, and the surface fit
without a start. The ring's pixels, correlated with the right image at every horizontal shift, show where
the plate really is, so that a part's note can say so instead of only that the fit did not settle.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MIN_PEAK = 0.4  # zero-mean normalised correlation of the best shift; 0.5-0.95 on the evaluation sets
MIN_CONTRAST = 2.0  # ... and this many times the best shift more than 2 px from it (0.1-0.36 there)
MIN_OVERLAP = 0.5  # a shift is scored where at least this share of the ring lies in the right image
MAX_PIXELS = 1024  # every k-th pixel of a larger ring: as many tell the correlation, at a quarter of the time of 4096


@dataclass(frozen=True)
class SurfaceMatch:
    """The shift (image disparity, px, without doffs) at which the ring's pixels match best, and its
    correlation."""

    disparity: float
    correlation: float


def scan_surface(left: np.ndarray, right: np.ndarray, u: np.ndarray, v: np.ndarray,
                 max_disparity: int | None = None) -> SurfaceMatch | None:
    """The whole-pixel disparity at which the pixels (u, v) of ``left`` best match ``right``, as one
    fronto-parallel surface, by zero-mean normalised correlation over 0 <= d < max_disparity (half the
    image's width if not given); None without a distinct best (a correlation below MIN_PEAK, or less than
    MIN_CONTRAST times that of any shift 3 px or more away from it).

    left, right: HxW float images (high-passed grey: the eyes' exposures may differ). u, v: (N,) integer
    pixel coordinates, inside the image."""
    return distinct_best(scan_correlations(left, right, u, v, max_disparity))


def scan_correlations(left: np.ndarray, right: np.ndarray, u: np.ndarray, v: np.ndarray,
                      max_disparity: int | None = None) -> np.ndarray:
    """``scan_surface``'s (D,) correlations, one per whole-pixel disparity 0 <= d < D; (0,) without pixels."""
    if left.shape != right.shape or left.ndim != 2:
        raise ValueError(f"scan_surface: left {left.shape} and right {right.shape} must be the same HxW")
    if u.shape != v.shape or u.ndim != 1:
        raise ValueError(f"scan_surface: u {u.shape} and v {v.shape} must be the same (N,)")
    if u.size == 0:
        return np.zeros(0, np.float32)
    step = -(-u.size // MAX_PIXELS)  # a few thousand pixels tell a correlation; the (D, N) arrays stay small
    u, v = u[::step], v[::step]
    w = left.shape[1]
    top = w // 2 if max_disparity is None else min(int(max_disparity), w)
    return correlations(left, right, u, v, np.arange(top))


def distinct_best(r: np.ndarray) -> SurfaceMatch | None:
    """The disparity of the (D,) correlations ``r`` (index = disparity) that stands out, as ``scan_surface``
    says; None without one."""
    if r.size == 0:
        return None
    best = int(np.argmax(r))
    peak = float(r[best])
    away = np.abs(np.arange(r.size) - best) > 2
    second = float(np.max(r[away], initial=-np.inf))
    if not peak >= MIN_PEAK or second * MIN_CONTRAST > peak:
        return None
    return SurfaceMatch(float(best), peak)


def correlations(left: np.ndarray, right: np.ndarray, u: np.ndarray, v: np.ndarray, d: np.ndarray) -> np.ndarray:
    """(D,) the zero-mean normalised correlation of the pixels (u, v) (N,) of ``left`` with ``right`` shifted by
    each whole-pixel disparity of ``d`` (D,); -inf where less than MIN_OVERLAP of them lie in ``right``.
    left, right: HxW float images; u, v inside them."""
    columns = u[None, :] - d[:, None]  # (D, N)
    inside = (columns >= 0) & (columns < right.shape[1])
    a = np.where(inside, left[v, u].astype(np.float32)[None, :], np.float32(0))
    b = np.where(inside, right[v[None, :], np.clip(columns, 0, right.shape[1] - 1)].astype(np.float32), np.float32(0))
    n = inside.sum(axis=1)
    scored = n >= MIN_OVERLAP * u.size
    n = np.maximum(n, 1).astype(np.float32)
    a = np.where(inside, a - (a.sum(axis=1) / n)[:, None], np.float32(0))
    b = np.where(inside, b - (b.sum(axis=1) / n)[:, None], np.float32(0))
    with np.errstate(invalid="ignore", divide="ignore"):
        r = (a * b).sum(axis=1) / np.sqrt((a * a).sum(axis=1) * (b * b).sum(axis=1))
    return np.where(scored & np.isfinite(r), r, -np.inf)
