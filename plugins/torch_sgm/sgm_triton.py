"""``sgm.sgm`` as a Triton kernel for CUDA: one program walks one path's line of pixels from end to end.

The torch versions advance a whole row or column per step: on a GPU each step is a handful of small
kernel launches, and WVGA with eight paths takes thousands of them. Here a path's recurrence along one
line of pixels (a row, a column or a diagonal) runs inside one program, all the lines of a direction in
parallel, so a direction is one launch. The volume is walked with each pixel's disparities side by side
(B, H, W, D), so a step reads one contiguous run of memory. ``sgm.sgm`` stays the reference the tests
hold this one to (on a machine without a GPU, through Triton's interpreter).
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np
import torch

from plugins.torch_sgm import sgm

try:
    import triton
    import triton.language as tl
except ImportError:  # torch without CUDA may come without Triton; the CPU has the numba kernel
    triton = None

BIG = 1e30  # a path cost no real one reaches, for the disparities beyond the range's ends (a constexpr there)


if triton is not None:
    # sizes left unspecialised: the crops of a live loop come in many sizes, and each specialisation is a compile
    @triton.jit(do_not_specialize=["n_lines", "n_most", "h", "w", "d_count"])
    def _walk(cost_ptr, p2_ptr, out_ptr, scratch_ptr, start_ptr, length_ptr, n_lines, n_most, h, w, d_count, p1,
              DY: tl.constexpr, DX: tl.constexpr, FIRST: tl.constexpr, BLOCK_D: tl.constexpr, BIG: tl.constexpr):
        """One line of pixels of one path direction (DY, DX): L(p) from L(p - r) along it, added to out.
        cost, out (B, H, W, D); p2 (B, H, W); start (lines, 2) int32 y, x of each line's first pixel; length
        (lines,) its pixel count, n_most the longest; scratch (B * lines or more, BLOCK_D + 2), BIG at both
        ends of each row: a program's previous path costs, read back shifted by one disparity either way."""
        line = tl.program_id(0)
        b = tl.program_id(1)
        y = tl.load(start_ptr + 2 * line)
        x = tl.load(start_ptr + 2 * line + 1)
        n = tl.load(length_ptr + line)
        d = tl.arange(0, BLOCK_D)
        inside = d < d_count
        upper = d + 1 < d_count
        own = scratch_ptr + (b * n_lines + line).to(tl.int64) * (BLOCK_D + 2) + 1
        pixel = ((b * h + y) * w + x).to(tl.int64)
        path = tl.load(cost_ptr + pixel * d_count + d, mask=inside, other=BIG)
        if FIRST:
            tl.store(out_ptr + pixel * d_count + d, path, mask=inside)
        else:
            total = tl.load(out_ptr + pixel * d_count + d, mask=inside, other=0.0)
            tl.store(out_ptr + pixel * d_count + d, total + path, mask=inside)
        # every program steps as often as the longest line, past its own end with its memory untouched: a
        # loop bound read from memory is a tensor, which Triton's interpreter cannot count to
        for i in range(1, n_most):
            y += DY
            x += DX
            on = i < n
            pixel = ((b * h + y) * w + x).to(tl.int64)
            here = tl.load(cost_ptr + pixel * d_count + d, mask=inside & on, other=BIG)
            p2 = tl.load(p2_ptr + pixel, mask=on, other=0.0)
            # the neighbours' costs: through memory, since a program cannot shift its values across lanes
            tl.store(own + d, path, mask=inside)
            tl.debug_barrier()
            below = tl.load(own + d - 1)
            above = tl.load(own + d + 1, mask=upper, other=BIG)
            floor = tl.min(tl.where(inside, path, BIG), axis=0)
            best = tl.minimum(tl.minimum(path, tl.minimum(below, above) + p1), floor + p2)
            path = here + best - floor
            # every lane has read the old costs before the next step overwrites them
            tl.debug_barrier()
            if FIRST:
                tl.store(out_ptr + pixel * d_count + d, path, mask=inside & on)
            else:
                total = tl.load(out_ptr + pixel * d_count + d, mask=inside & on, other=0.0)
                tl.store(out_ptr + pixel * d_count + d, total + path, mask=inside & on)


@lru_cache(maxsize=64)
def _lines(h: int, w: int, dy: int, dx: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor, int]:
    """The lines of pixels a path (dy, dx) walks: each starts at a pixel whose predecessor (y - dy, x - dx)
    lies outside the image, and runs until the image ends. -> (lines, 2) int32 y, x; (lines,) int32 length;
    the longest length."""
    ys, xs = np.mgrid[0:h, 0:w]
    first = (ys - dy < 0) | (ys - dy >= h) | (xs - dx < 0) | (xs - dx >= w)
    y, x = ys[first], xs[first]
    big = max(h, w)
    rows = np.where(dy > 0, h - y, np.where(dy < 0, y + 1, big))
    columns = np.where(dx > 0, w - x, np.where(dx < 0, x + 1, big))
    start = torch.from_numpy(np.stack([y, x], 1).astype(np.int32)).to(device)
    length = np.minimum(rows, columns).astype(np.int32)
    return start, torch.from_numpy(length).to(device), int(length.max())


def available(cost: torch.Tensor) -> bool:
    """True where this kernel can stand in for ``sgm.sgm``: Triton is installed and the tensor is float32
    on a CUDA device."""
    return triton is not None and cost.device.type == "cuda" and cost.dtype == torch.float32


def sgm_triton(cost: torch.Tensor, p1: float, p2: torch.Tensor | float, paths=sgm.PATHS_4,
               interpret: bool = False) -> torch.Tensor:
    """``sgm.sgm`` on CUDA: cost (B, D, H, W) float32 -> (B, D, H, W) sum of the path costs over ``paths``;
    p2 scalar, (B, H, W) or (B, len(paths), H, W) as there. The result is a view whose disparities lie
    side by side. ``interpret`` lets a CPU tensor through, for Triton's interpreter (TRITON_INTERPRET=1)."""
    if triton is None:
        raise ValueError("sgm_triton: Triton is not installed")
    if not (available(cost) or (interpret and cost.dtype == torch.float32)):
        raise ValueError(f"sgm_triton: needs a float32 CUDA tensor, got {cost.dtype} on {cost.device}")
    if cost.dim() != 4:
        raise ValueError(f"sgm_triton: cost must be (B, D, H, W), got {tuple(cost.shape)}")
    b, d_count, h, w = cost.shape
    penalty = sgm._per_path(p2, cost, paths)
    volume = cost.permute(0, 2, 3, 1).contiguous()  # (B, H, W, D)
    out = torch.empty_like(volume)  # the first path writes it
    block = triton.next_power_of_2(d_count)
    warps = max(1, min(4, block // 64))  # one warp per 64 disparities was the fastest on an H200
    # one row per line of the direction with the most (h + w - 1, a diagonal's); its BIG ends are never written,
    # so every direction reuses it
    scratch = torch.full((b * (h + w - 1), block + 2), BIG, dtype=cost.dtype, device=cost.device)
    for k, (dy, dx) in enumerate(paths):
        start, length, longest = _lines(h, w, dy, dx, cost.device)
        _walk[(len(length), b)](volume, penalty[dy, dx].to(cost.dtype).contiguous(), out, scratch, start, length,
                                len(length), longest, h, w, d_count, float(p1), DY=dy, DX=dx,
                                FIRST=k == 0, BLOCK_D=block, BIG=BIG, num_warps=warps)
    return out.permute(0, 3, 1, 2)
