"""Vertical alignment: measure how far the right image's rows sit from the left's, and resample it.

Matching searches along rows, so it assumes rectified images whose corresponding pixels share a row.
A rectification that is off by a quarter of a pixel already costs the census and gradient terms much of
their contrast on horizontal edges: in Middlebury's MiddEval3 scenes (which keep the imperfect
rectification of the 2014 capture, Scharstein et al., GCPR 2014) a misalignment of 0.2-0.4 px,
constant or growing across the image, is common, and a stereo camera whose calibration has drifted
shows the same. With a first disparity estimate (the coarse pass), the remaining vertical offset of
every textured pixel follows from Lucas-Kanade; a robust fit over the image of the field that a small
rotation of the cameras gives turns those into a smooth field, and the right image is resampled along its
columns by that field before the full-resolution pass.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from plugins.torch_sgm import cost, planes

# Tukey's biweight radius of the field's fit, in pixels: offsets further from the fit are mismatches
_FIT_RADIUS = 0.5
_FIT_ITERATIONS = 5
LANCZOS_LOBES = 3


def _central_gradients(grey: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, 1, H, W) -> d/dx, d/dy by central differences, (B, H, W) each."""
    padded = F.pad(grey, (1, 1, 1, 1), mode="replicate")
    gx = (padded[..., 1:-1, 2:] - padded[..., 1:-1, :-2]) / 2
    gy = (padded[..., 2:, 1:-1] - padded[..., :-2, 1:-1]) / 2
    return gx[:, 0], gy[:, 0]


def _sample(grey: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """(B, 1, H, W) image, (B, H, W) pixel coordinates -> (B, H, W) bilinear samples, border-clamped."""
    h, w = grey.shape[-2:]
    grid = torch.stack([2 * (x + 0.5) / w - 1, 2 * (y + 0.5) / h - 1], -1)
    return F.grid_sample(grey, grid, mode="bilinear", padding_mode="border", align_corners=False)[:, 0]


def vertical_offsets(left: torch.Tensor, right: torch.Tensor, disparity: torch.Tensor, radius: int = 3,
                     iterations: int = 6, max_offset: float = 2.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel row offset dy such that left(x, y) ~ right(x - disparity + dx, y + dy) over a
    (2 radius + 1)^2 window, by Lucas-Kanade (translation) iterations; dx, which absorbs the error of the
    first disparity, is solved for as well and dropped.

    left, right (B, 3, H, W) in [0, 1]; disparity (B, H, W) float, a first estimate that may be off by a
    pixel or two (finite everywhere) -> dy (B, H, W) and the smaller eigenvalue of each window's
    gradient matrix (B, H, W), which says how well the window pins both directions down.
    The gradients are the left image's (inverse compositional): they do not change between
    iterations, and they are not smoothed by the resampling of the right image."""
    grey_l, grey_r, gx, gy, (a, bxy, c) = gradient_windows(left, right, radius)
    b, _, h, w = left.shape
    ys, xs = torch.meshgrid(torch.arange(h, dtype=left.dtype, device=left.device),
                            torch.arange(w, dtype=left.dtype, device=left.device), indexing="ij")

    def window(t: torch.Tensor) -> torch.Tensor:
        return cost.box_mean(t[:, None], radius)[:, 0]

    det = a * c - bxy * bxy
    dx = torch.zeros_like(disparity)
    dy = torch.zeros_like(disparity)
    for _ in range(iterations):
        error = grey_l[:, 0] - _sample(grey_r, xs - disparity + dx, ys + dy)
        p, q = window(gx * error), window(gy * error)
        # tiny determinants belong to flat windows, which the eigenvalue test below discards anyway
        dx = (dx + (c * p - bxy * q) / (det + 1e-12)).clamp(-max_offset, max_offset)
        dy = (dy + (a * q - bxy * p) / (det + 1e-12)).clamp(-max_offset, max_offset)
    return dy, min_eigenvalue(a, bxy, c)


def gradient_windows(left: torch.Tensor, right: torch.Tensor, radius: int):
    """What ``vertical_offsets``' iterations read and do not change: the (B, 1, H, W) grey images, the left one's
    (B, H, W) central gradients gx, gy, and their (B, H, W) window means (gx^2, gx gy, gy^2)."""
    grey_l, grey_r = cost.to_grey(left), cost.to_grey(right)
    gx, gy = _central_gradients(grey_l)
    windows = tuple(cost.box_mean(t[:, None], radius)[:, 0] for t in (gx * gx, gx * gy, gy * gy))
    return grey_l, grey_r, gx, gy, windows


def min_eigenvalue(a: torch.Tensor, bxy: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """The smaller eigenvalue of each window's gradient matrix [[a, bxy], [bxy, c]]."""
    return (a + c) / 2 - torch.sqrt(((a - c) / 2) ** 2 + bxy * bxy)


def reliable_offsets(dy: torch.Tensor, min_eigen: torch.Tensor, matched: torch.Tensor,
                     max_offset: float = 1.5) -> torch.Tensor:
    """(B, H, W) -> (B, H, W) bool: the matched pixels whose window is more textured in both directions
    than the median matched window of its image, and whose offset did not run off."""
    out = torch.zeros_like(matched)
    for i in range(dy.shape[0]):
        if matched[i].any():
            floor = min_eigen[i][matched[i]].median()
            out[i] = matched[i] & (min_eigen[i] > floor) & (dy[i].abs() < max_offset)
    return out


def field_terms(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """The basis of a row-offset field at x, y (any shape, in units of the image's width and height,
    centred): (..., 5) x, y, 1, x y and y², the vertical component of a small relative rotation of the two
    cameras (pitch adds 1 + y², yaw x y, roll x) and of a difference in focal length (y), to first order."""
    return torch.stack(torch.broadcast_tensors(*_terms(x, y)), -1)


def _terms(x: torch.Tensor, y: torch.Tensor) -> list[torch.Tensor]:
    """``field_terms``' terms, each as broadcast from x and y (so (1, W) and (H, 1) give some of (H, W))."""
    return [x, y, torch.ones_like(x), x * y, y * y]


def fit_row_field(dy: torch.Tensor, reliable: torch.Tensor, min_pixels: int = 100) -> torch.Tensor:
    """Robust least-squares fit of dy to ``field_terms`` over the reliable pixels (Tukey's biweight,
    ``_FIT_RADIUS``), so that wrong first disparities do not tilt it.

    dy (B, H, W), reliable (B, H, W) bool -> (B, K) float64 coefficients; zeros (no correction) for an
    image with fewer than ``min_pixels`` reliable pixels."""
    b, h, w = dy.shape
    none = torch.zeros(0, dtype=torch.float64, device=dy.device)
    out = torch.zeros(b, field_terms(none, none).shape[-1], dtype=torch.float64, device=dy.device)
    for i in range(b):
        ys, xs = torch.nonzero(reliable[i], as_tuple=True)
        if ys.numel() < min_pixels:
            continue
        terms = field_terms(xs.double() / w - 0.5, ys.double() / h - 0.5).T.contiguous()  # (K, N)
        target = dy[i][reliable[i]].double()
        weight = torch.ones_like(target)
        for _ in range(_FIT_ITERATIONS):
            # the normal equations: a K x K system instead of a QR of tens of thousands of rows (the terms
            # are of order 1 over the centred image, so squaring their condition loses nothing in float64)
            weighted = terms * weight
            coeffs = torch.linalg.lstsq(weighted @ terms.T, (weighted @ target)[:, None]).solution[:, 0]
            residual = coeffs @ terms - target
            weight = planes.tukey_weight(residual, _FIT_RADIUS)
        out[i] = coeffs
    return out


def row_field(coeffs: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """(B, K) ``fit_row_field`` coefficients -> (B, H, W) float32 row offsets."""
    y = torch.arange(h, dtype=torch.float64, device=coeffs.device)[:, None] / h - 0.5
    x = torch.arange(w, dtype=torch.float64, device=coeffs.device)[None, :] / w - 0.5
    out = torch.zeros(coeffs.shape[0], h, w, dtype=torch.float64, device=coeffs.device)
    for k, term in enumerate(_terms(x, y)):  # term by term: no (H, W, K) stack of them
        out += coeffs[:, k, None, None] * term
    return out.float()


def lanczos(t: torch.Tensor, lobes: int = LANCZOS_LOBES) -> torch.Tensor:
    """The Lanczos kernel sinc(t) sinc(t / lobes) for |t| < lobes, else 0."""
    return torch.sinc(t) * torch.sinc(t / lobes) * (t.abs() < lobes)


def resample_rows(image: torch.Tensor, field: torch.Tensor, lobes: int = LANCZOS_LOBES) -> torch.Tensor:
    """(B, C, H, W) image, (B, H, W) offsets -> (B, C, H, W): pixel (x, y) takes the image at row
    y + field along its own column, interpolated with a Lanczos kernel (rows clamped at the border).
    A bilinear sample at a half-pixel offset averages two rows; the blur it adds to one image and not the
    other cost up to a point of Bad-1.0 on Middlebury (docs/research-log.md), and Lanczos keeps the
    texture sharp."""
    b, ch, h, w = image.shape
    y = torch.arange(h, dtype=field.dtype, device=field.device)[:, None] + field
    base = y.floor()
    frac = y - base
    out = torch.zeros_like(image)
    norm = torch.zeros_like(field)
    for k in range(1 - lobes, lobes + 1):
        weight = lanczos(frac - k, lobes)
        rows = (base + k).clamp(0, h - 1).long()
        out += weight[:, None] * image.gather(2, rows[:, None].expand(b, ch, h, w))
        norm += weight
    return out / norm[:, None]


def quantise(image: torch.Tensor, levels: int = 255) -> torch.Tensor:
    """Round to the 8-bit steps of the other image, so that census comparisons in flat areas tie
    (and break ties) the same way in both images."""
    return (image.clamp(0, 1) * levels).round() / levels


def upsample_disparity(disparity: torch.Tensor, matched: torch.Tensor, factor: int, size: tuple[int, int],
                       ) -> tuple[torch.Tensor, torch.Tensor]:
    """A coarse pass's (B, h, w) disparity (NaN or anything where not matched) and matched mask ->
    full-resolution (B, H, W) disparity (times ``factor``, 0 where unknown) and matched mask."""
    disp = torch.nan_to_num(torch.where(matched, disparity, torch.zeros_like(disparity)), 0.0)
    up = F.interpolate(disp[:, None], size=size, mode="bilinear", align_corners=False)[:, 0] * factor
    mask = F.interpolate(matched[:, None].float(), size=size, mode="nearest")[:, 0] > 0.5
    return up, mask

