"""``cost.cost_features`` and ``cost.fused_cost_chunk`` compiled for the CPU with numba: the three terms of
each voxel computed in registers and written once, where the torch version streams a chunk of slices through
memory about twenty times (one pass per operation) and, on a crop, spends most of its time starting those
operations; the zero-normalised colour from window sums in float64 instead of torch's cumulative sums.

numba has no vectorised exponential (its LLVM lacks Intel's SVML), and two per voxel left a compiled cost
no faster than torch's: ``exp_neg_`` is one in plain arithmetic that LLVM vectorises, 2^n built in the
float's exponent bits and 2^f by a polynomial, within 4e-8 of ``math.exp``.
``cost.cost_features`` and ``cost.fused_cost_chunk`` stay the references the tests hold these to.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange

from plugins.torch_sgm import cost, sgm_numba
from plugins.torch_sgm.aggregate_numba import box_sums

LOG2_E = 1.4426950408889634
# 2^f = e^(f ln 2) on -0.5 <= f <= 0.5 by its Taylor series to the 7th power (remainder below 2e-10)
POW2 = tuple(math.log(2.0) ** k / math.factorial(k) for k in range(8))


@njit(cache=True, inline="always", fastmath=True)
def exp_neg_(x, bits):
    """exp(-x) of the (n,) float32 ``x`` (x >= 0) in place; ``bits`` (n,) int32 scratch. Below 2^-126 (x
    over 87) the result stays at 2^-126 instead of going to 0."""
    pow2 = bits.view(np.float32)
    for i in range(x.shape[0]):
        u = min(x[i] * np.float32(LOG2_E), np.float32(126.0))  # exp(-x) = 2^-u = 2^-m * 2^(m - u)
        m = np.int32(u + np.float32(0.5))  # u >= 0, so truncation rounds: m - u lies in [-0.5, 0.5]
        f = np.float32(m) - u
        p = np.float32(POW2[7])
        p = p * f + np.float32(POW2[6])
        p = p * f + np.float32(POW2[5])
        p = p * f + np.float32(POW2[4])
        p = p * f + np.float32(POW2[3])
        p = p * f + np.float32(POW2[2])
        p = p * f + np.float32(POW2[1])
        p = p * f + np.float32(POW2[0])
        bits[i] = (np.int32(127) - m) << 23
        x[i] = p * pow2[i]


@njit(cache=True, inline="always")
def _shifted(row, d, out):
    """out[x] = row[x - d], the ends of ``row`` repeated where x - d leaves it (``cost.shift_right_image``)."""
    w = row.shape[0]
    lo = min(max(d, 0), w)
    hi = max(min(w + d, w), lo)
    for x in range(lo):
        out[x] = row[0]
    # slices, indexed from 0: an index that may be negative would be wrapped, pixel by pixel
    source, target = row[lo - d:hi - d], out[lo:hi]
    for i in range(hi - lo):
        target[i] = source[i]
    for x in range(hi, w):
        out[x] = row[w - 1]


@njit(cache=True, inline="always")
def _popcount(v):
    v = v - ((v >> 1) & 0x55555555)
    v = (v & 0x33333333) + ((v >> 2) & 0x33333333)
    v = (v + (v >> 4)) & 0x0F0F0F0F
    return (v + (v >> 8) + (v >> 16) + (v >> 24)) & 0x3F


@njit(cache=True, inline="always", fastmath=True)
def _take_term(row, term, bits, weight):
    """row -= weight * exp(-term), the (W,) ``term`` overwritten; ``bits`` (W,) int32 scratch."""
    exp_neg_(term, bits)
    for x in range(row.shape[0]):
        row[x] -= weight * term[x]


@njit(cache=True, inline="always", fastmath=True)
def _cost_row(zl, zr, cl, cr, gl, gr, b, y, d, weights, scales, row, shifted, words, term, bits):
    """Row y of image b's fused cost at disparity d into ``row`` (W,); shifted, term (W,) float32 and words,
    bits (W,) int32 scratch. Arguments as ``_fused_cost``'s."""
    w = row.shape[0]
    w_ad, w_census, w_grad = weights[0], weights[1], weights[2]
    for x in range(w):
        row[x] = w_ad + w_census + w_grad
    if w_ad != 0:
        for x in range(w):
            term[x] = 0.0
        for c in range(zl.shape[1]):
            _shifted(zr[b, c, y], d, shifted)
            left = zl[b, c, y]
            for x in range(w):
                term[x] += abs(left[x] - shifted[x])
        for x in range(w):
            term[x] *= scales[0]
        _take_term(row, term, bits, w_ad)
    if w_census != 0:
        for x in range(w):
            bits[x] = 0
        for j in range(cl.shape[1]):
            _shifted(cr[b, j, y], d, words)
            left_words = cl[b, j, y]
            for x in range(w):
                bits[x] += _popcount(left_words[x] ^ words[x])
        for x in range(w):
            term[x] = bits[x] * scales[1]
        _take_term(row, term, bits, w_census)
    if w_grad != 0:
        _shifted(gr[b, 0, y], d, shifted)
        left = gl[b, 0, y]
        for x in range(w):
            term[x] = abs(left[x] - shifted[x]) * scales[2]
        _take_term(row, term, bits, w_grad)


@njit(cache=True, nogil=True, parallel=True, fastmath=True)
def _fused_cost(zl, zr, cl, cr, gl, gr, d_first, weights, scales, out):
    """out (B, K, H, W): slice k the fused cost at disparity d_first + k. zl, zr (B, C, H, W) zero-normalised
    colour; cl, cr (B, N, H, W) int32 census words; gl, gr (B, 1, H, W) horizontal gradients; weights and
    scales (3,) float32: each term's weight and 1 / its lambda (the AD term's also / C)."""
    n_b, count, h, w = out.shape
    for job in prange(n_b * count * h):
        b, k, y = job // (count * h), (job // h) % count, job % h
        shifted, term = np.empty(w, np.float32), np.empty(w, np.float32)
        words, bits = np.empty(w, np.int32), np.empty(w, np.int32)
        _cost_row(zl, zr, cl, cr, gl, gr, b, y, d_first + k, weights, scales, out[b, k, y], shifted, words, term, bits)


@njit(cache=True, nogil=True, parallel=True)
def _zero_normalise(image, radius, eps, out):
    """``cost.zero_normalise`` of each (H, W) plane of the (N, H, W) float32 ``image`` into ``out``, from
    window sums of x and x^2 in float64 (``aggregate_numba.box_sums``) over the (2r+1)^2 window cut to the
    image."""
    n, h, w = image.shape
    for job in prange(n):
        plane, target = image[job], out[job]
        values, squares = np.empty((h, w), np.float64), np.empty((h, w), np.float64)
        for y in range(h):
            for x in range(w):
                values[y, x] = plane[y, x]
                squares[y, x] = values[y, x] * values[y, x]
        total, total2 = np.empty((h, w), np.float64), np.empty((h, w), np.float64)
        box_sums(values, squares, radius, np.empty((2, w), np.float64), total, total2)
        for y in range(h):
            rows = min(y + radius, h - 1) - max(y - radius, 0) + 1
            for x in range(w):
                count = rows * (min(x + radius, w - 1) - max(x - radius, 0) + 1)
                mean = total[y, x] / count
                var = max(total2[y, x] / count - mean * mean, 0.0)
                target[y, x] = (plane[y, x] - mean) / (np.sqrt(var) + eps)


@njit(cache=True, nogil=True, parallel=True)
def _census(grey, offsets, per_word, out):
    """``cost.pack_bits(cost.census_transform(grey, offsets))`` of the (N, H, W) ``grey`` into (N, words, H, W)
    ``out``: bit k (word k // per_word, bit k % per_word) set where the neighbour at offsets[k] (border
    repeated) is darker than the pixel."""
    n, h, w = grey.shape
    for job in prange(n * h):
        i, y = job // h, job % h
        for j in range(out.shape[1]):
            for x in range(w):
                out[i, j, y, x] = 0
        for k in range(offsets.shape[0]):
            yy = min(max(y + offsets[k, 0], 0), h - 1)
            word, bit = k // per_word, np.int32(1) << (k % per_word)
            for x in range(w):
                xx = min(max(x + offsets[k, 1], 0), w - 1)
                if grey[i, yy, xx] < grey[i, y, x]:
                    out[i, word, y, x] |= bit


def cost_features_numba(left: torch.Tensor, right: torch.Tensor, znorm_radius: int, census_offsets=cost.STAR_24,
                        znorm_eps: float = 1e-3) -> dict:
    """``cost.cost_features`` of a (B, 3, H, W) float32 CPU pair: the zero-normalised colour and the census
    words compiled, the gradients torch's."""
    if not (sgm_numba.available(left) and sgm_numba.available(right)) or left.dim() != 4 or left.shape != right.shape:
        raise ValueError(f"cost_features_numba: needs a (B, C, H, W) float32 CPU pair of one shape, got "
                         f"{left.dtype} {tuple(left.shape)} and {right.dtype} {tuple(right.shape)}")
    b, c, h, w = left.shape
    colour = np.ascontiguousarray(torch.stack([left, right]).numpy().reshape(2 * b * c, h, w))
    grey = torch.stack([cost.to_grey(left), cost.to_grey(right)])  # (2, B, 1, H, W)
    offsets = np.array(census_offsets, np.int64).reshape(-1, 2)
    words = np.empty((2 * b, -(-len(offsets) // cost.BITS_PER_WORD), h, w), np.int32)
    znorm = np.empty_like(colour)
    with sgm_numba.torch_threads():
        _zero_normalise(colour, int(znorm_radius), float(znorm_eps), znorm)
        _census(np.ascontiguousarray(grey.numpy().reshape(2 * b, h, w)), offsets, cost.BITS_PER_WORD, words)
    z = torch.from_numpy(znorm).view(2, b, c, h, w)
    codes = torch.from_numpy(words).view(2, b, -1, h, w)
    return {"zl": z[0], "zr": z[1], "cl": codes[0], "cr": codes[1],
            "gl": cost.horizontal_gradient(grey[0]), "gr": cost.horizontal_gradient(grey[1])}


def _term_arrays(features: dict, lam_ad: float, lam_census: float, lam_grad: float, w_ad: float, w_census: float,
                w_grad: float) -> tuple:
    """What ``_cost_row`` reads of ``cost.cost_features``: (zl, zr, cl, cr, gl, gr, weights, scales) as arrays."""
    arrays = tuple(np.ascontiguousarray(features[k].numpy()) for k in ("zl", "zr", "cl", "cr", "gl", "gr"))
    weights = np.array([w_ad, w_census, w_grad], np.float32)
    scales = np.array([1.0 / (arrays[0].shape[1] * lam_ad), 1.0 / lam_census, 1.0 / lam_grad], np.float32)
    return (*arrays, weights, scales)


def available(features: dict) -> bool:
    """True where this kernel can stand in for ``cost.fused_cost_chunk``: float32 CPU features."""
    floats = all(sgm_numba.available(features[k]) for k in ("zl", "zr", "gl", "gr"))
    return floats and features["cl"].device.type == "cpu" and features["cl"].dtype == torch.int32


def fused_cost_numba(features: dict, d_first: int, count: int, *, w_ad: float, w_census: float, w_grad: float,
                     lam_ad: float, lam_census: float, lam_grad: float) -> torch.Tensor:
    """``cost.fused_cost_chunk`` from the same ``cost.cost_features``: (B, count, H, W) float32, slice k the
    fused cost at disparity d_first + k."""
    if not available(features):
        raise ValueError("fused_cost_numba: needs the float32 CPU features of cost.cost_features")
    b, _, h, w = features["zl"].shape
    out = np.empty((b, count, h, w), np.float32)
    *arrays, weights, scales = _term_arrays(features, lam_ad, lam_census, lam_grad, w_ad, w_census, w_grad)
    with sgm_numba.torch_threads():
        _fused_cost(*arrays, int(d_first), weights, scales, out)
    return torch.from_numpy(out)
