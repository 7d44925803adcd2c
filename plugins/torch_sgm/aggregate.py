"""Cost aggregation: an edge-aware guided filter applied to every disparity slice."""
from __future__ import annotations

import torch

from plugins.torch_sgm.cost import box_counts, box_mean, box_mean_fast


def guided_filter(guide: torch.Tensor, src: torch.Tensor, radius: int, eps: float) -> torch.Tensor:
    """He et al.'s guided filter with a grey guide.

    guide: (B, 1, H, W); src: (B, C, H, W), each channel (here: each disparity slice) filtered
    independently. Returns (B, C, H, W). Edges of the guide survive because the output is locally
    an affine function of the guide.
    """
    if radius <= 0:
        return src
    mean_i = box_mean(guide, radius)
    var_i = box_mean(guide * guide, radius) - mean_i * mean_i
    mean_p = box_mean(src, radius)
    a = (box_mean(guide * src, radius) - mean_i * mean_p) / (var_i + eps)
    b = mean_p - a * mean_i
    del mean_p
    return box_mean(a, radius) * guide + box_mean(b, radius)


def guide_statistics(guide: torch.Tensor, radius: int, eps: float) -> tuple:
    """What ``guided_filter_fast`` needs of the guide (B, 1, H, W), computed once per image:
    (guide, its local mean, 1 / (local variance + eps), each (B, 1, H, W); eps)."""
    mean_i = box_mean(guide, radius)
    var_i = box_mean(guide * guide, radius) - mean_i * mean_i
    return guide, mean_i, 1.0 / (var_i + eps), eps


def guided_filter_fast(stats: tuple, src: torch.Tensor, radius: int) -> torch.Tensor:
    """``guided_filter`` (the reference) with the guide's statistics from ``guide_statistics``, box
    means by slicing running sums, and every step in place. ``src`` (B, C, H, W) is overwritten; the
    result (B, C, H, W) is returned. Needs H, W >= 2 * radius + 2; smaller inputs use the reference."""
    guide, mean_i, inv_var, eps = stats
    h, w = src.shape[-2:]
    if radius <= 0:
        return src
    if min(h, w) < 2 * radius + 2:
        return guided_filter(guide, src, radius, eps)
    inv_count = box_counts(h, w, radius, src.device, src.dtype)
    work = torch.empty_like(src)
    mean_p = box_mean_fast(src, radius, None, work, inv_count)
    a = box_mean_fast(src.mul_(guide), radius, None, work, inv_count)  # mean of guide * src
    a.addcmul_(mean_i, mean_p, value=-1.0).mul_(inv_var)              # a = cov / (var + eps)
    b = mean_p.addcmul_(a, mean_i, value=-1.0)                          # b = mean_p - a * mean_i
    out = box_mean_fast(a, radius, src, work, inv_count).mul_(guide)
    return out.add_(box_mean_fast(b, radius, a, work, inv_count))
