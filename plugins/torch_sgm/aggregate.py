"""Cost aggregation: an edge-aware guided filter applied to every disparity slice."""
from __future__ import annotations

import torch

from plugins.torch_sgm.cost import box_mean


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
