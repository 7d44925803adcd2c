"""``select.right_view_wta`` and ``select.unique_minimum`` compiled for the CPU with numba, for a volume in
either memory order: the cost volume's (B, D, H, W), or the SGM sums as ``sgm_numba`` leaves them, each
pixel's disparities side by side ((B, H, W, D) memory seen as a (B, D, H, W) view), which the torch versions
read slice by slice through strided memory. The ``select`` functions stay the references the tests hold
these to.
"""
from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from plugins.torch_sgm import sgm_numba


@njit(cache=True, parallel=True)
def _right_view_wta(cost, d_first, best, disp):
    n_b, h, w, d_count = cost.shape
    for job in prange(n_b * h):
        b, y = job // h, job % h
        # disparities in ascending order with a strict comparison: equal costs keep the lowest, as the reference
        for k in range(d_count):
            d = d_first + k
            for xr in range(max(0, -d), min(w, w - d)):
                value = cost[b, y, xr + d, k]
                if value < best[b, y, xr]:
                    best[b, y, xr] = value
                    disp[b, y, xr] = d


@njit(cache=True, parallel=True)
def _unique_minimum(cost, index, ratio, out):
    n_b, h, w, d_count = cost.shape
    for job in prange(n_b * h):
        b, y = job // h, job % h
        for x in range(w):
            i = index[b, y, x]
            second = np.inf
            for d in range(d_count):
                if i - 1 <= d <= i + 1:
                    continue
                value = cost[b, y, x, d]
                if value != value:  # a NaN, as torch's minimum propagates it
                    second = np.nan
                    break
                second = min(second, value)
            out[b, y, x] = second > (1.0 + ratio) * cost[b, y, x, i]


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


def right_view_wta_numba(volume: torch.Tensor, disparities) -> torch.Tensor:
    """``select.right_view_wta`` of a float32 CPU volume over ``disparities`` (consecutive integers);
    (B, D, H, W) in either memory order -> (B, H, W) float32, NaN where no disparity lands."""
    if not sgm_numba.available(volume) or volume.dim() != 4:
        raise ValueError(f"right_view_wta_numba: needs a (B, D, H, W) float32 CPU tensor, got {volume.dtype} "
                         f"of shape {tuple(volume.shape)} on {volume.device}")
    b, _, h, w = volume.shape
    best = np.full((b, h, w), np.inf, np.float32)
    disp = np.full((b, h, w), np.nan, np.float32)
    with sgm_numba.torch_threads():
        _right_view_wta(volume.permute(0, 2, 3, 1).numpy(), int(disparities[0]), best, disp)
    return torch.from_numpy(disp)
