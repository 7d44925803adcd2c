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
def _step(cost, out, prev, cur, b, y, x, p1, p2, fresh):
    """One pixel of one path: ``cur`` from ``prev`` (the predecessor's path costs), added to ``out``.
    cost, out: (B, H, W, D), so that a pixel's disparities lie side by side."""
    d_count = cost.shape[3]
    c, o = cost[b, y, x], out[b, y, x]
    if fresh:
        for d in range(d_count):
            cur[d] = c[d]
            o[d] += c[d]
        return
    floor = prev[0]
    for d in range(1, d_count):
        floor = min(floor, prev[d])
    jump = floor + p2
    if d_count == 1:
        cur[0] = c[0] + min(prev[0], jump) - floor
        o[0] += cur[0]
        return
    cur[0] = c[0] + min(min(prev[0], prev[1] + p1), jump) - floor
    for d in range(1, d_count - 1):
        cur[d] = c[d] + min(min(prev[d], min(prev[d - 1], prev[d + 1]) + p1), jump) - floor
    last = d_count - 1
    cur[last] = c[last] + min(min(prev[last], prev[last - 1] + p1), jump) - floor
    for d in range(d_count):
        o[d] += cur[d]


@njit(cache=True, parallel=True)
def _along_rows(cost, out, p2, p1, dx):
    """A horizontal path (dy = 0): each row on its own."""
    n_b, h, w, d_count = cost.shape
    for job in prange(n_b * h):
        b, y = job // h, job % h
        prev = np.empty(d_count, cost.dtype)
        cur = np.empty(d_count, cost.dtype)
        for i in range(w):
            x = i if dx > 0 else w - 1 - i
            _step(cost, out, prev, cur, b, y, x, p1, p2[b, y, x], i == 0)
            prev, cur = cur, prev


@njit(cache=True, parallel=True)
def _across_rows(cost, out, p2, p1, dy, dx):
    """A path with dy != 0: row after row, the pixels of a row in parallel. ``state`` holds each column's
    path costs at the previous row; a diagonal reads its neighbour's column there."""
    n_b, h, w, d_count = cost.shape
    for b in range(n_b):
        state = np.empty((2, w, d_count), cost.dtype)
        for i in range(h):
            y = i if dy > 0 else h - 1 - i
            now, before = i % 2, 1 - i % 2
            for x in prange(w):
                px = x - dx
                fresh = i == 0 or px < 0 or px >= w
                _step(cost, out, state[before, px if not fresh else 0], state[now, x], b, y, x, p1,
                      p2[b, y, x], fresh)


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
    with torch_threads():
        c = np.ascontiguousarray(cost.numpy().transpose(0, 2, 3, 1))  # (B, H, W, D)
        out = np.zeros_like(c)
        for dy, dx in paths:
            p = np.ascontiguousarray(penalty[dy, dx].to(cost.dtype).numpy())
            if dy == 0:
                _along_rows(c, out, p, float(p1), int(dx))
            else:
                _across_rows(c, out, p, float(p1), int(dy), int(dx))
    # a view in the (B, D, H, W) order: the winners read each pixel's disparities side by side, where the
    # numba kernels left them, instead of after a transposing copy
    return torch.from_numpy(out).permute(0, 3, 1, 2)
