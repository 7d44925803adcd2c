"""Disparity selection: winner-takes-all with parabolic sub-pixel interpolation, and a uniqueness test."""
from __future__ import annotations

import torch

from plugins.torch_sgm.refine import left_right_check


def winner_takes_all(volume: torch.Tensor) -> torch.Tensor:
    """(B, D, H, W) cost -> (B, H, W) int64 index of the lowest cost (the first of equal ones)."""
    # min(1).indices gives argmin's answer, ties included, and on a CPU is about 3x faster than
    # argmin(1), which reduces over the strided disparity axis element by element
    return volume.min(1).indices


def _neighbour_costs(volume: torch.Tensor, index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Cost at index-1, index, index+1 (clamped to the range), each (B, H, W)."""
    d = volume.shape[1]
    lo = (index - 1).clamp(0, d - 1)
    hi = (index + 1).clamp(0, d - 1)
    return tuple(volume.gather(1, i.unsqueeze(1))[:, 0] for i in (lo, index, hi))


def _bounded(offset: torch.Tensor, index: torch.Tensor, d: int) -> torch.Tensor:
    """Offsets within ±0.5, and zero at the ends of the range where one neighbour is missing."""
    inner = (index > 0) & (index < d - 1)
    return torch.where(inner, offset.clamp(-0.5, 0.5), torch.zeros_like(offset))


def parabolic_subpixel(volume: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Refine integer indices (B, H, W) to float32 indices by fitting a parabola through the cost
    at index-1, index, index+1; the offset is bounded to ±0.5 and zero at the ends of the range."""
    c0, c1, c2 = _neighbour_costs(volume, index)
    curvature = c0 - 2 * c1 + c2
    offset = torch.where(curvature > 0, (c0 - c2) / (2 * curvature.clamp_min(1e-12)), torch.zeros_like(c1))
    offset = _bounded(offset, index, volume.shape[1])
    return index.to(volume.dtype) + offset


def unique_minimum(volume: torch.Tensor, index: torch.Tensor, ratio: float) -> torch.Tensor:
    """Pixels whose lowest cost beats every disparity more than one step away from it by ``ratio`` of
    itself: second > (1 + ratio) * best. A flat or repetitive surface has several near-equal minima,
    and SGM picks one of them with no more reason than noise; such a pixel is better filled than trusted.

    (B, D, H, W) cost, (B, H, W) int64 winner -> (B, H, W) bool. **Overwrites** ``volume`` (the three
    costs around each winner become inf), so that no second volume is needed: call it last."""
    d = volume.shape[1]
    best = volume.gather(1, index.unsqueeze(1))[:, 0]
    for step in (-1, 0, 1):
        volume.scatter_(1, (index + step).clamp(0, d - 1).unsqueeze(1), float("inf"))
    second = volume.min(1).values
    return second > (1.0 + ratio) * best


def right_view_wta(volume: torch.Tensor, disparities) -> torch.Tensor:
    """Winner-takes-all of the right image, read off the left volume: C_R(x, d) = C_L(x + d, d).

    (B, D, H, W) -> (B, H, W) float32 disparity (not index), NaN where no disparity lands inside
    the image. Walks the slices with a running minimum so no second volume is held."""
    b, _, h, w = volume.shape
    best = torch.full((b, h, w), float("inf"), dtype=volume.dtype, device=volume.device)
    disp = torch.full((b, h, w), float("nan"), dtype=volume.dtype, device=volume.device)
    for k, d in enumerate(disparities):
        if abs(d) >= w:
            continue
        src = volume[:, k, :, d:] if d >= 0 else volume[:, k, :, : w + d]
        dst = slice(0, w - d) if d >= 0 else slice(-d, w)
        better = src < best[..., dst]
        best[..., dst] = torch.where(better, src, best[..., dst])
        disp[..., dst] = torch.where(better, torch.full_like(src, float(d)), disp[..., dst])
    return disp


def checked_winners(volume: torch.Tensor, disparities, lr_tolerance: float,
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Winner-takes-all of both views read off one volume, and the left-right check between them.

    (B, D, H, W) cost over ``disparities`` (consecutive integers) -> (disparity (B, H, W) float32, refined
    by ``parabolic_subpixel``; its index (B, H, W) int64 into the volume; the right view's disparity
    (``right_view_wta``); consistent (B, H, W) bool, the pixels that ``left_right_check`` passes within
    ``lr_tolerance``). Leaves ``volume`` as it was, so that
    ``unique_minimum`` may still be called on it afterwards."""
    index = winner_takes_all(volume)
    disp = parabolic_subpixel(volume, index) + disparities[0]
    right_disp = right_view_wta(volume, disparities)
    return disp, index, right_disp, left_right_check(disp, right_disp, lr_tolerance)


def local_winners(volume: torch.Tensor, disparities, lr_tolerance: float = 1.0, checked=checked_winners) -> torch.Tensor:
    """The winners of the cost before SGM, where they pass their own left-right check.

    SGM carries a disparity across a textureless surface from whatever borders it, so on a flat tabletop
    its winners agree with each other and the checks pass them, but they belong to the surface beside
    it. The locally aggregated cost is noisy there instead of biased: its winners scatter, and those on
    the faint texture the surface has still lie on its plane (``planes.local_planes`` fits them).
    (B, D, H, W) cost over ``disparities`` (consecutive integers) -> (B, H, W) float32 disparity, parabolic
    sub-pixel, NaN where the right view's winner (read off the same volume) disagrees by more than
    ``lr_tolerance``. ``checked``: ``checked_winners`` or a compiled stand-in."""
    disp, _, _, consistent = checked(volume, disparities, lr_tolerance)
    return torch.where(consistent, disp, torch.full_like(disp, float("nan")))
