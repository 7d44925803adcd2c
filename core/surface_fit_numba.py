"""The surface fit's inner loops compiled with numba: the cubic B-spline the images are sampled from, the
Gauss-Newton system (one pass over a fit's pixels per step instead of some thirty NumPy operations on a few
thousand of them each) and its steps, the costs of the defect's offset search, the ring's and the region's cells,
the ring cells' consensus and the cells' robust mean.

The fit reads the right image between its pixels from the cubic B-spline through them (``spline_coefficients``,
``sample_rows``): of the kernels tried, the one whose samples a sub-pixel shift moves least (the
interpolating B-spline keeps frequencies near the pixel pitch that cubic convolution damps, and damps
differently at each fraction of a pixel; docs/research-log.md). A sample at a float32 position is a number
1 px from the left or top border and 2 px from the right or bottom one, as the four taps x - 1 .. x + 2 need.

``normal_equations`` is the Huber-weighted Gauss-Newton system of the model's residuals, ``gauss_newton`` the
steps taken with it, ``offset_costs`` the Huber costs of the defect's offset search; ``tests/test_surface_fit.py``
holds each kernel to NumPy's arithmetic on the same samples or cells.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

N_PARAMS = 11
E = 10  # surface_fit.E: the eyes' vertical offset
SPLINE_POLE = math.sqrt(3.0) - 2.0  # of the cubic B-spline's interpolation filter (Unser 1999)
SPLINE_HORIZON = 30  # terms of the mirrored start of its causal pass: the pole's 30th power is below 1e-17


@njit(cache=True, inline="always")
def _spline_weights(t):
    """The cubic B-spline's weights of the taps x - 1 .. x + 2 at ``t`` in [0, 1) past x."""
    s = 1.0 - t
    t2 = t * t
    t3 = t2 * t
    return s * s * s / 6.0, (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0, (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0, t3 / 6.0


@njit(cache=True, nogil=True)
def _spline_columns(c):
    """Each column of ``c`` (float64, in place) -> its cubic B-spline coefficients, the column mirrored beyond
    its ends: a causal and an anticausal first-order recursion (Unser, Aldroubi & Eden 1993), run down the
    rows so that each step is a pass along a row in memory order."""
    n, w = c.shape
    if n < 2:
        return
    z = SPLINE_POLE
    first = np.zeros(w)
    zk = 6.0
    for k in range(min(n, SPLINE_HORIZON)):
        row = c[k]
        for x in range(w):
            first[x] += zk * row[x]
        zk *= z
    for x in range(w):
        c[0, x] = first[x]
    for y in range(1, n):
        above, row = c[y - 1], c[y]
        for x in range(w):
            row[x] = 6.0 * row[x] + z * above[x]
    last, before = c[n - 1], c[n - 2]
    for x in range(w):
        last[x] = (z / (z * z - 1.0)) * (last[x] + z * before[x])
    for y in range(n - 2, -1, -1):
        below, row = c[y + 1], c[y]
        for x in range(w):
            row[x] = z * (below[x] - row[x])


SPLINE_ROW_BLOCK = 8  # rows whose recursions along the row advance together: each waits on its own last step


@njit(cache=True, nogil=True)
def _spline_rows(c):
    """``_spline_columns`` along each row of ``c`` (in place), a block of rows at a time."""
    h, n = c.shape
    if n < 2:
        return
    z = SPLINE_POLE
    for top in range(0, h, SPLINE_ROW_BLOCK):
        rows = c[top:min(top + SPLINE_ROW_BLOCK, h)]
        b = rows.shape[0]
        for r in range(b):
            first, zk = 0.0, 6.0
            for k in range(min(n, SPLINE_HORIZON)):
                first += zk * rows[r, k]
                zk *= z
            rows[r, 0] = first
        for x in range(1, n):
            for r in range(b):
                rows[r, x] = 6.0 * rows[r, x] + z * rows[r, x - 1]
        for r in range(b):
            rows[r, n - 1] = (z / (z * z - 1.0)) * (rows[r, n - 1] + z * rows[r, n - 2])
        for x in range(n - 2, -1, -1):
            for r in range(b):
                rows[r, x] = z * (rows[r, x + 1] - rows[r, x])


@njit(cache=True, nogil=True)
def _spline_coefficients(image, out):
    h, w = image.shape
    c = np.empty((h, w))
    for y in range(h):
        for x in range(w):
            c[y, x] = image[y, x]
    _spline_columns(c)
    _spline_rows(c)
    for y in range(h):
        for x in range(w):
            out[y, x] = c[y, x]


def spline_coefficients(image: np.ndarray) -> np.ndarray:
    """HxW image -> HxW float32: the coefficients of the cubic B-spline that passes through its pixels (the
    image mirrored beyond its border), which ``sample_rows`` reads."""
    if image.ndim != 2:
        raise ValueError(f"spline_coefficients: image {image.shape} must be HxW")
    out = np.empty(image.shape, np.float32)
    _spline_coefficients(np.asarray(image, dtype=np.float32), out)
    return out


@njit(cache=True, nogil=True)
def _rows_at(splines, r_lo, x_lo, e, lines):
    """The splines' vertical half, applied once: ``lines`` (K, R, C) <- each spline interpolated on the rows
    r_lo .. r_lo + R - 1 moved by ``e``, at the columns x_lo .. x_lo + C - 1. Rows on which no sample is a
    number (``_position``) are left as they were."""
    h = splines[0].shape[0]
    n_k, n_rows, n_cols = lines.shape
    for r in range(n_rows):
        yf = np.float64(np.float32(r_lo + r + e))
        if not (yf >= 1 and yf <= h - 3):
            continue
        y0 = int(np.floor(yf))
        wy0, wy1, wy2, wy3 = _spline_weights(yf - y0)
        for k in range(n_k):
            c = splines[k]
            s0, s1 = c[y0 - 1, x_lo:x_lo + n_cols], c[y0, x_lo:x_lo + n_cols]
            s2, s3 = c[y0 + 1, x_lo:x_lo + n_cols], c[y0 + 2, x_lo:x_lo + n_cols]
            line = lines[k, r]
            for j in range(n_cols):
                line[j] = wy0 * s0[j] + wy1 * s1[j] + wy2 * s2[j] + wy3 * s3[j]


@njit(cache=True, inline="always")
def _along_row(line, xf, x_lo):
    """The horizontal half: a row of ``_rows_at`` (its first column x_lo) at column ``xf``."""
    x0 = int(np.floor(xf))
    wx0, wx1, wx2, wx3 = _spline_weights(xf - x0)
    c0 = x0 - 1 - x_lo
    return wx0 * line[c0] + wx1 * line[c0 + 1] + wx2 * line[c0 + 2] + wx3 * line[c0 + 3]


@njit(cache=True, nogil=True)
def _sample_rows(splines, x, rows, e, out):
    h, w = splines[0].shape
    n_k, n = len(splines), x.size
    # every sample lies on a row ``rows + e``: the splines' vertical half is applied once to the rows and
    # columns the samples read, and each sample then reads four columns
    r_lo, r_hi, x_lo, x_hi = h, -1, w, -1
    for i in range(n):
        xf = np.float64(np.float32(x[i]))
        if xf >= 1 and xf <= w - 3:
            r_lo, r_hi = min(r_lo, rows[i]), max(r_hi, rows[i])
            x_lo, x_hi = min(x_lo, int(np.floor(xf)) - 1), max(x_hi, int(np.floor(xf)) + 2)
    n_rows, n_cols = max(r_hi - r_lo + 1, 0), max(x_hi - x_lo + 1, 0)
    lines = np.empty((n_k, n_rows, n_cols))
    _rows_at(splines, r_lo, x_lo, e, lines)
    for i in range(n):
        xf, inside = _position(x[i], rows[i] + e, h, w)
        if not inside:
            for k in range(n_k):
                out[k, i] = np.nan
            continue
        for k in range(n_k):
            out[k, i] = _along_row(lines[k, rows[i] - r_lo], xf, x_lo)


def sample_rows(splines: tuple[np.ndarray, ...], x: np.ndarray, rows: np.ndarray, e: float) -> np.ndarray:
    """The cubic B-splines of HxW float32 coefficients (``spline_coefficients``, all one shape) at float
    columns ``x`` (N,) of the integer ``rows`` (N,) moved by ``e`` -> (K, N) float32; NaN where a tap
    (x - 1 .. x + 2, likewise down the rows) leaves the image."""
    splines = tuple(np.ascontiguousarray(c) for c in splines)
    if not splines or any(c.ndim != 2 or c.dtype != np.float32 or c.shape != splines[0].shape for c in splines):
        raise ValueError(f"sample_rows: coefficients {[(c.shape, str(c.dtype)) for c in splines]} must be HxW "
                         "float32 of one shape")
    rows = np.asarray(rows)
    if np.shape(x) != rows.shape or rows.ndim != 1:
        raise ValueError(f"sample_rows: x {np.shape(x)} and rows {rows.shape} must be (N,) alike")
    whole = rows.astype(np.int64)
    if not np.array_equal(whole, rows):
        raise ValueError("sample_rows: rows must be whole numbers (each sample lies on a pixel row moved by e)")
    out = np.empty((len(splines), len(whole)))  # float64, as the Gauss-Newton system reads them: one kernel
    _sample_rows(splines, np.asarray(x, dtype=np.float64), whole, float(e), out)
    return out.astype(np.float32)


@njit(cache=True, inline="always")
def _position(x, y, h, w):
    """x at float32 precision, and whether the sample at (x, y) is a number: 1 px from the left and top
    border, 2 px from the right and bottom one."""
    xf, yf = np.float64(np.float32(x)), np.float64(np.float32(y))
    return xf, xf >= 1 and xf <= w - 3 and yf >= 1 and yf <= h - 3


MEDIAN_BINS = 256


@njit(cache=True, inline="always")
def _bin(value, lo, scale, last):
    return min(int((value - lo) * scale), last)


@njit(cache=True, nogil=True)
def _select(a, k):
    """The k-th least of ``a`` (0-based), reordering it: Hoare's quickselect, median-of-three pivots."""
    lo, hi = 0, a.size - 1
    while hi > lo:
        x, y, z = a[lo], a[(lo + hi) >> 1], a[hi]
        pivot = max(min(x, y), min(max(x, y), z))
        i, j = lo, hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while a[j] > pivot:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    return a[k]


@njit(cache=True, nogil=True)
def _median(x):
    """``np.median`` of a 1-D array without NaN. The values are first counted into bins of their range and
    only the middle one's are sorted out: the fit's residuals lie in runs along the image, on which a
    quickselect of all of them mispredicts a branch at every other value (five times as slow)."""
    n = x.size
    if n == 0:
        return np.nan
    lo, hi = x[0], x[0]
    for value in x:
        lo, hi = min(lo, value), max(hi, value)
    if not hi > lo:
        return lo
    last = MEDIAN_BINS - 1
    scale = MEDIAN_BINS / (hi - lo)
    counts = np.zeros(MEDIAN_BINS, np.int64)
    for value in x:
        counts[_bin(value, lo, scale, last)] += 1
    k = n // 2  # the upper middle value; with n even, the lower one is the k - 1-th
    below, b = 0, 0
    while below + counts[b] <= k:
        below += counts[b]
        b += 1
    inside = np.empty(counts[b])
    m = 0
    for value in x:
        if _bin(value, lo, scale, last) == b:
            inside[m] = value
            m += 1
    upper = _select(inside, k - below)
    if n % 2:
        return upper
    if k - below > 0:  # the lower middle value is in the same bin, below the upper one after the select
        lower = inside[0]
        for i in range(1, k - below):
            lower = max(lower, inside[i])
    else:  # the greatest of the bins below
        lower = -np.inf
        for value in x:
            if _bin(value, lo, scale, last) < b:
                lower = max(lower, value)
    return (lower + upper) / 2


@njit(cache=True, nogil=True)
def robust_scale(r):
    """1.4826 times the median absolute deviation from the median of a 1-D float64 array without NaN: the
    residuals' standard deviation where they are normal, whatever their outliers."""
    return 1.4826 * _median(np.abs(r - _median(r)))


@njit(cache=True, inline="always")
def _huber_weight(size, cut):
    """Huber's weight of a residual of absolute ``size`` cut at ``cut``."""
    return 1.0 if size <= cut else cut / max(size, 1e-12)


@njit(cache=True, inline="always")
def _model_samples(splines, u, v, du, dv, m, theta, idx):
    """Where the surface model at ``theta`` reads the right image for the pixels ``idx`` (columns (n,)), and each
    spline's samples there ((K, n), NaN where a sample is no number)."""
    n = idx.size
    xs, rows = np.empty(n), np.empty(n, np.int64)
    for t in range(n):
        i = idx[t]
        xs[t] = u[i] - (theta[0] + theta[1] * du[i] + theta[2] * dv[i] + theta[3] * m[i])
        rows[t] = int(v[i])
    sampled = np.empty((len(splines), n))
    _sample_rows(splines, xs, rows, theta[E], sampled)
    return xs, sampled


@njit(cache=True, nogil=True)
def _ring_cell_offsets(splines, right_saturated, lvals, usable, prior, u, v, du, dv, m, theta, idx, cell, k, huber_k,
                       scale_floor):
    h, w = splines[0].shape
    n = idx.size
    xs, sampled = _model_samples(splines, u, v, du, dv, m, theta, idx)
    r, j = np.empty(n), np.empty(n)
    ok = np.zeros(n, np.bool_)
    kept = np.empty(n)
    count = 0
    for t in range(n):
        i = idx[t]
        # the samples at float32, as ``sample_rows`` gives them
        rv, gx = np.float64(np.float32(sampled[0, t])), np.float64(np.float32(sampled[1, t]))
        column = min(max(int(np.rint(xs[t])), 0), w - 1)
        row = min(max(int(np.rint(v[i] + theta[E])), 0), h - 1)
        ok[t] = usable[i] and np.isfinite(rv) and not right_saturated[row, column] and prior[i] > 0
        gain = theta[4] + theta[5] * du[i] + theta[6] * dv[i] + theta[8] * m[i]
        r[t] = lvals[i] - gain * rv - theta[7] - theta[9] * m[i]
        j[t] = gain * gx
        if ok[t]:
            kept[count] = r[t]
            count += 1
    scale = robust_scale(kept[:count])
    if scale == 0.0:
        scale = scale_floor
    cut = huber_k * scale
    info, num = np.zeros(k), np.zeros(k)
    for t in range(n):
        a = abs(r[t])
        weight = _huber_weight(a, cut) if ok[t] else 0.0
        # a pixel whose sample is no number leaves its cell none (0 x NaN), as NumPy's sums do
        info[cell[t]] += weight * j[t] * j[t]
        num[cell[t]] += weight * j[t] * r[t]
    offset, sd = np.empty(k), np.empty(k)
    for c in range(k):
        offset[c] = -num[c] / max(info[c], 1e-12)
        sd[c] = scale / np.sqrt(max(info[c], 1e-12)) if info[c] > 0 else np.inf
    return offset, sd, ok


def ring_cell_offsets(lvals: np.ndarray, splines: tuple[np.ndarray, np.ndarray], right_saturated: np.ndarray,
                      usable: np.ndarray, prior: np.ndarray, u: np.ndarray, v: np.ndarray, du: np.ndarray,
                      dv: np.ndarray, m: np.ndarray, theta: np.ndarray, idx: np.ndarray, cell: np.ndarray, k: int,
                      huber_k: float, scale_floor: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each of ``k`` cells' disparity offset from the surface model at ``theta``, by one Gauss-Newton step on its
    pixels ``idx`` (``cell``: each one's cell), Huber-weighted at the pixels' robust scale (``scale_floor`` where
    it is 0), and its standard deviation (inf for a cell with no gradient). A cell one of whose samples leaves the
    image has no number. Arguments as ``normal_equations``' (the splines of the right image and of its horizontal
    gradient alone). Returns (offsets (k,), sds (k,), usable (n,): the pixels that entered)."""
    _check_fit_arrays("ring_cell_offsets", 2, lvals, splines, right_saturated, usable, prior, u, v, du, dv, m, theta)
    if np.shape(cell) != np.shape(idx):
        raise ValueError(f"ring_cell_offsets: cell {np.shape(cell)} must be as idx {np.shape(idx)}")
    f64 = np.float64
    return _ring_cell_offsets(tuple(splines), right_saturated, lvals.astype(f64, copy=False), usable,
                              prior.astype(f64, copy=False), u, v, du, dv, m.astype(f64, copy=False),
                              theta.astype(f64, copy=False), np.asarray(idx, np.int64), np.asarray(cell, np.int64),
                              int(k), float(huber_k), float(scale_floor))


@njit(cache=True, nogil=True)
def _cell_steps(splines, u, rows, e, plane, gain, lv, o_surface, o_defect, p, cell, k, start, scale, huber_k,
                iterations, max_step, tolerance):
    n = u.size
    offsets = np.full(k, start)
    step = np.zeros(k)
    j = np.zeros(n)
    x = np.empty(n)
    sampled = np.empty((2, n))
    cut = huber_k * scale
    for _ in range(iterations):
        for i in range(n):
            x[i] = u[i] - plane[i] - offsets[cell[i]]
        _sample_rows(splines, x, rows, e, sampled)
        num, den = np.zeros(k), np.zeros(k)
        for i in range(n):
            # the samples at float32, as ``sample_rows`` gives them
            rv, gx = np.float64(np.float32(sampled[0, i])), np.float64(np.float32(sampled[1, i]))
            if np.isfinite(rv) and np.isfinite(gx) and p[i] > 0:
                r = lv[i] - gain[i] * rv - o_surface - o_defect
                j[i] = gain[i] * gx
            else:
                r, j[i] = 0.0, 0.0
            a = abs(r)
            h = _huber_weight(a, cut) * p[i]
            num[cell[i]] += h * j[i] * r
            den[cell[i]] += h * j[i] * j[i]
        settled = True
        for c in range(k):
            step[c] = -num[c] / max(den[c], 1e-12) if den[c] > 0 else 0.0
            offsets[c] += min(max(step[c], -max_step), max_step)
            settled &= abs(step[c]) < tolerance
        if settled:
            break
    return offsets, step, j


def cell_steps(splines: tuple[np.ndarray, np.ndarray], u: np.ndarray, rows: np.ndarray, e: float, plane: np.ndarray,
               gain: np.ndarray, lv: np.ndarray, exposure_offsets: tuple[float, float], p: np.ndarray, cell: np.ndarray,
               k: int, start: float, scale: float, huber_k: float, iterations: int, max_step: float,
               tolerance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each of ``k`` cells' own disparity offset by Gauss-Newton on its pixels, the plane and exposure held:
    pixel i (of N) reads the right image's spline and its gradient's (``splines``, HxW float32) at column
    ``u - plane - offset`` of row ``rows + e``; residual ``lv - gain * R - o - o_m`` (``exposure_offsets``: the
    surface's exposure offset and the defect's own), Huber-weighted at ``huber_k * scale`` times its share ``p``;
    each step clipped to ``max_step``, until every cell's step is below ``tolerance`` or after ``iterations``.
    u, plane, gain, lv, p: (N,) float64; rows, cell: (N,) int.
    Returns (offsets (k,), the last steps (k,), each pixel's derivative by the disparity at the last
    iteration's offsets (N,), 0 where its sample is no number)."""
    if len(splines) != 2 or any(c.ndim != 2 or c.dtype != np.float32 or c.shape != splines[0].shape for c in splines):
        raise ValueError(f"cell_steps: splines {[(np.shape(c), str(np.asarray(c).dtype)) for c in splines]} must be "
                         "two HxW float32 of one shape")
    n = len(u)
    for name, array in (("rows", rows), ("plane", plane), ("gain", gain), ("lv", lv), ("p", p), ("cell", cell)):
        if np.shape(array) != (n,):
            raise ValueError(f"cell_steps: {name} {np.shape(array)} must be ({n},) as u")
    f64 = np.float64
    return _cell_steps(tuple(np.ascontiguousarray(c) for c in splines), np.asarray(u, f64),
                       np.asarray(rows, np.int64), float(e), np.asarray(plane, f64), np.asarray(gain, f64),
                       np.asarray(lv, f64), float(exposure_offsets[0]), float(exposure_offsets[1]), np.asarray(p, f64),
                       np.asarray(cell, np.int64), int(k), float(start), float(scale), float(huber_k), int(iterations),
                       float(max_step), float(tolerance))


@njit(cache=True, nogil=True)
def _tukey_mean(x, s, prior, start, iterations, cut_k):
    mu = start
    n = x.size
    w = np.ones(n)
    scaled = np.empty(n)
    for _ in range(iterations):
        for i in range(n):
            scaled[i] = abs(x[i] - mu) / s[i]
        spread = max(1.0, 1.4826 * _median(scaled))
        total = 0.0
        for i in range(n):
            z = (x[i] - mu) / (cut_k * s[i] * spread)
            w[i] = (1 - z * z) ** 2 if abs(z) < 1 else 0.0
            total += w[i]
        if total <= 0:
            w[:] = 1.0
        num, den = 0.0, 0.0
        for i in range(n):
            num += w[i] * prior[i] * x[i]
            den += w[i] * prior[i]
        new = num / den
        done = abs(new - mu) < 1e-6
        mu = new
        if done:
            break
    return mu, w


@njit(cache=True, nogil=True)
def _tukey_offset(x, s, prior, start, iterations, cut_k, birge_z, birge_min):
    mu, w = _tukey_mean(x, s, prior, start, iterations, cut_k)
    total = 0.0
    for i in range(x.size):
        total += w[i] * prior[i]
    variance, weight, kept, chi2, kept_weight = 0.0, 0.0, 0, 0.0, 0.0
    for i in range(x.size):
        alpha = w[i] * prior[i] / total
        variance += alpha * alpha * s[i] * s[i]
        weight += w[i]
        if w[i] > 0:
            z = (x[i] - mu) / s[i]
            chi2 += w[i] * (z * z)
            kept += 1
            kept_weight += w[i]
    birge = 1.0
    if kept >= 2:
        dof = kept_weight - 1 + 1e-12
        birge = chi2 / dof
        if birge < 1.0:
            # the ratio's upper bound at birge_z: a chi-square's lower quantile over its dof (Wilson-Hilferty)
            a = 2.0 / (9.0 * dof)
            birge = min(1.0, max(birge_min, birge / max(1.0 - a - birge_z * math.sqrt(a), 1e-6) ** 3))
    return mu, w, variance * birge, weight, birge


def tukey_offset(x: np.ndarray, s: np.ndarray, prior: np.ndarray, start: float, iterations: int, cut_k: float,
                 birge_z: float, birge_min: float) -> tuple[float, np.ndarray, float, float, float]:
    """Tukey's M-estimate of the common value of ``x`` (K,) with standard deviations ``s`` (K,, finite, above 0),
    weighed by ``prior`` (K,), from ``start``: the cut at ``cut_k`` times each standard deviation times the values'
    robust spread in those units (at least 1), re-weighted until the estimate moves less than 1e-6 or after
    ``iterations``; and its variance.

    Returns (the estimate, the final Tukey weights w (K,), the variance, the weights' sum, the Birge ratio). The
    variance is the weighted mean's with the final weights held, ``sum (w p / sum w p)^2 s^2``, times the Birge ratio
    ``sum w ((x - estimate) / s)^2 / (sum w - 1)`` over the values kept (w > 0; 1 with fewer than two); a ratio below
    1 is taken at its upper bound at ``birge_z`` standard normal deviates, between ``birge_min`` and 1."""
    if not (x.shape == s.shape == np.shape(prior)) or x.ndim != 1 or x.size == 0:
        raise ValueError(f"tukey_offset: x {x.shape}, s {s.shape} and prior {np.shape(prior)} must be the same (K,), "
                         "K at least 1")
    f64 = np.float64
    mu, w, variance, weight, birge = _tukey_offset(x.astype(f64), s.astype(f64), np.asarray(prior, f64), float(start),
                                                   int(iterations), float(cut_k), float(birge_z), float(birge_min))
    return float(mu), w, float(variance), float(weight), float(birge)


def median(x: np.ndarray) -> float:
    """``np.median`` of a 1-D array without NaN, compiled: under a microsecond for a moved region's few dozen cells,
    where NumPy's call takes ten."""
    return float(_median(np.ascontiguousarray(x, dtype=np.float64)))


@njit(cache=True, nogil=True, fastmath=True)
def _dot(x, y):
    # reassociated so that LLVM vectorises it: a chain of dependent additions was most of the system's time
    total = 0.0
    for k in range(x.size):
        total += x[k] * y[k]
    return total


@njit(cache=True, nogil=True)
def _weighted_gram(rows, weight, count):
    """(R, R) ``sum_k weight[k] rows[a, k] rows[b, k]`` over the first ``count`` columns of ``rows`` (R, N): one
    row's weighted copy at a time, dotted with the others while it is in the cache (the whole weighted matrix, a
    megabyte for 10,000 pixels, was half the Gauss-Newton system's time)."""
    n_rows = rows.shape[0]
    out = np.zeros((n_rows, n_rows))
    weighted = np.empty(count)
    for a in range(n_rows):
        for k in range(count):
            weighted[k] = weight[k] * rows[a, k]
        for b in range(a, n_rows):
            out[a, b] = out[b, a] = _dot(weighted, rows[b, :count])
    return out


@njit(cache=True, nogil=True)
def _jacobian_rows(lvals, splines, right_saturated, usable, prior, u, v, du, dv, m, theta, idx):
    """(rows (12, n): the Jacobian's 11 rows and, last, the residuals over the usable pixels of ``idx`` in their
    first ``count`` columns; those pixels' shares (n,); their places in ``idx`` (n,); count)."""
    h, w = splines[0].shape
    n = idx.size
    jac = np.empty((N_PARAMS + 1, n))
    r = jac[N_PARAMS]
    weight = np.empty(n)
    kept = np.empty(n, np.int64)
    count = 0
    xs, sampled = _model_samples(splines, u, v, du, dv, m, theta, idx)  # NaN where a sample is no number
    for k in range(n):
        i = idx[k]
        if not usable[i]:
            continue
        x = xs[k]
        column = min(max(int(np.rint(x)), 0), w - 1)
        row = min(max(int(np.rint(v[i] + theta[E])), 0), h - 1)
        if right_saturated[row, column]:
            continue
        rv, gx, gy = sampled[0, k], sampled[1, k], sampled[2, k]
        if not (np.isfinite(rv) and np.isfinite(gx) and np.isfinite(gy)):
            continue
        gain = theta[4] + theta[5] * du[i] + theta[6] * dv[i] + theta[8] * m[i]
        r[count] = lvals[i] - gain * rv - theta[7] - theta[9] * m[i]
        j0, j4 = gain * gx, -rv
        jac[0, count] = j0
        jac[1, count] = j0 * du[i]
        jac[2, count] = j0 * dv[i]
        jac[3, count] = j0 * m[i]
        jac[4, count] = j4
        jac[5, count] = j4 * du[i]
        jac[6, count] = j4 * dv[i]
        jac[7, count] = -1.0
        jac[8, count] = j4 * m[i]
        jac[9, count] = -m[i]
        jac[E, count] = -gain * gy
        weight[count] = prior[i]
        kept[count] = k
        count += 1
    return jac, weight, kept, count


@njit(cache=True, nogil=True)
def _system(lvals, splines, right_saturated, usable, prior, u, v, du, dv, m, theta, idx, huber_k, scale_floor):
    # the residuals as the rows' last: their weighted products with the Jacobian's are -b
    jac, weight, _, count = _jacobian_rows(lvals, splines, right_saturated, usable, prior, u, v, du, dv, m, theta,
                                           idx)
    res = jac[N_PARAMS][:count]
    scale = robust_scale(res)
    if not scale > 0:
        scale = scale_floor
    cut = huber_k * scale
    for k in range(count):
        size = abs(res[k])
        weight[k] *= _huber_weight(size, cut)
    products = _weighted_gram(jac, weight, count)
    return products[:N_PARAMS, :N_PARAMS].copy(), -products[:N_PARAMS, N_PARAMS], scale, count


def _check_fit_arrays(who: str, n_splines: int, lvals, splines, right_saturated, usable, prior, u, v, du, dv, m,
                      theta) -> None:
    """ValueError naming ``who`` and the argument, unless the per-pixel arrays are (N,) as ``lvals``, ``splines``
    ``n_splines`` C-contiguous HxW float32 of ``right_saturated``'s shape and ``theta`` (11,)."""
    n = len(lvals)
    for name, array in (("usable", usable), ("prior", prior), ("u", u), ("v", v), ("du", du), ("dv", dv), ("m", m)):
        if array.shape != (n,):
            raise ValueError(f"{who}: {name} {array.shape} must be ({n},) as lvals")
    if (len(splines) != n_splines or any(c.ndim != 2 or c.dtype != np.float32 or not c.flags.c_contiguous
                                         or c.shape != right_saturated.shape for c in splines)):
        raise ValueError(f"{who}: splines {[(np.shape(c), str(c.dtype)) for c in splines]} must be {n_splines} "
                         f"C-contiguous HxW float32 and right_saturated {right_saturated.shape} HxW of their size")
    if theta.shape != (N_PARAMS,):
        raise ValueError(f"{who}: theta {theta.shape} must be ({N_PARAMS},)")


def normal_equations(lvals: np.ndarray, splines: tuple[np.ndarray, np.ndarray, np.ndarray],
                     right_saturated: np.ndarray, usable: np.ndarray, prior: np.ndarray, u: np.ndarray,
                     v: np.ndarray, du: np.ndarray,
                     dv: np.ndarray, m: np.ndarray, theta: np.ndarray, idx: np.ndarray, huber_k: float,
                     scale_floor: float) -> tuple[np.ndarray, np.ndarray, float, int]:
    """The Huber-weighted Gauss-Newton system of the surface model at ``theta`` over the pixels ``idx``.

    lvals, usable, prior, u, v, du, dv, m: (N,) per pixel of the fit (left grey level, usable, share,
    position on integer rows, position from the region's centre, 1 on the defect); splines: the HxW float32
    spline coefficients (``spline_coefficients``) of the right image and of its horizontal and vertical
    gradients; right_saturated: HxW bool; theta: (11,); idx: (n,) int indices of the pixels to use.
    Returns (A (11, 11), b (11,), the residuals' robust scale, the pixels used), ``A = sum w J J^T``,
    ``b = -sum w J r`` with ``w`` each pixel's share times its Huber weight at that scale
    (``scale_floor`` where the residuals' MAD is 0)."""
    _check_fit_arrays("normal_equations", 3, lvals, splines, right_saturated, usable, prior, u, v, du, dv, m, theta)
    return _system(lvals.astype(np.float64, copy=False), tuple(splines), right_saturated, usable,
                   prior.astype(np.float64, copy=False), u, v, du, dv, m.astype(np.float64, copy=False),
                   theta.astype(np.float64, copy=False), np.asarray(idx, dtype=np.int64), float(huber_k),
                   float(scale_floor))


def jacobian_rows(lvals: np.ndarray, splines: tuple[np.ndarray, np.ndarray, np.ndarray], right_saturated: np.ndarray,
                  usable: np.ndarray, u: np.ndarray, v: np.ndarray, du: np.ndarray, dv: np.ndarray, m: np.ndarray,
                  theta: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The residuals and their Jacobian at ``theta`` over the usable pixels of ``idx`` (arguments as
    ``normal_equations``'): (residuals (n,), Jacobian transposed (11, n), those pixels' places in ``idx`` (n,)), the
    pixels in ``idx``'s order."""
    prior = np.ones(len(lvals))
    _check_fit_arrays("jacobian_rows", 3, lvals, splines, right_saturated, usable, prior, u, v, du, dv, m, theta)
    f64 = np.float64
    rows, _, kept, count = _jacobian_rows(lvals.astype(f64, copy=False), tuple(splines), right_saturated, usable,
                                          prior, u, v, du, dv, m.astype(f64, copy=False),
                                          theta.astype(f64, copy=False), np.asarray(idx, dtype=np.int64))
    return rows[N_PARAMS, :count].copy(), rows[:N_PARAMS, :count].copy(), kept[:count].copy()


@njit(cache=True, nogil=True)
def e_prior(scale, spread_px):
    """The eyes' vertical offset's prior information in the normal equations: one observation of 0 with spread
    ``spread_px``, in units of the residuals' ``scale``."""
    return (scale / spread_px) ** 2


@njit(cache=True, nogil=True)
def _solve(a, b):
    """x with ``a x = b`` (a (n, n), b (n,)) by Gaussian elimination with partial pivoting; NaN where a pivot is 0
    (``a`` singular)."""
    n = b.size
    lu, x = a.copy(), b.copy()
    for k in range(n):
        pivot = k
        for i in range(k + 1, n):
            if abs(lu[i, k]) > abs(lu[pivot, k]):
                pivot = i
        if lu[pivot, k] == 0.0:
            x[:] = np.nan
            return x
        if pivot != k:
            for j in range(n):
                lu[k, j], lu[pivot, j] = lu[pivot, j], lu[k, j]
            x[k], x[pivot] = x[pivot], x[k]
        for i in range(k + 1, n):
            f = lu[i, k] / lu[k, k]
            for j in range(k, n):
                lu[i, j] -= f * lu[k, j]
            x[i] -= f * x[k]
    for i in range(n - 1, -1, -1):
        total = x[i]
        for j in range(i + 1, n):
            total -= lu[i, j] * x[j]
        x[i] = total / lu[i, i]
    return x


@njit(cache=True, nogil=True)
def _plane_consensus(e, s, x, y, triples, cut_sds, min_gain):
    n = e.size
    system, rhs, best = np.empty((3, 3)), np.empty(3), np.empty(3)
    least = np.inf
    for t in range(triples.shape[0]):
        for r in range(3):
            k = triples[t, r]
            system[r, 0], system[r, 1], system[r, 2], rhs[r] = 1.0, x[k], y[k], e[k]
        plane = _solve(system, rhs)
        if not np.isfinite(plane[0]):  # the three on one line (or two alike): no one plane through them
            continue
        cost = 0.0
        for k in range(n):
            z = (plane[0] + plane[1] * x[k] + plane[2] * y[k] - e[k]) / s[k]
            cost += min(z * z, cut_sds * cut_sds)
        if cost < least:
            least = cost
            best[:] = plane
    if not least < np.inf:
        return np.zeros(3), False
    # noisy cells let some triple beat the fitted plane by chance: move only for a clearly larger consensus
    inliers = np.empty(n, np.bool_)
    agree, agreed = 0, 0
    for k in range(n):
        inliers[k] = abs(best[0] + best[1] * x[k] + best[2] * y[k] - e[k]) <= cut_sds * s[k]
        agree += inliers[k]
        agreed += abs(e[k]) <= cut_sds * s[k]
    if agree / n - agreed / n < min_gain:
        return np.zeros(3), False
    # the inliers' weighted least-squares plane: the plane's rows and, last, the offsets, whose products are its
    # right-hand side
    rows, weight = np.empty((4, agree)), np.empty(agree)
    m = 0
    for k in range(n):
        if inliers[k]:
            rows[0, m], rows[1, m], rows[2, m], rows[3, m] = 1.0, x[k], y[k], e[k]
            weight[m] = 1.0 / (s[k] * s[k])
            m += 1
    products = _weighted_gram(rows, weight, agree)
    refined = _solve(products[:3, :3].copy(), products[:3, 3].copy())
    return (refined if np.isfinite(refined[0]) else best), True


def plane_consensus(e: np.ndarray, s: np.ndarray, x: np.ndarray, y: np.ndarray, triples: np.ndarray, cut_sds: float,
                    min_gain: float) -> tuple[np.ndarray, bool]:
    """The plane ``e = c + a x + b y`` most of the cells agree on, MSAC over ``triples`` (T, 3) of them.

    e, s: (K,) the cells' offsets and standard deviations; x, y: (K,) their positions. Each triple's plane through its
    three cells costs ``sum min(z^2, cut_sds^2)`` over the cells, z their offsets from it in their standard
    deviations; the least costly one's inliers (within ``cut_sds``) must outnumber the cells within ``cut_sds`` of
    e = 0 by ``min_gain`` of the cells, and their weighted least-squares plane (1 / s^2) is returned. Returns
    ((c, a, b), True), or (zeros, False) where no triple defines a plane or the consensus does not grow by that
    much."""
    n = len(e)
    for name, array in (("s", s), ("x", x), ("y", y)):
        if np.shape(array) != (n,):
            raise ValueError(f"plane_consensus: {name} {np.shape(array)} must be ({n},) as e")
    triples = np.asarray(triples, dtype=np.int64)
    if triples.ndim != 2 or triples.shape[1] != 3 or (triples.size and (triples.min() < 0 or triples.max() >= n)):
        raise ValueError(f"plane_consensus: triples {triples.shape} must be (T, 3) indices of the {n} cells")
    f64 = np.float64
    plane, moved = _plane_consensus(np.asarray(e, f64), np.asarray(s, f64), np.asarray(x, f64), np.asarray(y, f64),
                                    triples, float(cut_sds), float(min_gain))
    return plane, bool(moved)


FAILED, MOVING, SETTLED = 0, 1, 2  # how ``gauss_newton`` ended


@njit(cache=True, nogil=True)
def _gauss_newton(lvals, splines, right_saturated, usable, prior, u, v, du, dv, m, theta, idx, free, iterations,
                  tolerance, huber_k, scale_floor, e_prior_px):
    theta = theta.copy()
    n_free = free.size
    e_at = -1
    for a in range(n_free):
        if free[a] == E:
            e_at = a
    for _ in range(iterations):
        system, rhs, scale, count = _system(lvals, splines, right_saturated, usable, prior, u, v, du, dv, m, theta,
                                            idx, huber_k, scale_floor)
        if count < n_free + 2:
            return theta, FAILED
        a_free, b_free = np.empty((n_free, n_free)), np.empty(n_free)
        for a in range(n_free):
            b_free[a] = rhs[free[a]]
            for c in range(n_free):
                a_free[a, c] = system[free[a], free[c]]
        if e_at >= 0:
            information = e_prior(scale, e_prior_px)
            a_free[e_at, e_at] += information
            b_free[e_at] -= information * theta[E]
        step = _solve(a_free, b_free)
        moved = 0.0
        for a in range(n_free):
            if not np.isfinite(step[a]):
                return theta, FAILED
        for a in range(n_free):
            theta[free[a]] += step[a]
            if free[a] == 0 or free[a] == 3:  # the disparity's: the surface's and the defect's offset
                moved = max(moved, abs(step[a]))
        if moved < tolerance:
            return theta, SETTLED
    return theta, MOVING


def gauss_newton(lvals: np.ndarray, splines: tuple[np.ndarray, np.ndarray, np.ndarray], right_saturated: np.ndarray,
                 usable: np.ndarray, prior: np.ndarray, u: np.ndarray, v: np.ndarray, du: np.ndarray, dv: np.ndarray,
                 m: np.ndarray, theta: np.ndarray, idx: np.ndarray, free: np.ndarray, iterations: int,
                 tolerance: float, huber_k: float, scale_floor: float, e_prior_px: float
                 ) -> tuple[np.ndarray | None, bool]:
    """Huber-weighted Gauss-Newton on the parameters ``free`` (F,) of ``theta`` (11,) over the pixels ``idx`` (n,),
    each step from ``normal_equations`` (the arguments as there) with the eyes' vertical offset's prior (one
    observation of 0 with spread ``e_prior_px``) where it is free, at most ``iterations`` steps. Returns (theta,
    whether the last step moved the disparity's parameters (0 and 3) less than ``tolerance`` px), or (None, False)
    where fewer than F + 2 pixels are usable or a step is singular or no number."""
    _check_fit_arrays("gauss_newton", 3, lvals, splines, right_saturated, usable, prior, u, v, du, dv, m, theta)
    free = np.asarray(free, dtype=np.int64)
    if free.ndim != 1 or free.size == 0 or free.min() < 0 or free.max() >= N_PARAMS \
            or np.unique(free).size != free.size:
        raise ValueError(f"gauss_newton: free {free.tolist()} must be distinct parameters in 0 .. {N_PARAMS - 1}")
    f64 = np.float64
    theta, how = _gauss_newton(lvals.astype(f64, copy=False), tuple(splines), right_saturated, usable,
                               prior.astype(f64, copy=False), u, v, du, dv, m.astype(f64, copy=False),
                               theta.astype(f64), np.asarray(idx, dtype=np.int64), free, int(iterations),
                               float(tolerance), float(huber_k), float(scale_floor), float(e_prior_px))
    return (None, False) if how == FAILED else (theta, how == SETTLED)


@njit(cache=True, nogil=True)
def _offset_costs(lvals, image, u, v, base, gain, offset, weight, e, deltas, scale, huber_k):
    h, w = image.shape
    n = u.size
    cut = huber_k * scale
    # every sample lies on a row v + e, so the kernel's vertical half is the same for all of them and all
    # candidates: applied once to the rows and columns they read, each candidate then reads four columns
    v_lo, v_hi = int(v.min()), int(v.max())
    x_lo = max(int(np.floor((u - base).min() - deltas.max())) - 2, 0)
    x_hi = min(int(np.ceil((u - base).max() - deltas.min())) + 3, w)
    lines = np.empty((1, v_hi - v_lo + 1, max(x_hi - x_lo, 0)))
    _rows_at((image,), v_lo, x_lo, e, lines)
    costs = np.zeros(deltas.size)
    for t in range(deltas.size):
        total = 0.0
        for i in range(n):
            x = u[i] - base[i] - deltas[t]
            xf, inside = _position(x, v[i] + e, h, w)
            if not inside:
                continue  # the sample is NaN there: the pixel costs nothing
            rv = _along_row(lines[0, int(v[i]) - v_lo], xf, x_lo)
            size = abs(lvals[i] - gain[i] * rv - offset)
            total += weight[i] * (0.5 * size * size if size <= cut else cut * (size - 0.5 * cut))
        costs[t] = total
    return costs


def offset_costs(lvals: np.ndarray, image: np.ndarray, u: np.ndarray, v: np.ndarray, base: np.ndarray,
                 gain: np.ndarray, offset: float, weight: np.ndarray, e: float, deltas: np.ndarray, scale: float,
                 huber_k: float) -> np.ndarray:
    """The Huber cost ``sum weight * rho(lvals - gain * R(u - base - delta, v + e) - offset)`` of each of
    ``deltas`` (D,) over the pixels (N,) on integer rows ``v``, ``rho`` Huber's at ``huber_k * scale``, ``R``
    the B-spline of the HxW float32 coefficients ``image`` (``sample_rows``); a pixel whose sample is NaN
    there costs nothing. Returns (D,)."""
    n = len(lvals)
    for name, array in (("u", u), ("v", v), ("base", base), ("gain", gain), ("weight", weight)):
        if np.shape(array) != (n,):
            raise ValueError(f"offset_costs: {name} {np.shape(array)} must be ({n},) as lvals")
    if image.ndim != 2 or image.dtype != np.float32:
        raise ValueError(f"offset_costs: image {image.shape} {image.dtype} must be HxW float32")
    if n == 0 or len(deltas) == 0:
        return np.zeros(len(deltas))
    f64 = np.float64
    return _offset_costs(lvals.astype(f64), image, u.astype(f64), v.astype(f64), base.astype(f64), gain.astype(f64),
                         float(offset), weight.astype(f64), float(e), np.asarray(deltas, f64), float(scale),
                         float(huber_k))


@njit(cache=True, nogil=True)
def _sandwich_sums(jt, r, p, cut, groups, n_groups):
    n_p, n = jt.shape
    bread_w, meat_w, score = np.empty(n), np.empty(n), np.empty(n)
    s2 = 0.0
    for k in range(n):
        size = abs(r[k])
        hr = r[k] * _huber_weight(size, cut)
        bread_w[k] = p[k] if size <= cut else 0.0
        meat_w[k] = p[k] * p[k]
        score[k] = p[k] * hr
        s2 += p[k] * hr * hr
    blocks = np.zeros((n_groups, n_p))
    for a in range(n_p):
        for k in range(n):
            blocks[groups[k], a] += score[k] * jt[a, k]
    return _weighted_gram(jt, bread_w, n), _weighted_gram(jt, meat_w, n), s2, blocks


def sandwich_sums(jt: np.ndarray, r: np.ndarray, p: np.ndarray, cut: float, groups: np.ndarray, n_groups: int
                  ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """The sums of Huber's M-estimator's sandwich covariance over N pixels of P parameters, in one pass:
    ``jt`` (P, N) the residuals' Jacobian transposed, ``r`` (N,) the residuals, ``p`` (N,) each pixel's share,
    ``cut`` Huber's (k times the residuals' scale), ``groups`` (N,) each pixel's block in 0 .. n_groups - 1.
    Returns (bread (P, P) ``sum p psi' J J^T``, meat (P, P) ``sum p^2 J J^T``, ``sum p (h r)^2`` with ``h`` Huber's
    weight, blocks (n_groups, P) the block sums of the scores ``p h r J``)."""
    jt = np.ascontiguousarray(jt, dtype=np.float64)
    if jt.ndim != 2:
        raise ValueError(f"sandwich_sums: jt {jt.shape} must be (P, N)")
    n = jt.shape[1]
    for name, array in (("r", r), ("p", p), ("groups", groups)):
        if np.shape(array) != (n,):
            raise ValueError(f"sandwich_sums: {name} {np.shape(array)} must be ({n},) as jt's columns")
    groups = np.asarray(groups, dtype=np.int64)
    if n and (groups.min() < 0 or groups.max() >= n_groups):
        raise ValueError(f"sandwich_sums: groups must lie in 0 .. {n_groups - 1}")
    f64 = np.float64
    return _sandwich_sums(jt, np.asarray(r, f64), np.asarray(p, f64), float(cut), groups, int(n_groups))
