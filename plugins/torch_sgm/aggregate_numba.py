"""The cost aggregation of ``pipeline.cost_volume_fast`` compiled for the CPU with numba: both guided
filters and their blend by texture, one disparity slice at a time, so that a slice's few working arrays
stay in the processor's cache instead of each torch step streaming a chunk of slices through memory.
``aggregate.guided_filter`` and ``aggregate.blend_by_texture`` stay the references the tests hold it to.
"""
from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from plugins.torch_sgm import aggregate, sgm_numba
from plugins.torch_sgm.cost import box_counts


@njit(cache=True, nogil=True)
def _box_mean(x, radius, total, columns, acc, out):
    """``cost.box_mean`` of (N, H, W) ``x`` into ``out`` (the same shape and dtype), the same numbers: each pass's
    running sum accumulated in float64 and stored in x's dtype, as torch's ``cumsum`` does, and each window
    the difference of two of its entries over the window's pixel count, in x's dtype. Scratch: ``total``
    (W + 1,) and ``columns`` (H + 1, W) of x's dtype, ``acc`` (W,) float64."""
    n_img, h, w = x.shape
    r = radius
    one = total[:1].dtype.type(1)
    for i in range(n_img):
        # along the rows, into out
        for y in range(h):
            row, dst = x[i, y], out[i, y]
            s = 0.0
            total[0] = 0.0
            for j in range(w):
                s += row[j]
                total[j + 1] = s
            # the windows inside the row apart from those the borders cut: a pass LLVM vectorises
            inner_lo = min(r, w)
            inner_hi = max(w - r, inner_lo)
            count = one * (2 * r + 1)
            for p in range(inner_lo, inner_hi):
                dst[p] = (total[p + r + 1] - total[p - r]) / count
            for border in (range(0, inner_lo), range(inner_hi, w)):
                for p in border:
                    lo, hi = max(p - r, 0), min(p + r, w - 1) + 1
                    dst[p] = (total[hi] - total[lo]) / (one * (hi - lo))
        # down the columns of that, a row of running sums at a time
        for j in range(w):
            acc[j] = 0.0
            columns[0, j] = 0.0
        for y in range(h):
            for j in range(w):
                acc[j] += out[i, y, j]
                columns[y + 1, j] = acc[j]
        for y in range(h):
            lo, hi = max(y - r, 0), min(y + r, h - 1) + 1
            count = one * (hi - lo)
            dst, top, bottom = out[i, y], columns[hi], columns[lo]
            for j in range(w):
                dst[j] = (top[j] - bottom[j]) / count


def box_mean_numba(x: torch.Tensor, radius: int) -> torch.Tensor:
    """``cost.box_mean`` (the reference) of a float32 or float64 CPU tensor (..., H, W), compiled: the same
    numbers bit for bit, without the dozen torch calls a pass that were most of its time on a crop."""
    if x.device.type != "cpu" or x.dtype not in (torch.float32, torch.float64) or x.dim() < 2:
        raise ValueError(f"box_mean_numba: needs a float32 or float64 CPU tensor (..., H, W), got {x.dtype} "
                         f"{tuple(x.shape)} on {x.device}")
    if radius <= 0:
        return x
    h, w = x.shape[-2:]
    a = np.ascontiguousarray(x.reshape(-1, h, w).numpy())
    out = np.empty_like(a)
    _box_mean(a, int(radius), np.empty(w + 1, a.dtype), np.empty((h + 1, w), a.dtype), np.empty(w), out)
    return torch.from_numpy(out).reshape(x.shape)


@njit(cache=True, nogil=True)
def box_sums(first, second, radius, rows, out_first, out_second):
    """Window sums of two (H, W) arrays over the (2r+1)^2 window cut to the image, into the two outputs;
    ``rows`` is (2, W) float64 scratch for the running column sums (in float64, so that adding and taking
    away rows down the image leaves no drift). The two running sums along each row wait on their own
    previous additions only: taken together, each fills the other's wait."""
    h, w = first.shape
    row_a, row_b = rows[0], rows[1]
    for x in range(w):
        row_a[x] = 0.0
        row_b[x] = 0.0
    for y in range(min(radius, h - 1) + 1):
        for x in range(w):
            row_a[x] += first[y, x]
            row_b[x] += second[y, x]
    for y in range(h):
        # horizontal window sums of the column sums: a running sum along the row
        total_a, total_b = 0.0, 0.0
        for x in range(min(radius, w - 1) + 1):
            total_a += row_a[x]
            total_b += row_b[x]
        for x in range(w):
            out_first[y, x] = total_a
            out_second[y, x] = total_b
            if x + radius + 1 < w:
                total_a += row_a[x + radius + 1]
                total_b += row_b[x + radius + 1]
            if x - radius >= 0:
                total_a -= row_a[x - radius]
                total_b -= row_b[x - radius]
        if y + radius + 1 < h:
            for x in range(w):
                row_a[x] += first[y + radius + 1, x]
                row_b[x] += second[y + radius + 1, x]
        if y - radius >= 0:
            for x in range(w):
                row_a[x] -= first[y - radius, x]
                row_b[x] -= second[y - radius, x]


@njit(cache=True, nogil=True, fastmath=True)
def direct_box_sums(first, second, radius, cols, out_first, out_second):
    """``box_sums`` for a small radius, each window summed tap by tap in float32 (a few numbers: none of
    the drift of a running sum): down the columns a row at a time, then along the row. ``cols`` is
    (2, W + 2r) float32 scratch, or wider (its columns past W + 2r go unread). Every loop runs along a row
    with nothing carried from one pixel to the next, so the processor takes 8 pixels at once, where a
    running sum waits on its own previous addition at every pixel."""
    h, w = first.shape
    col_a, col_b = cols[0], cols[1]
    for x in range(cols.shape[1]):  # the margins stay zero: a window cut to the image
        col_a[x] = 0.0
        col_b[x] = 0.0
    in_a, in_b = col_a[radius:radius + w], col_b[radius:radius + w]
    for y in range(h):
        lo, hi = max(0, y - radius), min(h - 1, y + radius)
        _copy(first[lo], second[lo], in_a, in_b)
        for yy in range(lo + 1, hi + 1):
            _add(first[yy], second[yy], in_a, in_b)
        row_a, row_b = out_first[y], out_second[y]
        if radius == 1:
            for x in range(w):
                row_a[x] = col_a[x] + col_a[x + 1] + col_a[x + 2]
                row_b[x] = col_b[x] + col_b[x + 1] + col_b[x + 2]
        elif radius == 2:
            for x in range(w):
                row_a[x] = col_a[x] + col_a[x + 1] + col_a[x + 2] + col_a[x + 3] + col_a[x + 4]
                row_b[x] = col_b[x] + col_b[x + 1] + col_b[x + 2] + col_b[x + 3] + col_b[x + 4]
        else:
            _copy(col_a[:w], col_b[:w], row_a, row_b)
            for i in range(1, 2 * radius + 1):
                _add(col_a[i:i + w], col_b[i:i + w], row_a, row_b)


@njit(cache=True, nogil=True, fastmath=True, inline="always")
def _copy(a, b, to_a, to_b):
    for x in range(to_a.shape[0]):
        to_a[x] = a[x]
        to_b[x] = b[x]


@njit(cache=True, nogil=True, fastmath=True, inline="always")
def _add(a, b, to_a, to_b):
    for x in range(to_a.shape[0]):
        to_a[x] += a[x]
        to_b[x] += b[x]


DIRECT_MAX_RADIUS = 2  # up to this radius ``direct_box_sums`` (measured faster at 1 and 2)


@njit(cache=True, nogil=True)
def _window_sums(first, second, radius, rows, cols, out_first, out_second):
    if radius <= DIRECT_MAX_RADIUS:
        direct_box_sums(first, second, radius, cols, out_first, out_second)
    else:
        box_sums(first, second, radius, rows, out_first, out_second)


@njit(cache=True, nogil=True)
def _guided(p, guide, mean_i, inv_var, inv_count, radius, ip, mean_p, mean_ip, rows, cols, out):
    """He et al.'s guided filter of the (H, W) slice ``p`` with the guide's statistics; scratch arrays
    ip, mean_p, mean_ip (H, W), rows (2, W) float64 and cols (2, W + 2 radius) float32; the result into
    ``out``."""
    h, w = p.shape
    for y in range(h):
        for x in range(w):
            ip[y, x] = guide[y, x] * p[y, x]
    _window_sums(p, ip, radius, rows, cols, mean_p, mean_ip)
    for y in range(h):
        for x in range(w):
            mp = mean_p[y, x] * inv_count[y, x]
            a = (mean_ip[y, x] * inv_count[y, x] - mean_i[y, x] * mp) * inv_var[y, x]
            mean_ip[y, x] = a
            mean_p[y, x] = mp - a * mean_i[y, x]
    _window_sums(mean_ip, mean_p, radius, rows, cols, ip, out)  # the means of a and of b
    for y in range(h):
        for x in range(w):
            out[y, x] = (ip[y, x] * guide[y, x] + out[y, x]) * inv_count[y, x]


@njit(cache=True, nogil=True, parallel=True)
def _aggregate(raw, guide, wide_stats, wide_radius, detail_stats, detail_radius, weight, out):
    n_b, n_d, h, w = raw.shape
    for job in prange(n_b * n_d):
        b, k = job // n_d, job % n_d
        ip, mean_p, mean_ip = np.empty((h, w), np.float32), np.empty((h, w), np.float32), np.empty((h, w), np.float32)
        wide, rows = np.empty((h, w), np.float32), np.empty((2, w), np.float64)
        cols = np.empty((2, w + 2 * max(wide_radius, detail_radius)), np.float32)
        _guided(raw[b, k], guide[b], wide_stats[0, b], wide_stats[1, b], wide_stats[2, b], wide_radius, ip, mean_p,
                mean_ip, rows, cols, wide)
        if detail_radius < 0:
            # element by element: a whole-slice assignment compiles numba's shape check and its error message
            # into the kernel, which took its first compile from 7 to 13 s
            for y in range(h):
                for x in range(w):
                    out[b, k, y, x] = wide[y, x]
            continue
        if detail_radius == 0:
            detail = raw[b, k]
        else:
            detail = np.empty((h, w), np.float32)
            _guided(raw[b, k], guide[b], detail_stats[0, b], detail_stats[1, b], detail_stats[2, b], detail_radius,
                    ip, mean_p, mean_ip, rows, cols, detail)
        for y in range(h):
            for x in range(w):
                out[b, k, y, x] = detail[y, x] + weight[b, y, x] * (wide[y, x] - detail[y, x])


def _statistics(guide: torch.Tensor, radius: int, eps: float) -> np.ndarray:
    """(3, B, H, W) float32: the guide's local mean, 1 / (its local variance + eps), and 1 / the pixels in
    each window -- as ``aggregate.guide_statistics`` and ``cost.box_counts`` compute them."""
    _, mean_i, inv_var, _ = aggregate.guide_statistics(guide, radius, eps, box_mean_numba)
    counts = box_counts(*guide.shape[-2:], radius).expand(guide.shape[0], -1, -1)
    return np.ascontiguousarray(torch.stack([mean_i[:, 0], inv_var[:, 0], counts]).numpy())


class Guide:
    """What the aggregation of every disparity slice of one image reads, computed once: the (B, 1, H, W)
    grey guide, its statistics at ``radius`` and at ``detail_radius`` (-1: no narrow aggregation), and the
    (B, 1, H, W) ``weight`` of the wide one (``aggregate.texture_weight``; None with no narrow one)."""

    def __init__(self, guide: torch.Tensor, radius: int, detail_radius: int, eps: float, weight: torch.Tensor | None):
        if not sgm_numba.available(guide) or guide.dim() != 4 or radius < 1:
            raise ValueError(f"aggregate_numba.Guide: needs a (B, 1, H, W) float32 CPU guide and a radius of at "
                             f"least 1, got {guide.dtype} {tuple(guide.shape)} on {guide.device}, radius {radius}")
        self.shape = (guide.shape[0], *guide.shape[-2:])
        self.grey = np.ascontiguousarray(guide[:, 0].numpy())
        self.radius = int(radius)
        self.wide = _statistics(guide, radius, eps)
        self.detail_radius = int(detail_radius) if weight is not None else -1
        self.detail = _statistics(guide, detail_radius, eps) if self.detail_radius > 0 else self.wide
        self.weight = (np.ascontiguousarray(weight[:, 0].numpy()) if weight is not None
                       else np.zeros((1, 1, 1), np.float32))


def aggregate_numba(raw: torch.Tensor, guide: Guide, out: torch.Tensor | None = None) -> torch.Tensor:
    """The guided filter of radius ``guide.radius`` of each slice of ``raw`` (B, D, H, W) float32, blended
    by ``guide.weight`` with the one of ``guide.detail_radius`` (0: ``raw`` itself), as
    ``aggregate.blend_by_texture(guided_filter(.., detail_radius), guided_filter(.., radius), weight)``.
    Into ``out`` (B, D, H, W), a new tensor if not given, which is returned."""
    if not sgm_numba.available(raw) or raw.dim() != 4 or (raw.shape[0], *raw.shape[2:]) != guide.shape:
        raise ValueError(f"aggregate_numba: needs (B, D, H, W) float32 CPU costs for a {guide.shape} guide, got "
                         f"{raw.dtype} {tuple(raw.shape)} on {raw.device}")
    out = torch.empty_like(raw) if out is None else out
    with sgm_numba.torch_threads():
        _aggregate(raw.numpy(), guide.grey, guide.wide, guide.radius, guide.detail, guide.detail_radius,
                   guide.weight, out.numpy())
    return out
