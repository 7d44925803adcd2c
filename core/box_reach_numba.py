"""The moved regions' readings compiled with numba: for every copy of the region, which cells it holds and their
area-weighted mean, median and the mean's standard deviation, in one pass per copy instead of the (copies x cells)
arrays NumPy builds, masks, sums and sorts (most of ``box_reach.moved_regions``' own time). ``tests/test_box_reach.py``
holds it to NumPy's arithmetic."""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _copy_readings(x, s, areas, usable, u, v, edges):
    n_copies, n_cells = edges.shape[0], x.size
    inside = np.zeros((n_copies, n_cells), dtype=np.bool_)
    counts = np.zeros(n_copies, dtype=np.int64)
    mean, median, sd = np.empty(n_copies), np.empty(n_copies), np.empty(n_copies)
    order = np.argsort(x)
    for c in range(n_copies):
        total, weighted, variance = 0.0, 0.0, 0.0
        for k in range(n_cells):
            if usable[k] and u[k] >= edges[c, 0] and u[k] < edges[c, 2] and v[k] >= edges[c, 1] \
                    and v[k] < edges[c, 3]:
                inside[c, k] = True
                counts[c] += 1
                a = areas[k]
                total += a
                weighted += a * x[k]
                variance += a * a * s[k] * s[k]
        total = max(total, 1e-12)
        mean[c] = weighted / total
        sd[c] = np.sqrt(variance) / total
        # the cells in offset order, their area summed up to each: the first to reach half the area and the first
        # beyond it (the first cell of all where none does)
        half, below, reach, beyond = 0.5 * total, 0.0, -1, -1
        for j in range(n_cells):
            k = order[j]
            if inside[c, k]:
                below += areas[k]
            if reach < 0 and below >= half:
                reach = j
            if below > half:
                beyond = j
                break
        median[c] = 0.5 * (x[order[max(reach, 0)]] + x[order[max(beyond, 0)]])
    return inside, counts, mean, median, sd


def copy_readings(offsets: np.ndarray, sds: np.ndarray, areas: np.ndarray, usable: np.ndarray, centres: np.ndarray,
                  edges: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For each copy of the region (``edges`` (M, 4): x0, y0, x1, y1), the ``usable`` cells whose centres lie inside
    it and their readings by area.

    offsets, sds, areas: (K,) each cell's offset, its standard deviation and its area (an unusable cell's offset and
    sd may be anything); usable: (K,) bool; centres: (K, 2) the cells' (u, v). Returns (inside (M, K) bool, counts
    (M,), the area-weighted mean of the offsets (M,), their area-weighted median (M,: the two middle cells' mean
    where the area divides evenly between them), the mean's standard deviation (M,)); a copy without cells has the
    mean and deviation of a total area of 1e-12."""
    n = len(offsets)
    for name, array in (("sds", sds), ("areas", areas), ("usable", usable)):
        if np.shape(array) != (n,):
            raise ValueError(f"copy_readings: {name} {np.shape(array)} must be ({n},) as offsets")
    if np.shape(centres) != (n, 2) or np.ndim(edges) != 2 or np.shape(edges)[1] != 4:
        raise ValueError(f"copy_readings: centres {np.shape(centres)} must be ({n}, 2), edges {np.shape(edges)} (M, 4)")
    f64 = np.float64
    usable = np.asarray(usable, dtype=np.bool_)
    x = np.where(usable, offsets, 0.0).astype(f64)
    s = np.where(usable, sds, 0.0).astype(f64)
    return _copy_readings(x, s, np.asarray(areas, f64), usable, np.ascontiguousarray(centres[:, 0], f64),
                          np.ascontiguousarray(centres[:, 1], f64), np.ascontiguousarray(edges, f64))
