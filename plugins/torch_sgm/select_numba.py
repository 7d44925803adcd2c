"""``select.checked_winners`` and ``select.unique_minimum`` compiled for the CPU with numba, for a volume in
either memory order: the cost volume's (B, D, H, W), or the SGM sums as ``sgm_numba`` leaves them, each
pixel's disparities side by side ((B, H, W, D) memory seen as a (B, D, H, W) view), which the torch versions
read slice by slice through strided memory. The ``select`` functions stay the references the tests hold
these to.
"""
from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from plugins.torch_sgm import refine, sgm_numba


@njit(cache=True, inline="always")
def _subpixel(c0, c1, c2, i, d_count, d_first):
    """The winner ``i``'s disparity from its cost ``c1`` and its neighbours' ``c0``, ``c2`` (float32, as torch
    computes it): the parabola's vertex, at most half a step away."""
    half, two, tiny = np.float32(0.5), np.float32(2.0), np.float32(1e-12)
    spread = c0 - two * c1 + c2
    offset = np.float32(0.0)
    if 0 < i < d_count - 1 and spread > 0:
        offset = min(max((c0 - c2) / (two * max(spread, tiny)), -half), half)
    return (np.float32(i) + offset) + np.float32(d_first)


@njit(cache=True, nogil=True, parallel=True)
def _checked_winners(cost, d_first, disp, index, right_best, right_disp):
    """Each row's winners of both views in one pass over its costs: (B, H, W, D) ``cost`` (any strides) ->
    ``disp`` (sub-pixel, float32 as torch computes it), ``index`` and the right view's ``right_disp``;
    ``right_best`` (B, H, W) scratch."""
    n_b, h, w, d_count = cost.shape
    for job in prange(n_b * h):
        b, y = job // h, job % h
        for xr in range(w):
            right_best[b, y, xr] = np.inf
            right_disp[b, y, xr] = np.nan
        for x in range(w):
            # the first of equal minima, or the first NaN, as torch's min(1).indices
            best, i = cost[b, y, x, 0], 0
            if best == best:
                for d in range(1, d_count):
                    value = cost[b, y, x, d]
                    if value != value or value < best:
                        best, i = value, d
                        if value != value:
                            break
            index[b, y, x] = i
            disp[b, y, x] = _subpixel(cost[b, y, x, max(i - 1, 0)], cost[b, y, x, i],
                                      cost[b, y, x, min(i + 1, d_count - 1)], i, d_count, d_first)
            # the right view: right pixel x - d sees this cost at d; disparities arrive in ascending order at
            # each right pixel, so a strict comparison keeps the lowest of equal costs, as the reference
            for k in range(d_count):
                xr = x - (d_first + k)
                if 0 <= xr < w:
                    value = cost[b, y, x, k]
                    if value < right_best[b, y, xr]:
                        right_best[b, y, xr] = value
                        right_disp[b, y, xr] = d_first + k


@njit(cache=True, nogil=True, parallel=True)
def _checked_winners_by_slice(cost, d_first, disp, index, right_best, right_disp):
    """``_checked_winners`` of a (B, D, H, W) ``cost`` whose rows lie contiguous within each disparity slice
    (the cost volume's own memory): each row's slices in turn, every pixel's running winner kept beside
    them, so that the costs are read in memory order instead of one slice apart."""
    n_b, d_count, h, w = cost.shape
    for job in prange(n_b * h):
        b, y = job // h, job % h
        best = cost[b, 0, y].copy()
        winner = np.zeros(w, np.int64)
        settled = best != best  # the first NaN wins, as torch's min(1).indices
        for xr in range(w):
            right_best[b, y, xr] = np.inf
            right_disp[b, y, xr] = np.nan
        for k in range(d_count):
            row = cost[b, k, y]
            if k > 0:
                for x in range(w):  # selects, not branches: LLVM vectorises them
                    value = row[x]
                    nan = value != value
                    take = not settled[x] and (nan or value < best[x])
                    best[x] = value if take else best[x]
                    winner[x] = k if take else winner[x]
                    settled[x] = settled[x] or nan
            # right pixel x - d sees this cost at d; d ascends, so a strict comparison keeps the lowest of equal
            # costs, as the reference
            # through slices from 0: an index that numba cannot prove non-negative keeps the loop scalar
            shift = d_first + k
            lo, hi = max(shift, 0), min(w, w + shift)
            if hi <= lo:
                continue
            seen = row[lo:hi]
            least, at = right_best[b, y, lo - shift:hi - shift], right_disp[b, y, lo - shift:hi - shift]
            for x in range(hi - lo):
                take = seen[x] < least[x]
                least[x] = seen[x] if take else least[x]
                at[x] = np.float32(shift) if take else at[x]
        for x in range(w):
            i = winner[x]
            index[b, y, x] = i
            disp[b, y, x] = _subpixel(cost[b, max(i - 1, 0), y, x], cost[b, i, y, x],
                                      cost[b, min(i + 1, d_count - 1), y, x], i, d_count, d_first)


def checked_winners_numba(volume: torch.Tensor, disparities, lr_tolerance: float,
                          ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``select.checked_winners`` of a float32 CPU volume (B, D, H, W) in either memory order: the same four
    results."""
    if not sgm_numba.available(volume) or volume.dim() != 4:
        raise ValueError(f"checked_winners_numba: needs a (B, D, H, W) float32 CPU tensor, got {volume.dtype} "
                         f"of shape {tuple(volume.shape)} on {volume.device}")
    b, _, h, w = volume.shape
    disp, right_disp, best = (np.empty((b, h, w), np.float32) for _ in range(3))
    index = np.empty((b, h, w), np.int64)
    with sgm_numba.torch_threads():
        if volume.is_contiguous():
            _checked_winners_by_slice(volume.numpy(), int(disparities[0]), disp, index, best, right_disp)
        else:
            _checked_winners(volume.permute(0, 2, 3, 1).numpy(), int(disparities[0]), disp, index, best, right_disp)
    disp, right_disp = torch.from_numpy(disp), torch.from_numpy(right_disp)
    return disp, torch.from_numpy(index), right_disp, refine.left_right_check(disp, right_disp, lr_tolerance)


@njit(cache=True, inline="always")
def _least_of(values, lo, hi, least, nan):
    """(least, nan) updated by ``values[lo:hi]``: their least, and whether one is NaN. Eight running minima
    and NaN flags in turn, each waiting on its own previous value only (a NaN fails every comparison, so
    it never enters a minimum)."""
    part = values[lo:hi]
    n = part.shape[0]
    m0 = m1 = m2 = m3 = m4 = m5 = m6 = m7 = least
    f0 = f1 = f2 = f3 = f4 = f5 = f6 = f7 = False
    whole = n - n % 8
    for d in range(0, whole, 8):
        v0, v1, v2, v3 = part[d], part[d + 1], part[d + 2], part[d + 3]
        v4, v5, v6, v7 = part[d + 4], part[d + 5], part[d + 6], part[d + 7]
        m0, m1, m2, m3 = (v0 if v0 < m0 else m0), (v1 if v1 < m1 else m1), (v2 if v2 < m2 else m2), \
            (v3 if v3 < m3 else m3)
        m4, m5, m6, m7 = (v4 if v4 < m4 else m4), (v5 if v5 < m5 else m5), (v6 if v6 < m6 else m6), \
            (v7 if v7 < m7 else m7)
        f0, f1, f2, f3 = f0 | (v0 != v0), f1 | (v1 != v1), f2 | (v2 != v2), f3 | (v3 != v3)
        f4, f5, f6, f7 = f4 | (v4 != v4), f5 | (v5 != v5), f6 | (v6 != v6), f7 | (v7 != v7)
    for d in range(whole, n):
        v = part[d]
        m0 = v if v < m0 else m0
        f0 |= v != v
    m0, m1, m2, m3 = min(m0, m4), min(m1, m5), min(m2, m6), min(m3, m7)
    return min(min(m0, m1), min(m2, m3)), nan | f0 | f1 | f2 | f3 | f4 | f5 | f6 | f7


@njit(cache=True, nogil=True, parallel=True)
def _unique_minimum(cost, index, ratio, out):
    n_b, h, w, d_count = cost.shape
    for job in prange(n_b * h):
        b, y = job // h, job % h
        for x in range(w):
            i = index[b, y, x]
            values = cost[b, y, x]
            # the least cost beyond the winner's neighbours; a NaN anywhere there makes it NaN, as torch's
            # minimum propagates it
            second, nan = _least_of(values, 0, max(i - 1, 0), np.float32(np.inf), False)
            second, nan = _least_of(values, min(i + 2, d_count), d_count, second, nan)
            out[b, y, x] = not nan and second > (1.0 + ratio) * values[i]


def unique_minimum_numba(volume: torch.Tensor, index: torch.Tensor, ratio: float) -> torch.Tensor:
    """``select.unique_minimum`` of a float32 CPU volume (B, D, H, W) in either memory order and its (B, H, W)
    int64 winners -> (B, H, W) bool; unlike the reference it leaves ``volume`` as it was."""
    if not sgm_numba.available(volume) or volume.dim() != 4 or index.shape != (volume.shape[0], *volume.shape[2:]):
        raise ValueError(f"unique_minimum_numba: needs a (B, D, H, W) float32 CPU volume and (B, H, W) winners, got "
                         f"{volume.dtype} {tuple(volume.shape)} on {volume.device} and {tuple(index.shape)}")
    out = np.empty(tuple(index.shape), np.bool_)
    with sgm_numba.torch_threads():
        _unique_minimum(volume.permute(0, 2, 3, 1).numpy(), np.ascontiguousarray(index.numpy()), float(ratio), out)
    return torch.from_numpy(out)


def pixel_major(volume: torch.Tensor) -> bool:
    """Whether ``volume`` (B, D, H, W) is a view of (B, H, W, D) memory, as ``sgm_numba`` returns."""
    return volume.dim() == 4 and volume.permute(0, 2, 3, 1).is_contiguous()
