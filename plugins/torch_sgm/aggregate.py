"""Cost aggregation: an edge-aware guided filter applied to every disparity slice, optionally with a
smaller radius where the left image is textured."""
from __future__ import annotations

import torch

from plugins.torch_sgm.cost import box_counts, box_mean, box_mean_fast, local_mean_variance


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


def guide_statistics(guide: torch.Tensor, radius: int, eps: float, mean=box_mean) -> tuple:
    """What ``guided_filter_fast`` needs of the guide (B, 1, H, W), computed once per image:
    (guide, its local mean, 1 / (local variance + eps), each (B, 1, H, W); eps). ``mean``: the box mean to take
    them with (``aggregate_numba.box_mean_numba``, the same numbers compiled)."""
    mean_i = mean(guide, radius)
    var_i = mean(guide * guide, radius) - mean_i * mean_i
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


def texture_weight(guide: torch.Tensor, radius: int, scale: float, mean=box_mean) -> torch.Tensor:
    """(B, 1, H, W) grey guide in [0, 1] -> (B, 1, H, W) exp(-std / ``scale``), std being the guide's
    standard deviation over a (2 ``radius`` + 1)^2 window: 1 on a flat area, towards 0 where textured.

    The weight of the wider of two aggregations in ``blend_by_texture``: a flat area needs a wide
    window to find any match at all, while on texture a narrow one keeps thin structures and depth
    edges that a wide one blurs. ``mean``: the box mean to take the variance with."""
    # in float32 the running sums leave a variance of ~1e-7 on a flat area, a std that is not small
    # against a scale of 0.02
    _, var = local_mean_variance(guide.double(), radius, mean)
    return torch.exp(-var.sqrt() / scale).to(guide.dtype)


def blend_by_texture(detail: torch.Tensor, wide: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """(B, D, H, W) costs aggregated narrowly and widely, (B, 1, H, W) ``texture_weight`` ->
    (B, D, H, W) their per-pixel mix, ``wide`` where the weight is 1. Overwrites ``detail``."""
    return detail.lerp_(wide, weight.expand_as(detail))
