"""The ring plane's consensus compiled with numba: RANSAC scores every hypothesis on the same points, one
pass per hypothesis instead of a (hypotheses x points) array NumPy builds, thresholds and sums (most of
``depth.fit_plane_robust``'s time). ``tests/test_depth.py`` holds it to NumPy's count."""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _inlier_counts(planes, u, v, d, tolerance):
    counts = np.zeros(planes.shape[0], dtype=np.int64)
    for t in range(planes.shape[0]):
        a, b, c = planes[t, 0], planes[t, 1], planes[t, 2]
        count = 0
        for i in range(u.size):
            # the same expression, in the same order, as NumPy's: a point on the tolerance counts alike
            if abs(a * u[i] + b * v[i] + c - d[i]) <= tolerance:
                count += 1
        counts[t] = count
    return counts


def inlier_counts(planes: np.ndarray, u: np.ndarray, v: np.ndarray, d: np.ndarray, tolerance: float) -> np.ndarray:
    """For each plane ``d = a * u + b * v + c`` of ``planes`` (T, 3), the points (u, v, d) (N,) each within
    ``tolerance`` of it. Returns (T,) int64."""
    n = len(u)
    if planes.ndim != 2 or planes.shape[1] != 3:
        raise ValueError(f"inlier_counts: planes {planes.shape} must be (T, 3)")
    if np.shape(v) != (n,) or np.shape(d) != (n,):
        raise ValueError(f"inlier_counts: u {np.shape(u)}, v {np.shape(v)} and d {np.shape(d)} must be (N,) alike")
    f64 = np.float64
    return _inlier_counts(np.ascontiguousarray(planes, f64), np.ascontiguousarray(u, f64),
                          np.ascontiguousarray(v, f64), np.ascontiguousarray(d, f64), float(tolerance))
