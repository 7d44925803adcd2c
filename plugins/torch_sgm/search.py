"""Coarse-to-fine search: a pass at a fraction of the resolution finds which disparities the scene
occupies, so the full-resolution pass searches only those.

A plate on a conveyor spans 10-25 disparities of the 128 a WVGA ZED needs over its working distance;
every stage of the matcher costs time in proportion to the disparities searched, and a pass at a
quarter of the resolution costs 1/64 of a full one. Pixels whose best match sits on a bound that the
narrowing introduced, or that the coarse pass matched outside the narrowed range, are treated as
unmatched (``at_narrowed_bound``, ``outside_range``): their true disparity may lie outside the searched
range, and a wrong depth is worse than a filled hole.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def downsample(image: torch.Tensor, factor: int) -> torch.Tensor:
    """(B, C, H, W) -> (B, C, H // factor, W // factor), each pixel the mean of a factor x factor block.

    Full-resolution column x maps to coarse column (x - (factor - 1) / 2) / factor in both views, so a
    coarse disparity times ``factor`` is a full-resolution disparity."""
    return F.avg_pool2d(image, factor) if factor > 1 else image


def coarse_bounds(min_disp: float, max_disp: float, factor: int, width: int) -> tuple[int, int]:
    """The coarse search ``lo <= d < hi`` covering full-resolution ``min_disp <= d < max_disp``, kept
    below the coarse width ``width`` and at least two disparities wide."""
    lo = math.floor(min_disp / factor)
    hi = min(math.ceil(max_disp / factor) + 1, max(width - 1, lo + 2))
    return lo, max(hi, lo + 2)


def occupied_range(disparity: torch.Tensor, matched: torch.Tensor, factor: int, margin: float,
                   quantile: float, min_coverage: float, min_disp: float, max_disp: float,
                   ) -> tuple[int, int] | None:
    """The full-resolution search ``lo <= d < hi`` that a coarse result calls for.

    disparity: (B, h, w) coarse disparity; matched: (B, h, w) bool, the pixels that passed the
    left-right check. The range spans the ``quantile`` and ``1 - quantile`` quantiles of the matched
    disparities times ``factor``, widened by ``margin`` full-resolution pixels and kept inside
    ``[min_disp, max_disp)``. None (search everything) when fewer than ``min_coverage`` of the pixels
    matched, since then the coarse pass has not seen the scene."""
    values = disparity[matched & torch.isfinite(disparity)]
    if values.numel() == 0 or values.numel() < min_coverage * disparity.numel():
        return None
    q = torch.quantile(values.double() * factor, torch.tensor([quantile, 1.0 - quantile], dtype=torch.float64,
                                                                device=values.device))
    lo = max(math.floor(min_disp), math.floor(float(q[0]) - margin))
    hi = min(math.ceil(max_disp), math.ceil(float(q[1]) + margin) + 1)
    if hi - lo < 2:  # a degenerate coarse result (one disparity everywhere at the edge of the range)
        return None
    return lo, hi


def at_narrowed_bound(index: torch.Tensor, count: int, narrowed_low: bool, narrowed_high: bool) -> torch.Tensor:
    """(B, H, W) winner indices into a search of ``count`` disparities -> (B, H, W) bool: the winner sits on
    a bound that the narrowing moved (``narrowed_low``: the first disparity; ``narrowed_high``: the last)."""
    edge = torch.zeros_like(index, dtype=torch.bool)
    if narrowed_low:
        edge |= index == 0
    if narrowed_high:
        edge |= index == count - 1
    return edge


def outside_range(disparity: torch.Tensor, matched: torch.Tensor, factor: int, size: tuple[int, int],
                  lo: int, hi: int) -> torch.Tensor:
    """(B, h, w) coarse disparity and matches -> (B, H, W) bool at full resolution ``size``: pixels whose
    coarse block matched at a disparity outside the full-resolution search ``lo <= d < hi`` (with a pixel
    of slack), i.e. a surface that the narrowed search cannot see. Rows and columns beyond the coarse
    image (the remainder of H / factor) are never flagged. The flags grow by one coarse block, because a
    block on the border of such a surface averages it with its surroundings and matches at theirs."""
    d = disparity * factor
    flagged = matched & torch.isfinite(d) & ((d < lo - 1) | (d > hi))
    flagged = F.max_pool2d(flagged.unsqueeze(1).float(), 3, stride=1, padding=1)[:, 0] > 0
    up = flagged.repeat_interleave(factor, -2).repeat_interleave(factor, -1)
    out = torch.zeros((*disparity.shape[:-2], *size), dtype=torch.bool, device=disparity.device)
    h, w = min(size[0], up.shape[-2]), min(size[1], up.shape[-1])
    out[..., :h, :w] = up[..., :h, :w]
    return out
