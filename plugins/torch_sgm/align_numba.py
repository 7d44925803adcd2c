"""The vertical alignment's two whole-image stages compiled for the CPU with numba: ``align.vertical_offsets``'
Lucas-Kanade iterations (a bilinear sample, two window sums and an update of every pixel each, where torch
made a dozen whole-image passes) and ``align.resample_rows`` (each pixel's Lanczos taps along its column in
one pass, where torch built a weight map, a gather and a sum per tap). The ``align`` functions stay the
references the tests hold these to.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange

from plugins.torch_sgm import align, cost, sgm_numba
from plugins.torch_sgm.aggregate_numba import box_sums


@njit(cache=True, nogil=True, parallel=True)
def _resample_rows(image, field, lobes, out):
    """``align.resample_rows`` of the (B, C, H, W) image by the (B, H, W) field into ``out``."""
    n_b, n_c, h, w = image.shape
    third = math.pi / lobes
    taps = 2 * lobes
    cos_k, sin_k = np.empty(taps), np.empty(taps)
    for i in range(taps):
        cos_k[i], sin_k[i] = math.cos(third * (i + 1 - lobes)), math.sin(third * (i + 1 - lobes))
    for job in prange(n_b * h):
        b, y = job // h, job % h
        for x in range(w):
            at = y + field[b, y, x]
            base = math.floor(at)
            frac = at - base
            # sin(pi (frac - k)) is (-1)^k sin(pi frac), and sin(pi (frac - k) / lobes) follows from the sine and
            # cosine of pi frac / lobes: three trigonometric calls a pixel instead of two a tap
            s_pi = math.sin(math.pi * frac)
            s_lobe, c_lobe = math.sin(third * frac), math.cos(third * frac)
            norm = 0.0
            for c in range(n_c):
                out[b, c, y, x] = 0.0
            for i in range(taps):
                k = i + 1 - lobes
                t = frac - k
                if abs(t) >= lobes:
                    continue
                if t == 0.0:
                    weight = 1.0
                else:
                    sign = 1.0 if k % 2 == 0 else -1.0
                    near = sign * s_pi / (math.pi * t)
                    far = (s_lobe * cos_k[i] - c_lobe * sin_k[i]) / (third * t)
                    weight = near * far
                row = min(max(base + k, 0), h - 1)
                for c in range(n_c):
                    out[b, c, y, x] += weight * image[b, c, row, x]
                norm += weight
            for c in range(n_c):
                out[b, c, y, x] /= norm


def available(image: torch.Tensor) -> bool:
    """True where this kernel can stand in for ``align.resample_rows``: a CPU tensor of float32."""
    return sgm_numba.available(image)


def resample_rows_numba(image: torch.Tensor, field: torch.Tensor, lobes: int = align.LANCZOS_LOBES) -> torch.Tensor:
    """``align.resample_rows`` on the CPU: (B, C, H, W) float32 image, (B, H, W) row offsets -> (B, C, H, W)."""
    if not (available(image) and field.device.type == "cpu") or image.dim() != 4 or \
            field.shape != (image.shape[0], *image.shape[-2:]):
        raise ValueError(f"resample_rows_numba: needs a (B, C, H, W) float32 CPU image and (B, H, W) offsets, got "
                         f"{image.dtype} {tuple(image.shape)} on {image.device} and {tuple(field.shape)}")
    out = np.empty(tuple(image.shape), np.float32)
    with sgm_numba.torch_threads():
        _resample_rows(np.ascontiguousarray(image.numpy()), np.ascontiguousarray(field.numpy(), dtype=np.float32),
                       int(lobes), out)
    return torch.from_numpy(out)


@njit(cache=True, nogil=True, parallel=True)
def _sample_error(grey_l, grey_r, gx, gy, disp, dx, dy, gxe, gye):
    """Each pixel's error left - right at (x - disparity + dx, y + dy), the right image sampled bilinearly with
    its border repeated (``align._sample``), times the left image's gradients: into gxe, gye."""
    h, w = grey_l.shape
    for y in prange(h):
        for x in range(w):
            sx = min(max(x - disp[y, x] + dx[y, x], 0.0), w - 1.0)
            sy = min(max(y + dy[y, x], 0.0), h - 1.0)
            x0, y0 = int(sx), int(sy)
            fx, fy = sx - x0, sy - y0
            x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
            top = grey_r[y0, x0] + fx * (grey_r[y0, x1] - grey_r[y0, x0])
            bottom = grey_r[y1, x0] + fx * (grey_r[y1, x1] - grey_r[y1, x0])
            error = grey_l[y, x] - (top + fy * (bottom - top))
            gxe[y, x] = gx[y, x] * error
            gye[y, x] = gy[y, x] * error


@njit(cache=True, nogil=True, parallel=True)
def _lk_step(p, q, a, bxy, c, det, inv_count, max_offset, dx, dy):
    """One Lucas-Kanade update of (dx, dy) from the window sums p, q of gx e and gy e, as ``align.vertical_offsets``
    takes it."""
    h, w = p.shape
    for y in prange(h):
        for x in range(w):
            pp, qq = p[y, x] * inv_count[y, x], q[y, x] * inv_count[y, x]
            d = det[y, x] + 1e-12
            dx[y, x] = min(max(dx[y, x] + (c[y, x] * pp - bxy[y, x] * qq) / d, -max_offset), max_offset)
            dy[y, x] = min(max(dy[y, x] + (a[y, x] * qq - bxy[y, x] * pp) / d, -max_offset), max_offset)


def lucas_kanade_rows(grey_l: np.ndarray, grey_r: np.ndarray, gx: np.ndarray, gy: np.ndarray, windows: np.ndarray,
                      disparity: np.ndarray, radius: int, iterations: int, max_offset: float) -> np.ndarray:
    """``align.vertical_offsets``' iterations for one image on the CPU: the (H, W) float32 grey images and the left
    one's gradients, ``windows`` (4, H, W) its window means of gx^2, gx gy, gy^2 and their determinant, a first
    ``disparity`` -> (H, W) float32 row offsets dy. The window sums of each iteration are running sums in float64
    (``aggregate_numba.box_sums``), one pass down the image."""
    h, w = grey_l.shape
    inv_count = np.ascontiguousarray(cost.box_counts(h, w, radius).numpy())
    dx, dy = np.zeros((h, w), np.float32), np.zeros((h, w), np.float32)
    gxe, gye, p, q = (np.empty((h, w), np.float32) for _ in range(4))
    rows = np.empty((2, w))
    a, bxy, c, det = windows
    for _ in range(iterations):
        _sample_error(grey_l, grey_r, gx, gy, disparity, dx, dy, gxe, gye)
        box_sums(gxe, gye, radius, rows, p, q)
        _lk_step(p, q, a, bxy, c, det, inv_count, np.float32(max_offset), dx, dy)
    return dy


def vertical_offsets_numba(left: torch.Tensor, right: torch.Tensor, disparity: torch.Tensor, radius: int = 3,
                           iterations: int = 6, max_offset: float = 2.0) -> tuple[torch.Tensor, torch.Tensor]:
    """``align.vertical_offsets`` on the CPU, the same arguments and results: the gradients' window means as
    there, the Lucas-Kanade iterations compiled (``lucas_kanade_rows``)."""
    if not (available(left) and available(right) and available(disparity)):
        raise ValueError("vertical_offsets_numba: needs float32 CPU tensors")
    grey_l, grey_r, gx, gy, (a, bxy, c) = align.gradient_windows(left, right, radius)
    det = a * c - bxy * bxy
    windows = torch.stack([a, bxy, c, det], 1).numpy()
    dy = torch.empty_like(disparity)
    with sgm_numba.torch_threads():
        for i in range(left.shape[0]):
            dy[i] = torch.from_numpy(lucas_kanade_rows(
                np.ascontiguousarray(grey_l[i, 0].numpy()), np.ascontiguousarray(grey_r[i, 0].numpy()),
                np.ascontiguousarray(gx[i].numpy()), np.ascontiguousarray(gy[i].numpy()),
                np.ascontiguousarray(windows[i]), np.ascontiguousarray(disparity[i].numpy()), int(radius),
                int(iterations), float(max_offset)))
    return dy, align.min_eigenvalue(a, bxy, c)
