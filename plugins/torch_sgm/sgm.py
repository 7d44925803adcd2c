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


def path_p2(grey: torch.Tensor, paths, p2: float, alpha: float, p1: float) -> torch.Tensor:
    """One P2 map per path: p2 / (1 + alpha * |I(p) - I(p - r)|) for each direction r = (dy, dx) in
    ``paths``, never below P1 (Hirschmueller, PAMI 2008, adapts P2 to this intensity step).

    A gradient magnitude lowers P2 for every path through an edge pixel, so a path running along a
    shelf's edge may jump at every step, while the same edge does not tell a path that crosses it
    more than one that follows it. The step to the path's predecessor lowers P2 only where the path
    crosses the edge. grey (B, H, W) -> (B, len(paths), H, W); a pixel without a predecessor inside the
    image compares with itself (its path restarts there anyway)."""
    h, w = grey.shape[-2:]
    padded = F.pad(grey.unsqueeze(1), (1, 1, 1, 1), mode="replicate")[:, 0]
    steps = [(grey - padded[:, 1 - dy: 1 - dy + h, 1 - dx: 1 - dx + w]).abs() for dy, dx in paths]
    return (p2 / (1.0 + alpha * torch.stack(steps, 1))).clamp_min(p1)


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


def _per_path(p2: torch.Tensor | float, cost: torch.Tensor, paths) -> dict:
    """A scalar, (B, H, W) or per-path (B, len(paths), H, W) P2 -> {path: (B, H, W) map}."""
    if not torch.is_tensor(p2):
        p2 = torch.full((cost.shape[0], *cost.shape[-2:]), float(p2), dtype=cost.dtype, device=cost.device)
    if p2.dim() == 3:
        return {path: p2 for path in paths}
    if p2.shape[1] != len(paths):
        raise ValueError(f"{p2.shape[1]} P2 maps for {len(paths)} paths")
    return {path: p2[:, k] for k, path in enumerate(paths)}


def sgm(cost: torch.Tensor, p1: float, p2: torch.Tensor | float, paths=PATHS_4) -> torch.Tensor:
    """cost: (B, D, H, W) -> (B, D, H, W) sum of the path costs over ``paths`` (directions (dy, dx)).
    p2: scalar, (B, H, W), or (B, len(paths), H, W) with one map per path (``path_p2``).

    Paths with dx != 0 walk the columns, all rows at once; vertical paths walk the rows. Each group
    works on a transposed contiguous copy; peak memory is about four volumes."""
    penalty = _per_path(p2, cost, paths)
    by_columns = [(dy, dx) for dy, dx in paths if dx]
    by_rows = [(dy, dx) for dy, dx in paths if not dx]
    cost_c = cost.permute(0, 3, 1, 2).contiguous()  # (B, W, D, H)
    out_c = torch.zeros_like(cost_c)
    for dy, dx in by_columns:
        walk(cost_c, p1, penalty[dy, dx].transpose(1, 2).contiguous(), dx, dy, out_c)
    del cost_c
    if by_rows:
        cost_r = cost.permute(0, 2, 1, 3).contiguous()  # (B, H, D, W)
        out_r = torch.zeros_like(cost_r)
        for dy, dx in by_rows:
            walk(cost_r, p1, penalty[dy, dx], dy, 0, out_r)
        del cost_r
        out_c += out_r.permute(0, 3, 2, 1)
        del out_r
    return out_c.permute(0, 2, 3, 1).contiguous()


# --- Fast path -------------------------------------------------------------------------------------
# ``sgm`` above is the reference. ``sgm_fast`` gives the same sums with fewer, larger tensor operations:
# each walk advances both directions along an axis (and, for 8 paths, all three predecessor offsets)
# in one step on a (2, G, B, D, X) stack, every step writes into two alternating buffers, and the
# smoothness term uses min(t[d-1], t[d]) once for both neighbours instead of two padded shifts.


def _walk_both(cost: torch.Tensor, p1: float, p2: torch.Tensor, crosses: tuple[int, ...], out: torch.Tensor) -> None:
    """Add to ``out`` the path costs of walking dim 1 forwards and backwards, once per predecessor
    offset in ``crosses`` along X. cost, out: (B, N, D, X), views allowed; p2: (2, len(crosses), B, N, X),
    the forward walks' maps first (expanded views allowed)."""
    b, n, d, x = cost.shape
    g = len(crosses)
    bufs = [torch.empty(2, g, b, d, x, dtype=cost.dtype, device=cost.device) for _ in range(2)]
    pair = torch.empty(2, g, b, d - 1, x, dtype=cost.dtype, device=cost.device) if d > 1 else None
    floor = torch.empty(2, g, b, 1, x, dtype=cost.dtype, device=cost.device)
    prev = None
    for i in range(n):
        j = n - 1 - i  # the backward walk's position
        c = torch.stack((cost[:, i], cost[:, j])).unsqueeze(1)  # (2, 1, B, D, X)
        cur = bufs[i % 2]
        if prev is None:
            cur.copy_(c.expand_as(cur))
        else:
            # t = L(p-r, d) - min_k L(p-r, k): the predecessor shifted along X, less its minimum, in one
            # pass; pixels without a predecessor (t = 0) restart the path: L = C
            torch.amin(prev, 3, keepdim=True, out=floor)
            for k, dy in enumerate(crosses):
                if dy == 0:
                    torch.sub(prev[:, k], floor[:, k], out=cur[:, k])
                elif dy > 0:
                    torch.sub(prev[:, k, ..., :-dy], floor[:, k, ..., :-dy], out=cur[:, k, ..., dy:])
                    cur[:, k, ..., :dy].zero_()
                else:
                    torch.sub(prev[:, k, ..., -dy:], floor[:, k, ..., -dy:], out=cur[:, k, ..., :dy])
                    cur[:, k, ..., dy:].zero_()
            if pair is not None:
                torch.minimum(cur[..., 1:, :], cur[..., :-1, :], out=pair).add_(p1)
                torch.minimum(cur[..., 1:, :], pair, out=cur[..., 1:, :])
                torch.minimum(cur[..., :-1, :], pair, out=cur[..., :-1, :])
            step_p2 = torch.stack((p2[0, :, :, i], p2[1, :, :, j])).view(2, g, b, 1, x)
            torch.minimum(cur, step_p2, out=cur).add_(c)
        for k in range(g):
            out[:, i].add_(cur[0, k])
            out[:, j].add_(cur[1, k])
        prev = cur


def _to_columns(cost: torch.Tensor) -> torch.Tensor:
    """(B, D, H, W) -> contiguous (B, W, D, H), one 2-D transpose per disparity (several times faster
    on a CPU than ``permute(...).contiguous()``, which walks the whole volume with large strides)."""
    b, d, h, w = cost.shape
    out = torch.empty(b, w, d, h, dtype=cost.dtype, device=cost.device)
    for k in range(d):
        out[:, :, k].copy_(cost[:, k].transpose(-1, -2))
    return out


def sgm_fast(cost: torch.Tensor, p1: float, p2: torch.Tensor | float, paths=PATHS_4) -> torch.Tensor:
    """``sgm`` (the reference) for path sets that hold every direction with its opposite (PATHS_4,
    PATHS_8). cost: (B, D, H, W) -> (B, D, H, W); p2 as for ``sgm``."""
    if set(paths) not in (set(PATHS_4), set(PATHS_8)):
        # the walks below pair each direction with its mirror image of the same row step; other
        # sets (say only the two main diagonals) go to the reference
        return sgm(cost, p1, p2, paths)
    penalty = _per_path(p2, cost, paths)
    crosses = tuple(sorted({dy for dy, dx in paths if dx == 1}, key=abs))
    out = torch.zeros_like(cost)
    if any(dx == 0 for _, dx in paths):
        # Vertical paths step along H: each step's (B, D, W) slice is D rows of W contiguous values,
        # so they walk the volume as it is, through a (B, H, D, W) view. Walking forwards the
        # predecessor is the row above: direction (1, 0).
        rows = torch.stack([penalty[1, 0], penalty[-1, 0]]).unsqueeze(1)  # (2, 1, B, H, W)
        _walk_both(cost.permute(0, 2, 1, 3), p1, rows, (0,), out.permute(0, 2, 1, 3))
    if crosses:
        # Horizontal and diagonal paths step along W: a column slice would touch a cache line per
        # value, so they walk a transposed copy.
        cost_c = _to_columns(cost)  # (B, W, D, H)
        out_c = torch.zeros_like(cost_c)
        # walking forwards with cross dy the predecessor is (y - dy, x - 1): direction (dy, 1)
        columns = torch.stack([torch.stack([penalty[dy, step] for dy in crosses]) for step in (1, -1)])
        _walk_both(cost_c, p1, columns.transpose(-1, -2).contiguous(), crosses, out_c)
        del cost_c
        for k in range(cost.shape[1]):
            out[:, k].add_(out_c[:, :, k].transpose(-1, -2))
    return out
