"""``select.right_view_wta`` compiled for the CPU with numba, for the SGM sums as ``sgm_numba`` leaves them:
each pixel's disparities side by side ((B, H, W, D) memory seen as a (B, D, H, W) view). The torch version
walks the disparity slices, each of which is then strided through memory; this one walks each row's
disparities where they lie. ``select.right_view_wta`` stays the reference the tests hold it to.
"""
from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from plugins.torch_sgm import select, sgm_numba


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


def pixel_major(volume: torch.Tensor) -> bool:
    """Whether ``volume`` (B, D, H, W) is a float32 CPU view of (B, H, W, D) memory, as ``sgm_numba`` returns."""
    return sgm_numba.available(volume) and volume.dim() == 4 and volume.permute(0, 2, 3, 1).is_contiguous()


def right_view_wta_numba(volume: torch.Tensor, disparities) -> torch.Tensor:
    """``select.right_view_wta`` of a ``pixel_major`` volume over ``disparities`` (consecutive integers);
    any other volume goes to the reference. (B, D, H, W) -> (B, H, W) float32, NaN where no disparity lands."""
    if not pixel_major(volume):
        return select.right_view_wta(volume, disparities)
    b, _, h, w = volume.shape
    best = np.full((b, h, w), np.inf, np.float32)
    disp = np.full((b, h, w), np.nan, np.float32)
    with sgm_numba.torch_threads():
        _right_view_wta(volume.permute(0, 2, 3, 1).numpy(), int(disparities[0]), best, disp)
    return torch.from_numpy(disp)
