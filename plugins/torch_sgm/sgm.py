"""Semi-Global Matching: 1-D dynamic programming along several image directions, summed.

Each path's recurrence runs over one image axis in a Python loop and is vectorised over the
other axis and over disparities.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

PATHS_4 = ((0, 1), (0, -1), (1, 0), (-1, 0))
PATHS_8 = PATHS_4 + ((1, 1), (1, -1), (-1, 1), (-1, -1))


def adaptive_p2(edge: torch.Tensor, p2: float, alpha: float, p1: float) -> torch.Tensor:
    """P2 / (1 + alpha * |edge|), never below P1 so the large-jump penalty stays the larger one.
    edge: (B, H, W) edge strength of the left image."""
    return (p2 / (1.0 + alpha * edge.abs())).clamp_min(p1)


def _shift_cross(prev: torch.Tensor, dy: int) -> tuple[torch.Tensor, torch.Tensor | None]:
    """prev (B, D, X) seen one row further along a diagonal path; also the rows lacking a predecessor."""
    if dy == 0:
        return prev, None
    big = torch.finfo(prev.dtype).max / 4
    if dy > 0:
        shifted = F.pad(prev[..., :-dy], (dy, 0), value=big)
        fresh = torch.zeros(prev.shape[-1], dtype=torch.bool, device=prev.device)
        fresh[:dy] = True
    else:
        shifted = F.pad(prev[..., -dy:], (0, -dy), value=big)
        fresh = torch.zeros(prev.shape[-1], dtype=torch.bool, device=prev.device)
        fresh[dy:] = True
    return shifted, fresh


def path_step(cost: torch.Tensor, prev: torch.Tensor, p1: float, p2: torch.Tensor) -> torch.Tensor:
    """One step of L(p, d) = C(p, d) + min(L(p-r, d), L(p-r, d±1) + P1, min_k L(p-r, k) + P2) - min_k L(p-r, k).

    cost, prev: (B, D, X); p2: (B, 1, X). Subtracting the minimum keeps L bounded."""
    floor = prev.min(1, keepdim=True).values
    big = torch.finfo(prev.dtype).max / 4
    up = F.pad(prev[:, :-1], (0, 0, 1, 0), value=big)
    down = F.pad(prev[:, 1:], (0, 0, 0, 1), value=big)
    best = torch.minimum(prev, torch.minimum(up, down) + p1)
    best = torch.minimum(best, floor + p2)
    return cost + best - floor


def walk(cost: torch.Tensor, p1: float, p2: torch.Tensor, step: int, cross: int, out: torch.Tensor) -> None:
    """Add one direction's path costs to ``out``, walking dim 1.

    cost, out: (B, N, D, X), contiguous so each step reads one block; p2: (B, N, X).
    step = +1 / -1 walks dim 1 forwards / backwards; cross = the predecessor's offset along X
    (0 for straight paths, ±1 for diagonals)."""
    n = cost.shape[1]
    prev = None
    for i in (range(n) if step > 0 else range(n - 1, -1, -1)):
        c = cost[:, i]
        if prev is None:
            current = c
        else:
            shifted, fresh = _shift_cross(prev, cross)
            current = path_step(c, shifted, p1, p2[:, i].unsqueeze(1))
            if fresh is not None:
                current = torch.where(fresh, c, current)
        out[:, i] += current
        prev = current


def sgm(cost: torch.Tensor, p1: float, p2: torch.Tensor | float, paths=PATHS_4) -> torch.Tensor:
    """cost: (B, D, H, W) -> (B, D, H, W) sum of the path costs over ``paths`` (directions (dy, dx)).
    p2: scalar or (B, H, W).

    Paths with dx != 0 walk the columns, all rows at once; vertical paths walk the rows. Each group
    works on a transposed contiguous copy; peak memory is about four volumes."""
    if not torch.is_tensor(p2):
        p2 = torch.full((cost.shape[0], *cost.shape[-2:]), float(p2), dtype=cost.dtype, device=cost.device)
    by_columns = [(dy, dx) for dy, dx in paths if dx]
    by_rows = [(dy, dx) for dy, dx in paths if not dx]
    cost_c = cost.permute(0, 3, 1, 2).contiguous()  # (B, W, D, H)
    out_c = torch.zeros_like(cost_c)
    p2_c = p2.transpose(1, 2).contiguous()
    for dy, dx in by_columns:
        walk(cost_c, p1, p2_c, dx, dy, out_c)
    del cost_c
    if by_rows:
        cost_r = cost.permute(0, 2, 1, 3).contiguous()  # (B, H, D, W)
        out_r = torch.zeros_like(cost_r)
        for dy, _ in by_rows:
            walk(cost_r, p1, p2, dy, 0, out_r)
        del cost_r
        out_c += out_r.permute(0, 3, 2, 1)
        del out_r
    return out_c.permute(0, 2, 3, 1).contiguous()
