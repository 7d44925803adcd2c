"""``refine.local_plane_fit``, ``refine.weighted_median`` and ``refine.out_of_view`` compiled for the CPU
with numba: the same arithmetic one pixel at a time instead of whole-map tensor passes per window offset
(which on the line's small crops cost more in per-operation overhead than in arithmetic). The ``refine``
functions stay the references the tests hold these to.
"""
from __future__ import annotations

import math

import cv2
import numpy as np
import torch
from numba import njit, prange

from plugins.torch_sgm import sgm_numba
from plugins.torch_sgm.cost_numba import exp_neg_
from plugins.torch_sgm.linalg_numba import solve3


@njit(cache=True, inline="always")
def _weight(image, b, y, x, yy, xx, u, v, inv_colour2, inv_space2):
    """The weight of pixel (yy, xx), at offset (v, u), in the window of pixel (y, x): by colour similarity
    and by distance, as ``refine.local_plane_fit`` and ``refine.weighted_median`` weigh it."""
    colour = 0.0
    for c in range(image.shape[1]):
        diff = image[b, c, yy, xx] - image[b, c, y, x]
        colour += diff * diff
    return math.exp(-colour * inv_colour2 - (u * u + v * v) * inv_space2)


@njit(cache=True, nogil=True, parallel=True, fastmath=True)
def _pair_weights(image, radius, inv_colour2, inv_space2, slot, weights):
    """The weight of every pair of pixels (p, p + (u, v)) with (v, u) after (0, 0) in reading order and
    within ``radius``, into ``weights[slot[v + r, u + r], b, y, x]`` (p = (y, x)): the weight is symmetric
    (the colour distance and the spatial one alike), so each pair's exponential is taken once for both
    pixels. 0 where p + (u, v) lies outside the image. A row of exponents at a time, then their
    exponentials in vector registers (``cost_numba.exp_neg_``)."""
    n_b, n_c, h, w = image.shape
    inv_colour2, inv_space2 = np.float32(inv_colour2), np.float32(inv_space2)
    for job in prange(n_b * h):
        b, y = job // h, job % h
        exponent, bits = np.empty(w, np.float32), np.empty(w, np.int32)
        for v in range(0, radius + 1):
            yy = y + v
            for u in range(-radius, radius + 1):
                if v == 0 and u <= 0:
                    continue
                target = weights[slot[v + radius, u + radius], b, y]
                lo, hi = max(0, -u), min(w, w - u)  # the pixels whose partner lies inside the image
                if yy >= h or lo >= hi:
                    for x in range(w):
                        target[x] = 0.0
                    continue
                for x in range(lo, hi):
                    exponent[x] = np.float32(u * u + v * v) * inv_space2
                # slices, indexed from 0: an index that may be negative would be wrapped, pixel by pixel
                sums = exponent[lo:hi]
                for c in range(n_c):
                    here, there = image[b, c, y, lo:hi], image[b, c, yy, lo + u:hi + u]
                    for i in range(hi - lo):
                        diff = there[i] - here[i]
                        sums[i] += diff * diff * inv_colour2
                exp_neg_(sums, bits[lo:hi])
                for x in range(lo):
                    target[x] = 0.0
                for x in range(lo, hi):
                    target[x] = exponent[x]
                for x in range(hi, w):
                    target[x] = 0.0


NAN_SAFE = {"nsz", "arcp", "contract", "afn", "reassoc"}  # fastmath less "nnan" and "ninf": NaN marks a hole
FIT_BLOCK = 64  # pixels of a row fitted together: their neighbours' weights stay in the L1 cache


@njit(cache=True, nogil=True, parallel=True, fastmath=NAN_SAFE)
def _plane_fit(disp, weights, slot, radius, tolerance, out):
    """Each pixel's weighted plane through the disparities of its window within ``tolerance`` of its own,
    from the pairs' weights (``_pair_weights``). For a block of a row at a time, first every neighbour's
    weight and weighted disparity (0 where it is out of tolerance, a hole or outside the image), then the
    window's nine moments as sums of those rows times each offset's coefficients: loops along the row
    that the processor runs several pixels at once, where a branch per neighbour kept each pixel scalar."""
    n_b, h, w = disp.shape
    tol = np.float32(tolerance)
    side = 2 * radius + 1
    k = side * side
    # each neighbour's coefficient in the moments s1, su, sv, suu, suv, svv (of the weights) and sd, sud, svd
    # (of the weighted disparities), the window in reading order
    coeff = np.empty((6, k))
    for j in range(k):
        u, v = float(j % side - radius), float(j // side - radius)
        coeff[0, j], coeff[1, j], coeff[2, j] = 1.0, u, v
        coeff[3, j], coeff[4, j], coeff[5, j] = u * u, u * v, v * v
    for job in prange(n_b * h):
        b, y = job // h, job % h
        wt = np.empty((k, FIT_BLOCK), np.float32)
        wr = np.empty((k, FIT_BLOCK), np.float32)
        acc = np.empty((9, FIT_BLOCK))
        m = np.empty((3, 3))
        r = np.empty(3)
        sol = np.empty(3)
        here = disp[b, y]
        for x0 in range(0, w, FIT_BLOCK):
            n = min(FIT_BLOCK, w - x0)
            for j in range(k):
                u, v = j % side - radius, j // side - radius
                yy = y + v
                wj, rj = wt[j], wr[j]
                for i in range(n):
                    wj[i] = 0.0
                    rj[i] = 0.0
                if yy < 0 or yy >= h:
                    continue
                there = disp[b, yy]
                lo, hi = max(x0, -u), min(x0 + n, w - u)  # where the neighbour lies inside the row
                if v == 0 and u == 0:
                    for x in range(lo, hi):
                        wj[x - x0] = 1.0  # rel = 0: the pixel's own, unless a hole (the fit skips it)
                    continue
                forward = v > 0 or (v == 0 and u > 0)
                # a pair's weight as the pixel first in reading order stored it
                row = weights[slot[v + radius, u + radius], b, y] if forward else weights[slot[radius - v, radius - u], b, yy]
                at = 0 if forward else u
                # slices, indexed from 0: an index that may be negative would be wrapped, pixel by pixel
                count = max(hi - lo, 0)
                near, far, pair = here[lo:lo + count], there[lo + u:lo + u + count], row[lo + at:lo + at + count]
                wo, ro = wj[lo - x0:lo - x0 + count], rj[lo - x0:lo - x0 + count]
                for i in range(count):
                    rel = far[i] - near[i]
                    ok = abs(rel) <= tol  # NaN fails too
                    weight = pair[i] if ok else np.float32(0.0)
                    wo[i] = weight
                    ro[i] = weight * rel if ok else np.float32(0.0)
            for q in range(9):
                for i in range(n):
                    acc[q, i] = 0.0
            for j in range(k):
                wj, rj = wt[j], wr[j]
                for q in range(6):
                    c = coeff[q, j]
                    if c != 0.0:
                        for i in range(n):
                            acc[q, i] += c * wj[i]
                for q in range(3):
                    c = coeff[q, j]
                    if c != 0.0:
                        for i in range(n):
                            acc[6 + q, i] += c * rj[i]
            for i in range(n):
                x = x0 + i
                d0 = here[x]
                out[b, y, x] = d0
                if not math.isfinite(d0):
                    continue
                m[0, 0], m[0, 1], m[0, 2] = acc[3, i], acc[4, i], acc[1, i]
                m[1, 0], m[1, 1], m[1, 2] = acc[4, i], acc[5, i], acc[2, i]
                m[2, 0], m[2, 1], m[2, 2] = acc[1, i], acc[2, i], acc[0, i]
                r[0], r[1], r[2] = acc[7, i], acc[8, i], acc[6, i]
                # the plane's value at the pixel: the third unknown, where the system has a finite solution
                solved = solve3(m, r, sol)
                shift = sol[2] if solved and math.isfinite(sol[0]) and math.isfinite(sol[1]) else math.nan
                if math.isfinite(shift) and abs(shift) <= tolerance:
                    out[b, y, x] = d0 + shift


def _pair_slots(radius: int) -> np.ndarray:
    """(2r+1, 2r+1) int64: the index of each offset (v, u) after (0, 0) in reading order, -1 elsewhere."""
    slot = np.full((2 * radius + 1, 2 * radius + 1), -1, np.int64)
    k = 0
    for v in range(0, radius + 1):
        for u in range(-radius, radius + 1):
            if v > 0 or u > 0:
                slot[v + radius, u + radius] = k
                k += 1
    return slot


PAIR_WEIGHT_BYTES = 32 * 2**20  # the most memory the pairs' weights of one band of rows take


def _plane_fit_paired(disp, image, radius, inv_colour2, inv_space2, tolerance, out):
    """The local plane fit from each pair's weight taken once (``_pair_weights``), as ``_windowed`` calls it:
    in bands of rows, each with ``radius`` rows of the image above and below it, so that the weights of a
    large image need not be held at once (a pixel's window lies inside its band's rows either way)."""
    slot = _pair_slots(radius)
    pairs = int(slot.max()) + 1
    n_b, h, w = disp.shape
    band = max(2 * radius + 1, PAIR_WEIGHT_BYTES // (pairs * n_b * w * 4))
    for top in range(0, h, band):
        lo, hi = max(0, top - radius), min(h, top + band + radius)
        weights = np.empty((pairs, n_b, hi - lo, w), np.float32)
        part = np.empty((n_b, hi - lo, w), disp.dtype)
        _pair_weights(image[:, :, lo:hi], radius, inv_colour2, inv_space2, slot, weights)
        _plane_fit(disp[:, lo:hi], weights, slot, radius, tolerance, part)
        rows = min(band, h - top)
        out[:, top: top + rows] = part[:, top - lo: top - lo + rows]


def local_plane_fit_numba(disp: torch.Tensor, image: torch.Tensor, radius: int, sigma_colour: float,
                          sigma_space: float, tolerance: float = 1.0) -> torch.Tensor:
    """``refine.local_plane_fit`` on the CPU: disp (B, H, W) float32, image (B, C, H, W) float32 ->
    (B, H, W); the same arguments and result (up to float rounding: the moments are summed in float64)."""
    return _windowed("local_plane_fit_numba", _plane_fit_paired, disp, image, radius, sigma_colour, sigma_space,
                     tolerance)


def _windowed(name, kernel, disp, image, radius, sigma_colour, sigma_space, last):
    """Check the maps, then run a window ``kernel`` of (disp, image, radius, 1 / sigma_colour^2,
    1 / sigma_space^2, ``last``, out) on torch's threads; ``disp`` itself at radius 0."""
    if not (sgm_numba.available(disp) and sgm_numba.available(image)):
        raise ValueError(f"{name}: needs float32 CPU tensors, got {disp.dtype} on {disp.device}")
    if disp.dim() != 3 or image.dim() != 4 or image.shape[0] != disp.shape[0] or image.shape[-2:] != disp.shape[-2:]:
        raise ValueError(f"{name}: disp (B, H, W) {tuple(disp.shape)} and image (B, C, H, W) "
                         f"{tuple(image.shape)} must match")
    if radius <= 0:
        return disp
    d = np.ascontiguousarray(disp.numpy())
    out = np.empty_like(d)
    with sgm_numba.torch_threads():
        kernel(d, np.ascontiguousarray(image.numpy()), int(radius), 1.0 / sigma_colour ** 2, 1.0 / sigma_space ** 2,
               float(last), out)
    return torch.from_numpy(out)


@njit(cache=True, nogil=True, parallel=True)
def _weighted_median(disp, image, radius, inv_colour2, inv_space2, wanted, out):
    """``refine.weighted_median`` of (B, H, W) ``disp`` at the (B, H, W) bool pixels ``wanted``, into ``out``."""
    n_b, h, w = disp.shape
    k = 2 * radius + 1
    for job in prange(n_b * h):
        b, y = job // h, job % h
        values = np.empty(k * k, disp.dtype)
        weights = np.empty(k * k)
        for x in range(w):
            out[b, y, x] = disp[b, y, x]
            if not wanted[b, y, x]:
                continue
            n = 0
            for v in range(-radius, radius + 1):
                yy = min(max(y + v, 0), h - 1)  # the border replicated, as the reference pads
                for u in range(-radius, radius + 1):
                    xx = min(max(x + u, 0), w - 1)
                    values[n] = disp[b, yy, xx]
                    weights[n] = _weight(image, b, y, x, yy, xx, u, v, inv_colour2, inv_space2)
                    n += 1
            order = np.argsort(values)
            total = weights.sum()
            running = 0.0
            at = k * k - 1
            for i in range(k * k):
                running += weights[order[i]]
                if not running < total / 2:
                    at = i
                    break
            out[b, y, x] = values[order[at]]


def weighted_median_numba(disp: torch.Tensor, image: torch.Tensor, radius: int, sigma_colour: float,
                          sigma_space: float, jump: float = 0.0) -> torch.Tensor:
    """``refine.weighted_median`` on the CPU: disp (B, H, W) float32 without holes, image (B, C, H, W)
    float32 -> (B, H, W); the same arguments and result (the weights are summed in float64, so where the
    running weight meets half the total within rounding a neighbouring value may be taken)."""
    return _windowed("weighted_median_numba", _weighted_median_spanning, disp, image, radius, sigma_colour, sigma_space,
                     jump)


def _weighted_median_spanning(disp, image, radius, inv_colour2, inv_space2, jump, out):
    """The weighted median at the pixels whose window spans more than ``jump`` (all where ``jump`` <= 0), as
    ``_windowed`` calls it: each window's largest and smallest value from OpenCV's dilation and erosion of the
    map (a window cut to the image), one vectorised pass each, where taking them pixel by pixel was nine
    tenths of this stage's time (a plate's windows mostly span less)."""
    if jump > 0:
        kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
        with np.errstate(over="ignore", invalid="ignore"):  # a map where nothing matched is NaN throughout
            wanted = np.stack([cv2.dilate(m, kernel) - cv2.erode(m, kernel) > jump for m in disp])
    else:
        wanted = np.ones(disp.shape, np.bool_)
    _weighted_median(disp, image, radius, inv_colour2, inv_space2, wanted, out)


@njit(cache=True, nogil=True, parallel=True)
def _out_of_view(disp, matched, labels, suspect):
    n_b, h, w = disp.shape
    for job in prange(n_b * h):
        b, y = job // h, job % h
        reference, region = math.nan, -1
        for x in range(w - 1, -1, -1):
            if not matched[b, y, x]:
                continue
            if reference > x and labels[b, y, x] == region:  # NaN compares false
                suspect[b, y, x] = True
            else:
                reference, region = disp[b, y, x], labels[b, y, x]


def out_of_view_numba(disp: torch.Tensor, matched: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """``refine.out_of_view`` on the CPU: disp (B, H, W) float32, matched (B, H, W) bool, labels (B, H, W)
    int64 -> (B, H, W) bool, the same pixels (each row walked once from the right, rows in parallel)."""
    if not sgm_numba.available(disp):
        raise ValueError(f"out_of_view_numba: needs a float32 CPU tensor, got {disp.dtype} on {disp.device}")
    if matched.shape != disp.shape or labels.shape != disp.shape or disp.dim() != 3:
        raise ValueError(f"out_of_view_numba: disp {tuple(disp.shape)}, matched {tuple(matched.shape)} and labels "
                         f"{tuple(labels.shape)} must be the same (B, H, W)")
    suspect = np.zeros(tuple(disp.shape), np.bool_)
    with sgm_numba.torch_threads():
        _out_of_view(np.ascontiguousarray(disp.numpy()), np.ascontiguousarray(matched.numpy()),
                     np.ascontiguousarray(labels.numpy()), suspect)
    return torch.from_numpy(suspect)
