"""``sgm.sgm`` compiled for the CPU with numba: the same path recurrences, one pixel at a time.

The torch versions advance a whole row or column per step; on the small crops the line matches
(about 190 x 60 px at half resolution) each step is a handful of tiny tensor operations, and their
overhead, not arithmetic, is most of the time. Here each path is a loop over its pixels in C-like
code, the paths that cross the image's rows in parallel over the rows (``prange``), the others over
the columns. ``sgm.sgm`` stays the reference the tests hold this one to.
"""
from __future__ import annotations

from contextlib import contextmanager

import numpy as np
import torch
import numba
from numba import njit, prange

from plugins.torch_sgm import sgm



@njit(cache=True, inline="always", fastmath=True)
def _min(a, b):
    # a select, which LLVM vectorises over the disparities; the builtin min's NaN rules keep it scalar
    return a if a < b else b


@njit(cache=True, inline="always", fastmath=True)
def _least(values):
    """The least of a 1-D array, as eight running minima: a single one waits on each comparison in turn."""
    n = values.shape[0]
    m0 = m1 = m2 = m3 = m4 = m5 = m6 = m7 = values[0]
    whole = n - n % 8
    for d in range(0, whole, 8):
        m0, m1 = _min(m0, values[d]), _min(m1, values[d + 1])
        m2, m3 = _min(m2, values[d + 2]), _min(m3, values[d + 3])
        m4, m5 = _min(m4, values[d + 4]), _min(m5, values[d + 5])
        m6, m7 = _min(m6, values[d + 6]), _min(m7, values[d + 7])
    for d in range(whole, n):
        m0 = _min(m0, values[d])
    return _min(_min(_min(m0, m1), _min(m2, m3)), _min(_min(m4, m5), _min(m6, m7)))


@njit(cache=True, inline="always", fastmath=True)
def _step(cost, out, prev, cur, b, y, x, p1, p2, fresh, first):
    """One pixel of one path: ``cur`` from ``prev`` (the predecessor's path costs), added to ``out`` (written
    to it for the ``first`` path, so that ``out`` needs no zeroing). cost, out: (B, H, W, D), so that a
    pixel's disparities lie side by side; p1, p2 float32 (a float64 operand would widen every disparity's
    arithmetic and keep it scalar)."""
    d_count = cost.shape[3]
    c, o = cost[b, y, x], out[b, y, x]
    if fresh:
        for d in range(d_count):
            cur[d] = c[d]
    else:
        floor = _least(prev)
        jump = floor + p2
        if d_count == 1:
            cur[0] = c[0] + _min(prev[0], jump) - floor
        else:
            cur[0] = c[0] + _min(_min(prev[0], prev[1] + p1), jump) - floor
            last = d_count - 1
            for d in range(1, last):
                cur[d] = c[d] + _min(_min(prev[d], _min(prev[d - 1], prev[d + 1]) + p1), jump) - floor
            cur[last] = c[last] + _min(_min(prev[last], prev[last - 1] + p1), jump) - floor
    if first:
        for d in range(d_count):
            o[d] = cur[d]
    else:
        for d in range(d_count):
            o[d] += cur[d]


@njit(cache=True, nogil=True, parallel=True)
def _along_rows(cost, out, p2, p1, dxs, first):
    """The horizontal paths (dy = 0), one per entry of ``dxs`` (+1 / -1) with its (B, H, W) map in ``p2``
    (K, B, H, W): each row on its own, all of its paths in turn, so that the later ones read the row's
    costs from the cache instead of memory."""
    n_b, h, w, d_count = cost.shape
    p1 = np.float32(p1)
    for job in prange(n_b * h):
        b, y = job // h, job % h
        prev = np.empty(d_count, cost.dtype)
        cur = np.empty(d_count, cost.dtype)
        for k in range(len(dxs)):
            for i in range(w):
                x = i if dxs[k] > 0 else w - 1 - i
                _step(cost, out, prev, cur, b, y, x, p1, p2[k, b, y, x], i == 0, first and k == 0)
                prev, cur = cur, prev


@njit(cache=True, nogil=True, parallel=True)
def _across_rows(cost, out, p2, p1, dy, dxs, first):
    """The paths that step ``dy`` rows (one per entry of ``dxs``, with its map in ``p2`` (K, B, H, W)):
    row after row, the pixels of a row in parallel, every path at each pixel while its costs are in the
    cache. ``state`` holds each path's costs at the previous row; a diagonal reads its neighbour's column
    there."""
    n_b, h, w, d_count = cost.shape
    n_k = len(dxs)
    p1 = np.float32(p1)
    for b in range(n_b):
        state = np.empty((2, n_k, w, d_count), cost.dtype)
        for i in range(h):
            y = i if dy > 0 else h - 1 - i
            now, before = i % 2, 1 - i % 2
            for x in prange(w):
                for k in range(n_k):
                    px = x - dxs[k]
                    fresh = i == 0 or px < 0 or px >= w
                    _step(cost, out, state[before, k, px if not fresh else 0], state[now, k, x], b, y, x, p1,
                          p2[k, b, y, x], fresh, first and k == 0)


@njit(cache=True, nogil=True)
def _across_rows_one_thread(cost, out, p2, p1, dy, dxs, first):
    """``_across_rows`` with a plain loop over each row's pixels, for one thread: a parallel region started at every
    row cost a crop's SGM a fifth to a third of its time, even with one thread to run it. (The loop is written out
    as there: through a helper that both called, this one measured several times slower.)"""
    n_b, h, w, d_count = cost.shape
    n_k = len(dxs)
    p1 = np.float32(p1)
    for b in range(n_b):
        state = np.empty((2, n_k, w, d_count), cost.dtype)
        for i in range(h):
            y = i if dy > 0 else h - 1 - i
            now, before = i % 2, 1 - i % 2
            for x in range(w):
                for k in range(n_k):
                    px = x - dxs[k]
                    fresh = i == 0 or px < 0 or px >= w
                    _step(cost, out, state[before, k, px if not fresh else 0], state[now, k, x], b, y, x, p1,
                          p2[k, b, y, x], fresh, first and k == 0)


@njit(cache=True, nogil=True, parallel=True)
def _pixel_major(cost, out):
    """(B, D, H, W) -> ``out`` (B, H, W, D): rows in parallel (NumPy's copy of the transposed view runs on one
    thread)."""
    n_b, d_count, h, w = cost.shape
    for job in prange(n_b * h):
        b, y = job // h, job % h
        for d in range(d_count):
            row = cost[b, d, y]
            for x in range(w):
                out[b, y, x, d] = row[x]


@contextmanager
def torch_threads():
    """Run numba's parallel loops on as many threads as torch has, and leave torch's count as it was."""
    # the process's one thread setting (recipe ``threads``, ``--threads``) is torch's: two stations on
    # two cores must not each spin numba's threads on both. numba's OpenMP layer resets the OpenMP
    # thread count that torch reads, so it is put back.
    n = torch.get_num_threads()
    numba.set_num_threads(max(1, min(n, numba.config.NUMBA_NUM_THREADS)))
    try:
        yield
    finally:
        torch.set_num_threads(n)


def available(cost: torch.Tensor) -> bool:
    """True where this kernel can stand in for ``sgm.sgm``: a CPU tensor of float32."""
    return cost.device.type == "cpu" and cost.dtype == torch.float32


def sgm_numba(cost: torch.Tensor, p1: float, p2: torch.Tensor | float, paths=sgm.PATHS_4) -> torch.Tensor:
    """``sgm.sgm`` on the CPU: cost (B, D, H, W) float32 -> (B, D, H, W) sum of the path costs over
    ``paths``; p2 scalar, (B, H, W) or (B, len(paths), H, W) as there."""
    if not available(cost):
        raise ValueError(f"sgm_numba: needs a float32 CPU tensor, got {cost.dtype} on {cost.device}")
    if cost.dim() != 4:
        raise ValueError(f"sgm_numba: cost must be (B, D, H, W), got {tuple(cost.shape)}")
    penalty = sgm._per_path(p2, cost, paths)
    # paths that step alike walk the volume together: it is read from memory once per group, not per path
    groups = []
    for dy in sorted({dy for dy, _ in paths}, key=lambda dy: (abs(dy), -dy)):
        group = [path for path in paths if path[0] == dy]
        maps = np.ascontiguousarray(torch.stack([penalty[path] for path in group]).to(cost.dtype).numpy())
        groups.append((dy, np.array([dx for _, dx in group], np.int64), maps))
    with torch_threads():
        volume = cost.numpy()
        c = np.empty((volume.shape[0], *volume.shape[2:], volume.shape[1]), volume.dtype)
        _pixel_major(volume, c)
        out = np.empty_like(c)  # the first path writes it
        across = _across_rows_one_thread if numba.get_num_threads() == 1 else _across_rows
        for n, (dy, dxs, maps) in enumerate(groups):
            if dy == 0:
                _along_rows(c, out, maps, float(p1), dxs, n == 0)
            else:
                across(c, out, maps, float(p1), int(dy), dxs, n == 0)
    # a view in the (B, D, H, W) order: the winners read each pixel's disparities side by side, where the
    # numba kernels left them, instead of after a transposing copy
    return torch.from_numpy(out).permute(0, 3, 1, 2)
