"""``planes.planes_and_slopes`` compiled for the CPU with numba: the same regions, RANSAC start, Tukey IRLS,
support tests and filling, one pixel at a time instead of a few dozen tensor operations per fit (on the line's
small crops those operations' overhead, not their arithmetic, made the slanted-plane filling a third of the
stereo time), each region's plane kept as its coefficients and written only where a pixel takes it.
``planes.planes_and_slopes`` stays the reference the tests hold this one to; the triples are drawn from the
same seeded CPU generator, so both choose among the same hypotheses. ``planes.edge_magnitude`` on the CPU from
OpenCV's filters (``edge_magnitude_opencv``), for the same reason.
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
TOLERANCE = planes._SUPPORT_PX


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
def _support(x, y, d, region, coeffs, active, k, tolerance, inlier_share):
    """``region_planes``' support test: (k,) bool, an active region whose fit pixels lie within ``tolerance`` of
    its plane for at least ``inlier_share`` of them."""
    inliers = np.zeros(k)
    total = np.zeros(k)
    for i in range(x.size):
        c = coeffs[region[i]]
        residual = c[0] * x[i] + c[1] * y[i] + c[2] - d[i]
        total[region[i]] += 1.0
        if abs(residual) < tolerance:
            inliers[region[i]] += 1.0
    good = np.zeros(k, np.bool_)
    for g in range(k):
        good[g] = active[g] and inliers[g] >= inlier_share * total[g]
    return good


@njit(cache=True, inline="always")
def _plane_value(c, x, ay):
    """The float32 value of the plane ``c`` (3,) at column ``x`` of the row ``ay`` (its index over COORD_SCALE), as
    ``region_planes`` writes it."""
    return np.float32(c[0] * (x / COORD_SCALE) + c[1] * ay + c[2])


@njit(cache=True, inline="always")
def _plane_at(c, p, w, h):
    """``_plane_value`` at flat pixel ``p`` of (B, H, W) rows of ``w``."""
    return _plane_value(c, p % w, ((p // w) % h) / COORD_SCALE)


def _fit_values(fit: np.ndarray, values: np.ndarray, index: np.ndarray, w: int, h: int) -> tuple[np.ndarray, ...]:
    """The fit pixels (flat indices) as ``region_planes`` fits them: x, y (float64, in ``COORD_SCALE`` units),
    their values (float64) and their regions."""
    x = (fit % w).astype(np.float64) / COORD_SCALE
    y = ((fit // w) % h).astype(np.float64) / COORD_SCALE
    return x, y, values[fit].astype(np.float64), index[fit]


def _region_fits(index: np.ndarray, use: np.ndarray, values: np.ndarray, active: np.ndarray, count: np.ndarray,
                 w: int, h: int, samples: int, seed: int, inlier_share: float) -> tuple[np.ndarray, np.ndarray]:
    """``planes.region_planes`` of the ``active`` regions of the flat labels ``index``, fitted to their pixels ``use``
    (``count``: each region's) of ``values``: (the regions' planes (k, 3), which of them are supported (k,))."""
    k = active.size
    x, y, d, region = _fit_values(_chosen_pixels(index, use, active, count, planes._FIT_PIXELS), values, index, w, h)
    coeffs = _robust_planes(x, y, d, region, k, samples, TOLERANCE, seed)
    return coeffs, _support(x, y, d, region, coeffs, active, k, TOLERANCE, inlier_share)


def _robust_planes(x: np.ndarray, y: np.ndarray, d: np.ndarray, region: np.ndarray, k: int, samples: int,
                   tolerance: float, seed: int) -> np.ndarray:
    """``planes._robust_fit``: each of ``k`` regions' plane (k, 3) from its fit pixels, from RANSAC's best of
    ``samples`` triples drawn by the CPU generator seeded with ``seed`` (plain least squares with none)."""
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
    return _irls(x, y, d, region, k, weight, radii)


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
def _region_counts(index, k, matched, todo, finite, use_local):
    """Per region of the flat labels ``index``: its pixels (float64), its matched ones, its pixels still to fill,
    and its pixels with a finite winner (only ``use_local``)."""
    size = np.zeros(k)
    count_m, want, count_l = np.zeros(k, np.int64), np.zeros(k, np.int64), np.zeros(k, np.int64)
    for i in range(index.size):
        g = index[i]
        size[g] += 1.0
        if matched[i]:
            count_m[g] += 1
        if todo[i]:
            want[g] += 1
        if use_local and finite[i]:
            count_l[g] += 1
    return size, count_m, want, count_l


@njit(cache=True, nogil=True)
def _chosen_pixels(index, use, active, count, fit_max):
    """The pixels a region's plane is fitted to, as ``planes.region_planes`` chooses them (``count``: each region's
    pixels ``use``): the pixels ``use`` of ``active`` regions in raster order, every step-th so that at most
    ``fit_max`` remain."""
    n = 0
    for g in range(active.size):
        if active[g]:
            n += count[g]
    step = max(1, -(-n // fit_max))
    out = np.empty(-(-n // step), np.int64)
    taken = seen = 0
    for i in range(index.size):
        if use[i] and active[index[i]]:
            if seen % step == 0:
                out[taken] = i
                taken += 1
            seen += 1
    return out


@njit(cache=True, nogil=True)
def _dense(index, local, coeffs, active, w, h, tolerance, k):
    """Per region, its pixels whose finite winner in ``local`` lies within ``tolerance`` of its plane's float32
    value (``local_planes``' inliers counted against the whole region); 0 where the region is not ``active``."""
    inliers = np.zeros(k)
    for i in range(index.size):
        g = index[i]
        if active[g] and np.isfinite(local[i]) and abs(local[i] - _plane_at(coeffs[g], i, w, h)) < tolerance:
            inliers[g] += 1.0
    return inliers


@njit(cache=True, nogil=True)
def _fill_level(index, w, h, coeffs, good, local_coeffs, by_local, slope, filled, todo):
    """One threshold's result into ``slope`` (``planes.row_slope`` where first found), ``filled`` and ``todo``, in
    place, all flat over (B, H, W) rows of ``w``: a region ``good`` takes its plane ``coeffs``, one ``by_local``
    the winners' ``local_coeffs``, each pixel at its float32 value (``_plane_value``, a row at a time)."""
    value = np.empty(w, np.float32)
    taken = np.zeros(w, np.bool_)
    for row in range(index.size // w):
        first = row * w
        ay = (row % h) / COORD_SCALE
        for x in range(w):
            g = index[first + x]
            taken[x] = good[g] or by_local[g]
            if taken[x]:
                value[x] = _plane_value(coeffs[g] if good[g] else local_coeffs[g], x, ay)
        for x in range(w):
            if not taken[x]:
                continue
            i = first + x
            if not np.isfinite(slope[i]):
                step = np.float32(np.nan)
                if x < w - 1 and index[i + 1] == index[i]:
                    step = value[x + 1] - value[x]
                if not np.isfinite(step):
                    step = np.float32(np.nan)
                    if x > 0 and index[i - 1] == index[i]:
                        step = value[x] - value[x - 1]
                slope[i] = step
            if todo[i]:
                filled[i] = value[x]
                todo[i] = False


def planes_and_slopes_numba(filled: torch.Tensor, disp: torch.Tensor, matched: torch.Tensor,
                            magnitude: torch.Tensor, thresholds: list[float], min_pixels: int, inlier_share: float,
                            samples: int = 0, local: torch.Tensor | None = None,
                            local_test: tuple[float, float, float] | None = None,
                            seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """``planes.planes_and_slopes`` on the CPU, with the same arguments and results up to float rounding (where two
    RANSAC hypotheses score within it, the other may be chosen); each threshold in a few passes over the frame
    (the regions' counts, the fit pixels of each fit, the filling) that keep each region's plane as its
    coefficients, where the reference writes whole-frame planes and masks a dozen times."""
    if not (sgm_numba.available(disp) and sgm_numba.available(filled)):
        raise ValueError(f"planes_and_slopes_numba: needs float32 CPU tensors, got {filled.dtype} and "
                         f"{disp.dtype} on {disp.device}")
    if not (filled.shape == disp.shape == matched.shape == magnitude.shape) or disp.dim() != 3:
        raise ValueError(f"planes_and_slopes_numba: filled {tuple(filled.shape)}, disp {tuple(disp.shape)}, "
                         f"matched {tuple(matched.shape)} and magnitude {tuple(magnitude.shape)} must be the "
                         "same (B, H, W)")
    if local is not None and local_test is None:
        raise ValueError("planes_and_slopes_numba: local winners given without their local_test")
    shape, (h, w) = disp.shape, disp.shape[-2:]
    out = filled.numpy().reshape(-1).copy()
    values = np.ascontiguousarray(disp.numpy().reshape(-1))
    matched_flat = np.ascontiguousarray(matched.numpy().reshape(-1))
    edges = np.ascontiguousarray(magnitude.numpy())
    todo = ~matched_flat
    slope = np.full(out.size, np.nan, np.float32)
    use_local = local is not None
    local_flat = np.ascontiguousarray(local.numpy().reshape(-1)) if use_local else values[:1]
    finite = np.isfinite(local_flat) if use_local else matched_flat[:1]
    none = np.zeros((1, 3))
    for threshold in thresholds:
        if not todo.any():
            break
        labels, k = planes.connected_regions(edges <= np.float32(threshold))
        index = labels.reshape(-1)
        size, count_m, want, count_l = _region_counts(index, k, matched_flat, todo, finite, use_local)
        active = (count_m >= min_pixels) & (want > 0)
        active[0] = False
        coeffs, good = _region_fits(index, matched_flat, values, active, count_m, w, h, samples, seed,
                                    float(inlier_share))
        by_local, local_coeffs = np.zeros(k, np.bool_), none
        if use_local:
            share, density, max_matched = local_test
            # local_planes' regions: a pixel still to fill, no plane of their own, and too few pixels matched for
            # their matches to have said what they are
            wanted = (want > 0) & ~good & (count_m < max_matched * np.maximum(size, 1.0))
            active_l = (count_l >= min_pixels) & wanted
            active_l[0] = False
            local_coeffs, backed = _region_fits(index, finite, local_flat, active_l, count_l, w, h, samples, seed,
                                                float(share))
            inliers = _dense(index, local_flat, local_coeffs, active_l, w, h, TOLERANCE, k)
            by_local = ~good & backed & (inliers >= density * np.maximum(size, 1.0))
        _fill_level(index, w, h, coeffs, good, local_coeffs, by_local, slope, out, todo)
    return torch.from_numpy(out.reshape(shape)), torch.from_numpy(slope.reshape(shape))
