"""``planes.region_planes`` compiled for the CPU with numba: the same RANSAC start, Tukey IRLS and support
test, one pixel at a time instead of a few dozen tensor operations per fit (on the line's small crops
those operations' overhead, not their arithmetic, made the slanted-plane filling a third of the stereo
time). ``planes.region_planes`` stays the reference the tests hold this one to; the triples are drawn
from the same seeded CPU generator, so both choose among the same hypotheses. ``planes.edge_magnitude``
on the CPU from OpenCV's filters (``edge_magnitude_opencv``), for the same reason.
"""
from __future__ import annotations

import math

import cv2
import numpy as np
import torch
from numba import njit

from plugins.torch_sgm import planes, sgm_numba
from plugins.torch_sgm.linalg_numba import solve3

COORD_SCALE = planes._COORD_SCALE


@njit(cache=True, nogil=True)
def _fit_pixels(index, matched, wanted, use_wanted, k, min_pixels, fit_max):
    """The regions to fit (``active``) and the matched pixels they are fitted to, as ``region_planes``
    chooses them: (active (k,) bool, pixels of active regions (flat indices), fit pixels)."""
    count = np.zeros(k, np.int64)
    want = np.zeros(k, np.int64)
    for i in range(index.size):
        if matched[i]:
            count[index[i]] += 1
        if use_wanted and wanted[i]:
            want[index[i]] += 1
    active = count >= min_pixels
    if use_wanted:
        active &= want > 0
    active[0] = False
    n_at = 0
    n_fit = 0
    for i in range(index.size):
        if active[index[i]]:
            n_at += 1
            if matched[i]:
                n_fit += 1
    at = np.empty(n_at, np.int64)
    fit_all = np.empty(n_fit, np.int64)
    a = f = 0
    for i in range(index.size):
        if active[index[i]]:
            at[a] = i
            a += 1
            if matched[i]:
                fit_all[f] = i
                f += 1
    step = max(1, -(-n_fit // fit_max))
    return active, at, fit_all[::step].copy()


@njit(cache=True, nogil=True)
def _eligible(region, k):
    """The regions with at least three fit pixels, ascending (the rows RANSAC draws triples for), and
    every region's count of fit pixels."""
    count = np.zeros(k, np.int64)
    for r in region:
        count[r] += 1
    return np.nonzero(count >= 3)[0], count


@njit(cache=True, nogil=True)
def _ransac(x, y, d, region, k, ids, count, draws, tolerance, voters_max):
    """``planes.ransac_planes`` over the fit pixels (all of them in regions of >= 3): (k, 3) float64,
    NaN for the regions not in ``ids``. ids, count: ``_eligible``'s; draws: (len(ids), samples, 3)
    float64 uniform in [0, 1)."""
    best = np.full((k, 3), np.nan)
    n_ids, samples = draws.shape[0], draws.shape[1]
    if n_ids == 0:
        return best
    row = np.full(k, -1, np.int64)
    for j in range(n_ids):
        row[ids[j]] = j
    # a stable counting sort by region: the pixels of each eligible region side by side, in their order
    start = np.zeros(k, np.int64)
    total = 0
    for j in range(n_ids):
        start[ids[j]] = total
        total += count[ids[j]]
    fill = start.copy()
    order = np.empty(total, np.int64)
    for i in range(region.size):
        if row[region[i]] >= 0:
            order[fill[region[i]]] = i
            fill[region[i]] += 1
    coeffs = np.empty((n_ids, samples, 3), np.float32)
    usable = np.zeros((n_ids, samples), np.bool_)
    m = np.empty((3, 3))
    rhs = np.empty(3)
    sol = np.empty(3)
    for j in range(n_ids):
        g = ids[j]
        for s in range(samples):
            for t in range(3):
                p = order[start[g] + int(draws[j, s, t] * count[g])]
                m[t, 0], m[t, 1], m[t, 2] = x[p], y[p], 1.0
                rhs[t] = d[p]
            ok = solve3(m, rhs, sol)
            for t in range(3):
                coeffs[j, s, t] = np.float32(sol[t]) if ok else np.float32(np.nan)
            usable[j, s] = ok and math.isfinite(coeffs[j, s, 0]) and math.isfinite(coeffs[j, s, 1]) \
                and math.isfinite(coeffs[j, s, 2])
    votes = np.zeros((n_ids, samples), np.float32)
    step = max(1, -(-total // voters_max))
    tol = np.float32(tolerance)
    one = np.float32(1.0)
    for v in range(0, total, step):
        p = order[v]
        j = row[region[p]]
        vx, vy, vd = np.float32(x[p]), np.float32(y[p]), np.float32(d[p])
        for s in range(samples):
            residual = coeffs[j, s, 0] * vx + coeffs[j, s, 1] * vy + coeffs[j, s, 2] * one - vd
            z = residual / tol
            vote = one - z * z
            if vote > 0:  # NaN fails too
                votes[j, s] += vote
    for j in range(n_ids):
        chosen, top = 0, np.float32(-np.inf)
        for s in range(samples):
            score = votes[j, s] if usable[j, s] else np.float32(-1.0)
            if score > top:
                chosen, top = s, score
        for t in range(3):
            best[ids[j], t] = np.float64(coeffs[j, chosen, t])
    return best


@njit(cache=True, nogil=True)
def _irls(x, y, d, region, k, weight, radii):
    """``planes._robust_fit``'s iterations from the pixels' starting ``weight``: (k, 3) float64."""
    coeffs = np.zeros((k, 3))
    m = np.empty((3, 3))
    rhs = np.empty(3)
    sol = np.empty(3)
    for it in range(radii.size + 1):
        sums = np.zeros((k, 9))
        for i in range(x.size):
            w, xi, yi, di = weight[i], x[i], y[i], d[i]
            s = sums[region[i]]
            s[0] += xi * xi * w
            s[1] += xi * yi * w
            s[2] += xi * w
            s[3] += yi * yi * w
            s[4] += yi * w
            s[5] += w
            s[6] += xi * di * w
            s[7] += yi * di * w
            s[8] += di * w
        for g in range(k):
            s = sums[g]
            m[0, 0], m[0, 1], m[0, 2] = s[0] + 1e-9, s[1], s[2]
            m[1, 0], m[1, 1], m[1, 2] = s[1], s[3] + 1e-9, s[4]
            m[2, 0], m[2, 1], m[2, 2] = s[2], s[4], s[5] + 1e-9
            rhs[0], rhs[1], rhs[2] = s[6], s[7], s[8]
            if solve3(m, rhs, sol):
                coeffs[g, 0], coeffs[g, 1], coeffs[g, 2] = sol[0], sol[1], sol[2]
            else:
                coeffs[g, 0] = coeffs[g, 1] = coeffs[g, 2] = np.nan
        if it < radii.size:
            for i in range(x.size):
                c = coeffs[region[i]]
                residual = c[0] * x[i] + c[1] * y[i] + c[2] - d[i]
                z = residual / radii[it]
                weight[i] = np.nan if math.isnan(z) else max(1.0 - z * z, 0.0) ** 2
    return coeffs


@njit(cache=True, nogil=True)
def _start_weights(x, y, d, region, start, radius):
    """Tukey's weight of each pixel's residual from its region's RANSAC plane; 0 where it has none."""
    weight = np.empty(x.size)
    for i in range(x.size):
        c = start[region[i]]
        z = (c[0] * x[i] + c[1] * y[i] + c[2] - d[i]) / radius
        weight[i] = 0.0 if math.isnan(z) else max(1.0 - z * z, 0.0) ** 2
    return weight


@njit(cache=True, nogil=True)
def _support_and_planes(x, y, d, region, coeffs, active, at, index, w, h, k, tolerance, inlier_share, plane, good):
    """The support test and every pixel of an active region's plane value (``plane`` float32, flat)."""
    inliers = np.zeros(k)
    total = np.zeros(k)
    for i in range(x.size):
        c = coeffs[region[i]]
        residual = c[0] * x[i] + c[1] * y[i] + c[2] - d[i]
        total[region[i]] += 1.0
        if abs(residual) < tolerance:
            inliers[region[i]] += 1.0
    for g in range(k):
        good[g] = active[g] and inliers[g] >= inlier_share * total[g]
    for p in at:
        c = coeffs[index[p]]
        ax = (p % w) / COORD_SCALE
        ay = ((p // w) % h) / COORD_SCALE
        plane[p] = np.float32(c[0] * ax + c[1] * ay + c[2])


def region_planes_numba(disp: torch.Tensor, matched: torch.Tensor, labels: torch.Tensor, min_pixels: int,
                        inlier_share: float, tolerance: float = 1.0, samples: int = 0,
                        wanted: torch.Tensor | None = None, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """``planes.region_planes`` on the CPU, with the same arguments and results: disp (B, H, W) float32,
    matched (B, H, W) bool, labels (B, H, W) int64 -> (plane (B, H, W) float32, NaN where not fitted;
    supported (B, H, W) bool). Up to float rounding: where two RANSAC hypotheses score within it, the
    other may be chosen."""
    if not sgm_numba.available(disp):
        raise ValueError(f"region_planes_numba: needs a float32 CPU tensor, got {disp.dtype} on {disp.device}")
    if disp.dim() != 3 or matched.shape != disp.shape or labels.shape != disp.shape:
        raise ValueError(f"region_planes_numba: disp {tuple(disp.shape)}, matched {tuple(matched.shape)} and "
                         f"labels {tuple(labels.shape)} must be the same (B, H, W)")
    b, h, w = disp.shape
    index = np.ascontiguousarray(labels.numpy().reshape(-1)).astype(np.int64, copy=False)
    k = int(index.max()) + 1 if index.size else 1
    use_wanted = wanted is not None
    wanted_flat = (np.ascontiguousarray(wanted.numpy().reshape(-1)) if use_wanted
                   else np.zeros(1, np.bool_))
    matched_flat = np.ascontiguousarray(matched.numpy().reshape(-1))
    active, at, fit = _fit_pixels(index, matched_flat, wanted_flat, use_wanted, k, min_pixels, planes._FIT_PIXELS)
    x = (fit % w).astype(np.float64) / COORD_SCALE
    y = ((fit // w) % h).astype(np.float64) / COORD_SCALE
    d = disp.numpy().reshape(-1)[fit].astype(np.float64)
    region = index[fit]
    if samples > 0:
        ids, count = _eligible(region, k)
        gen = torch.Generator().manual_seed(seed)
        draws = torch.rand(ids.size, samples, 3, generator=gen, dtype=torch.float64).numpy()
        start = _ransac(x, y, d, region, k, ids, count, draws, float(tolerance), planes._VOTERS)
        weight = _start_weights(x, y, d, region, start, planes._RANSAC_RADIUS)
        radii = np.array(planes._TUKEY_RADII_AFTER_RANSAC)
    else:
        weight = np.ones(x.size)
        radii = np.array(planes._TUKEY_RADII)
    coeffs = _irls(x, y, d, region, k, weight, radii)
    plane = np.full(b * h * w, np.nan, np.float32)
    good = np.zeros(k, np.bool_)
    _support_and_planes(x, y, d, region, coeffs, active, at, index, w, h, k, float(tolerance), float(inlier_share),
                        plane, good)
    return torch.from_numpy(plane.reshape(b, h, w)), torch.from_numpy(good[index].reshape(b, h, w))


def edge_magnitude_opencv(image: torch.Tensor, sigma: float) -> torch.Tensor:
    """``planes.edge_magnitude`` of a (B, C, H, W) float32 CPU image -> (B, H, W): the same Gaussian blur (its
    border mirrored without repeating the edge pixel, as kornia's) and normalised Sobel gradients (border
    repeated), by OpenCV's filters in place of kornia's convolutions."""
    if not sgm_numba.available(image) or image.dim() != 4:
        raise ValueError(f"edge_magnitude_opencv: needs a (B, C, H, W) float32 CPU image, got {image.dtype} "
                         f"{tuple(image.shape)} on {image.device}")
    size = 2 * int(round(4 * sigma)) + 1
    kernel = cv2.getGaussianKernel(size, sigma, cv2.CV_32F) if sigma > 0 else None
    out = np.zeros((image.shape[0], *image.shape[2:]), np.float32)
    for best, planes_of_b in zip(out, image.numpy()):
        for plane in planes_of_b:
            blurred = plane if kernel is None else cv2.sepFilter2D(plane, -1, kernel, kernel,
                                                                   borderType=cv2.BORDER_REFLECT_101)
            gx = cv2.Sobel(blurred, -1, 1, 0, ksize=3, scale=1 / 8, borderType=cv2.BORDER_REPLICATE)
            gy = cv2.Sobel(blurred, -1, 0, 1, ksize=3, scale=1 / 8, borderType=cv2.BORDER_REPLICATE)
            np.maximum(best, cv2.magnitude(gx, gy), out=best)
    return torch.from_numpy(out)


@njit(cache=True, nogil=True)
def _local_wanted(index, matched, wanted, size, max_matched):
    """``planes.local_planes``' regions worth its fit: ``wanted`` where fewer than ``max_matched`` of the
    region's pixels matched (``size``: each region's pixels)."""
    hits = np.zeros(size.size)
    for i in range(index.size):
        if matched[i]:
            hits[index[i]] += 1.0
    out = np.empty(index.size, np.bool_)
    for i in range(index.size):
        out[i] = wanted[i] and hits[index[i]] < max_matched * max(size[index[i]], 1.0)
    return out


@njit(cache=True, nogil=True)
def _take_local(index, plane, supported, extra, backed, local, tolerance, density, size):
    """``planes.planes_and_slopes``' merge of ``local_planes``: where no region plane is supported, the
    winners' plane ``extra``; supported where ``backed`` and its inliers cover ``density`` of the region
    (``size``: each region's pixels)."""
    inliers = np.zeros(size.size)
    for i in range(index.size):
        if np.isfinite(local[i]) and abs(local[i] - extra[i]) < tolerance:
            inliers[index[i]] += 1.0
    for i in range(index.size):
        g = index[i]
        if not supported[i]:
            plane[i] = extra[i]
            supported[i] = backed[i] and inliers[g] >= density * max(size[g], 1.0)


@njit(cache=True, nogil=True)
def _fill_level(index, plane, supported, w, slope, filled, todo):
    """One threshold's result into ``slope`` (``planes.row_slope`` where first found), ``filled`` and
    ``todo``, in place; all flat over (B, H, W) rows of ``w``."""
    for i in range(index.size):
        if supported[i] and not np.isfinite(slope[i]):
            x = i % w
            step = np.float32(np.nan)
            if x < w - 1 and index[i + 1] == index[i]:
                step = plane[i + 1] - plane[i]
            if not np.isfinite(step):
                step = np.float32(np.nan)
                if x > 0 and index[i - 1] == index[i]:
                    step = plane[i] - plane[i - 1]
            slope[i] = step
    for i in range(index.size):
        if todo[i] and supported[i]:
            filled[i] = plane[i]
            todo[i] = False


def planes_and_slopes_numba(filled: torch.Tensor, disp: torch.Tensor, matched: torch.Tensor,
                            magnitude: torch.Tensor, thresholds: list[float], min_pixels: int, inlier_share: float,
                            samples: int = 0, local: torch.Tensor | None = None,
                            local_test: tuple[float, float, float] | None = None,
                            seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """``planes.planes_and_slopes`` with ``region_planes_numba`` fits, on the CPU, with the same arguments
    and results; the bookkeeping between the fits (which regions to fit, the local winners' density test,
    the row slopes, the filling) in one pass each instead of some twenty tensor operations per threshold."""
    if not (sgm_numba.available(disp) and sgm_numba.available(filled)):
        raise ValueError(f"planes_and_slopes_numba: needs float32 CPU tensors, got {filled.dtype} and "
                         f"{disp.dtype} on {disp.device}")
    if not (filled.shape == disp.shape == matched.shape == magnitude.shape) or disp.dim() != 3:
        raise ValueError(f"planes_and_slopes_numba: filled {tuple(filled.shape)}, disp {tuple(disp.shape)}, "
                         f"matched {tuple(matched.shape)} and magnitude {tuple(magnitude.shape)} must be the "
                         "same (B, H, W)")
    if local is not None and local_test is None:
        raise ValueError("planes_and_slopes_numba: local winners given without their local_test")
    shape, w = disp.shape, disp.shape[-1]
    out = filled.numpy().reshape(-1).copy()
    matched_flat = np.ascontiguousarray(matched.numpy().reshape(-1))
    todo = ~matched_flat
    slope = np.full(out.size, np.nan, np.float32)
    if local is not None:
        local_flat = np.ascontiguousarray(local.numpy().reshape(-1))
        finite = torch.isfinite(local)
        inlier_share_local, density, max_matched = local_test
    for threshold in thresholds:
        if not todo.any():
            break
        labels = planes.edge_regions(magnitude, threshold)
        index = labels.numpy().reshape(-1)
        plane, supported = region_planes_numba(disp, matched, labels, min_pixels, inlier_share, samples=samples,
                                               wanted=torch.from_numpy(todo.reshape(shape)), seed=seed)
        plane, supported = plane.numpy().reshape(-1), supported.numpy().reshape(-1)
        if local is not None:
            size = np.bincount(index, minlength=1).astype(np.float64)  # each region's pixels, for both steps
            wanted = _local_wanted(index, matched_flat, todo & ~supported, size, float(max_matched))
            extra, backed = region_planes_numba(local, finite, labels, min_pixels, inlier_share_local, 1.0, samples,
                                                torch.from_numpy(wanted.reshape(shape)), seed)
            _take_local(index, plane, supported, extra.numpy().reshape(-1), backed.numpy().reshape(-1), local_flat,
                        1.0, float(density), size)
        _fill_level(index, plane, supported, w, slope, out, todo)
    return torch.from_numpy(out.reshape(shape)), torch.from_numpy(slope.reshape(shape))
