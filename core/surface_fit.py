"""Sub-pixel surfaces by direct image alignment: the ring's plane and the defect's offset from it.

A rectified pair sees a plane as ``I_L(u, v) = g * I_R(u - d(u, v), v) + o`` with ``d`` linear in
(u, v) and (g, o) the exposure difference between the eyes. Fitting ``d`` to the grey levels of every
pixel of a region (Gauss-Newton, as in Lucas-Kanade) instead of to per-pixel disparities averages the
sensor noise over all of them: the standard deviation of the region's disparity falls as
``sigma_noise * sqrt(2) / sqrt(sum I_x^2)``, a few hundredths of a pixel over a few thousand pixels
of rolled steel, where a per-pixel matcher is off by a tenth or more.

The model, fitted over the ring around a box and the defect's region inside it::

    d(u, v) = c + a * (u - u0) + b * (v - v0) + delta * m(u, v)
    I_L(u, v) = (g + g_u * (u - u0) + g_v * (v - v0) + g_m * m) * I_R(u - d(u, v), v + e) + o + o_m * m

``m`` is 1 on the defect's region, 0 on the ring; (u0, v0) the region's centre, so ``c`` is the
surrounding surface's disparity there and ``delta`` the defect's offset from it. The gain varies over
the ring because both eyes' vignetting differs at pixels ``d`` apart; the defect has an exposure of its
own because its walls reflect the light differently towards each eye. ``e`` is what rectification
left of the eyes' vertical offset: a few tenths of a pixel on a real camera, which, unmodelled, the
fit reads as disparity wherever the texture runs diagonally. Both images are high-passed
first (what varies more slowly than ``HIGH_PASS_SIGMA`` is sheen, not texture), saturated pixels are
left out and residuals are weighted with Huber's function. The right image is read between its pixels
from the cubic B-spline through them (``surface_fit_numba``).

Steps (``fit_surface``): the ring alone, coarse to fine, from the backend's plane; the defect's offset
by a search of the robust cost at full resolution (a narrow region, blurred, is mostly its ring);
both together. Then ``robust_offset`` re-estimates ``delta`` from the offsets of small cells of the
region, combined with Tukey's weights, so that cells on a wall or a glint do not pull it, and widens
its uncertainty by the cells' Birge ratio where they scatter more than their own noise says.

Uncertainties come from the fit: the M-estimator's sandwich covariance, inflated where neighbouring
residuals are correlated (the right image is interpolated; a JPEG has blocks).
"""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import cv2
import numpy as np

from core import surface_fit_numba

SATURATED = (3.0, 252.0)  # grey levels outside which a pixel carries no usable gradient
HIGH_PASS_SIGMA = 10.0  # px
BLUR_SIGMAS = (2.0, 1.0)  # the ring's levels before the joint fit on the images as they are
ITERATIONS = (6, 6)
JOINT_ITERATIONS = 10
REFIT_ITERATIONS = 4  # after the ring's cells are weighted again: the fit starts at its solution
TOLERANCE_PX = 5e-4  # disparity steps below this end the fit: a tenth of the smallest uncertainty seen
HUBER_K = 1.345  # 95 % efficiency for Gaussian noise
TUKEY_K = 4.685  # likewise
CLUSTER_PX = 4  # blocks over which residuals may be correlated
CELL_PX = 4  # cells of the defect's region whose offsets are combined robustly
CELL_SETTLED_PX = 0.05  # a cell's last Gauss-Newton step beyond this: it has not settled on an offset
BIRGE_CONFIDENCE_Z = 1.2816  # cells scattering less than their noise: the 90 % upper bound of that ratio,
BIRGE_MIN = 0.25  # and never below a quarter (cells that agree to the digit would otherwise claim no uncertainty)
RADIAL_MIN_CELLS = 6  # cells that tell a bowl from a plane and a constant
RING_CELL_PX = 6  # cells of the ring that are kept or left out together
MATCH_RATIO = 1.0  # residual / texture spread: 0.2-0.83 on the evaluation sets, 1.55 for a plate outside the range
MIN_GAIN = 0.25  # the right eye's fitted gain: above 0.34 on the evaluation sets, ~0 on noise alone, 0.21 on a
# defect started 45 px from its surface
SEARCH_STEP_PX = 0.05
COARSE_STEP_PX = 0.2
SEARCH_PX = 1.5  # the defect's offset is searched this far either side of the backend's
LEFT_SEARCH_PX = 0.5  # a fit that moves the offset this far from the searched minimum has found another surface
PARAMS = ("c", "a", "b", "delta", "g", "g_u", "g_v", "o", "g_m", "o_m", "e")
RING = [0, 1, 2, 4, 5, 6, 7, 10]
E = 10  # the vertical offset between the eyes
E_PRIOR_PX = 1.0  # its prior spread: a rectified pair is within a pixel, and a texture without rows cannot tell
ALL = list(range(len(PARAMS)))


@dataclass(frozen=True)
class SurfaceFit:
    """The fitted parameters (``PARAMS``, see the module docstring), their covariance and what the fit saw."""

    params: np.ndarray  # (11,)
    covariance: np.ndarray  # (11, 11)
    centre: tuple[float, float]  # (u0, v0), px
    ring_pixels: int
    defect_pixels: int
    residual_sigma: float  # grey levels of the high-passed images, robust
    inflation: float  # covariance factor for correlated residuals (>= 1)
    converged: bool
    ring_weights: np.ndarray | None = None  # (ring pixels,) each one's cell weight in [0, 1] at the end
    signal_sigma: float = float("inf")  # grey levels: the robust spread of the ring's high-passed left image
    images: DefectImages | None = None  # the high-passed window the fit read, for the defect's cells

    @property
    def matches(self) -> bool:
        """The pair agrees at the fitted surface better than two unrelated patches of its texture would:
        their difference spreads sqrt(1 + g^2) ~ 1.4 times the texture, or the texture itself where the fit
        drives the right eye's gain to nothing, on the ring (``g``) or on the defect (``g + g_m``). Where the
        texture is no stronger than the noise, the surface lies where the backend did not search (a plate
        outside the working distance), or the defect was started from a gross mismatch, the fit has found
        nothing to vouch for."""
        return (self.residual_sigma < MATCH_RATIO * self.signal_sigma and self.params[4] > MIN_GAIN
                and self.params[4] + self.params[8] > MIN_GAIN)

    @property
    def c(self) -> float:
        return float(self.params[0])

    @property
    def slopes(self) -> tuple[float, float]:
        return float(self.params[1]), float(self.params[2])

    @property
    def delta(self) -> float:
        return float(self.params[3])


@dataclass(frozen=True)
class RobustOffset:
    """The defect's offset from the ring's plane from its cells: ``delta`` (px), its variance given the
    plane (px^2, Birge ratio included), the number of cells and the sum of their final weights."""

    delta: float
    variance: float
    cells: int
    weight: float
    birge: float


def to_grey(image: np.ndarray) -> np.ndarray:
    """HxWx3 BGR (or HxW) uint8 -> HxW float32 grey levels."""
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.shape[2] == 3 else image[..., 0]
    return image.astype(np.float32)


def high_pass(image: np.ndarray, sigma: float = HIGH_PASS_SIGMA) -> np.ndarray:
    """HxW float32 -> the image less its Gaussian blur: the texture without the slowly varying light."""
    return image - low_pass(image, sigma)


PYRAMID_LEVELS = 2  # a blur of sigma 10 px is taken at a quarter of the size
PYRAMID_VARIANCE = 5.0  # px^2: what two of OpenCV's pyramid steps down (variance 1, then 4) blur, and two up again
PYRAMID_PAD_PX = 32  # the mirrored border, a multiple of the pyramid's factor


def low_pass(image: np.ndarray, sigma: float) -> np.ndarray:
    """HxW float32 -> its Gaussian blur of ``sigma`` px (the border mirrored, as OpenCV's ``GaussianBlur``). A wide
    blur is taken PYRAMID_LEVELS levels down a Gaussian pyramid and brought back up: what the levels add to the
    blur, down and up, is taken off the blur in between. It is the direct filter's within 0.015 grey levels on
    the evaluation sets' images, border included, a hundredth of their noise, in a fifth of its time."""
    factor = 2 ** PYRAMID_LEVELS
    rest = sigma * sigma - 2 * PYRAMID_VARIANCE
    if rest < factor * factor or min(image.shape) < 8 * factor:
        return cv2.GaussianBlur(image, (0, 0), sigma)
    # mirrored beyond the border first, as the direct filter mirrors it: the pyramid's own border would not be
    h, w = image.shape
    pad = PYRAMID_PAD_PX
    small = cv2.copyMakeBorder(image, pad, pad + (-h) % factor, pad, pad + (-w) % factor, cv2.BORDER_REFLECT_101)
    for _ in range(PYRAMID_LEVELS):
        small = cv2.pyrDown(small)
    small = cv2.GaussianBlur(small, (0, 0), math.sqrt(rest) / factor)
    for _ in range(PYRAMID_LEVELS):
        small = cv2.pyrUp(small)
    return small[pad:pad + h, pad:pad + w]


def gradient_x(image: np.ndarray) -> np.ndarray:
    """HxW -> HxW central difference along the rows (0 in the first and last column)."""
    g = np.zeros_like(image)
    g[:, 1:-1] = 0.5 * (image[:, 2:] - image[:, :-2])
    return g


def gradient_y(image: np.ndarray) -> np.ndarray:
    """HxW -> HxW central difference along the columns (0 in the first and last row)."""
    g = np.zeros_like(image)
    g[1:-1] = 0.5 * (image[2:] - image[:-2])
    return g


def spline(image: np.ndarray) -> np.ndarray:
    """HxW -> HxW float32: the coefficients of the cubic B-spline through the image's pixels, which
    ``sample`` reads."""
    return surface_fit_numba.spline_coefficients(image)


def sample(coefficients: np.ndarray, x: np.ndarray, rows: np.ndarray, e: float) -> np.ndarray:
    """Samples of the cubic B-spline of HxW float32 ``coefficients`` (``spline``) at float columns ``x`` of
    the integer ``rows`` moved by ``e`` (1-D arrays): every sample of the fit lies on a pixel row moved by
    the eyes' vertical offset. NaN where its taps (x - 1 .. x + 2, likewise down the rows) leave the image."""
    return surface_fit_numba.sample_rows((coefficients,), x, rows, e)[0]


def samples(coefficients: tuple[np.ndarray, ...], x: np.ndarray, rows: np.ndarray, e: float) -> list[np.ndarray]:
    """``sample`` of each of several splines of one shape at the same positions."""
    return list(surface_fit_numba.sample_rows(coefficients, x, rows, e))


def _blurred(image: np.ndarray, sigma: float) -> np.ndarray:
    return image if sigma <= 0 else cv2.GaussianBlur(image, (0, 0), sigma)


def _tukey_weights(z: np.ndarray) -> np.ndarray:
    """Tukey's biweight of residuals ``z`` already divided by their cut."""
    return np.where(np.abs(z) < 1, (1 - z * z) ** 2, 0.0)


def _cell_index(u: np.ndarray, v: np.ndarray, px: int) -> np.ndarray:
    """Each pixel's ``px`` square cell, numbered 0 .. K-1 over the cells present."""
    if u.size == 0:
        return np.zeros(0, np.intp)
    # np.unique's numbering (the cells in reading order) by a count of the cells present, not a sort
    cu, cv = u.astype(np.intp) // px, v.astype(np.intp) // px
    cu, cv = cu - cu.min(), cv - cv.min()
    key = cv * (int(cu.max()) + 1) + cu
    present = np.zeros(int(key.max()) + 1, np.intp)
    present[key] = 1
    return (np.cumsum(present) - 1)[key]


def _cell_means(cell: np.ndarray, k: int, *values: np.ndarray) -> list[np.ndarray]:
    """Each of ``values`` (per pixel) averaged over the K cells of ``cell``."""
    count = np.maximum(np.bincount(cell, minlength=k), 1)
    return [np.bincount(cell, x, minlength=k) / count for x in values]


def _e_prior(scale: float) -> float:
    """The vertical offset's prior information in the normal equations, with spread E_PRIOR_PX (the Gauss-Newton
    kernel's own: ``surface_fit_numba.e_prior``)."""
    return float(surface_fit_numba.e_prior(scale, E_PRIOR_PX))


def _robust_scale(r: np.ndarray) -> float:
    return surface_fit_numba.robust_scale(np.ascontiguousarray(r, dtype=np.float64)) or 1e-3


class _Problem:
    """The pixels of one fit and the images they are read from (high-passed), with the model's residuals.
    ``R``, ``Rx``, ``Ry``: the right image and its gradients as the coefficients of their splines (``spline``);
    ``origin``: the left image's top-left corner in the camera's image, where it is a window of it, and
    ``right_shift`` how many columns further left the right image's window starts (``ur``, the pixels' columns
    in it, is where the right image is read before the disparity is taken off); ``at_u``,
    ``at_v``: the pixels' positions there, on whose grid the ring's cells, the coarse levels' pixels and the
    residuals' clusters lie (the window's corner follows the starting disparity, and cells cut where each start
    put it weighed the ring otherwise for each: faint pairs settled 0.006 px apart)."""

    def __init__(self, left, right, ring, defect, prior, raw_left, raw_right, centre, origin=(0, 0), right_shift=0):
        self.u = np.concatenate([ring[0], defect[0]]).astype(np.float64)
        self.ur = self.u + right_shift
        self.v = np.concatenate([ring[1], defect[1]]).astype(np.float64)
        self.m = np.concatenate([np.zeros(len(ring[0])), np.ones(len(defect[0]))])
        self.ui, self.vi = self.u.astype(np.intp), self.v.astype(np.intp)
        self.at_u, self.at_v = self.ui + origin[0], self.vi + origin[1]
        self.du, self.dv = self.u - centre[0], self.v - centre[1]
        self.prior = prior
        self.left, self.right, self.raw_left, self.raw_right = left, right, raw_left, raw_right
        grey = raw_left[self.vi, self.ui]
        self.usable = (grey > SATURATED[0]) & (grey < SATURATED[1]) & (prior > 0)
        # the right image's saturated pixels: a sample that reads one is not usable
        self.right_saturated = (raw_right <= SATURATED[0]) | (raw_right >= SATURATED[1])
        ring = self.m == 0
        # the ring's cells never change; their numbering (a sort) and centres are wanted at every reweighting
        self.ring_idx = np.flatnonzero(ring)
        self.ring_cell = _cell_index(self.at_u[ring], self.at_v[ring], RING_CELL_PX)
        self.ring_cells = int(self.ring_cell.max()) + 1 if self.ring_cell.size else 0
        self.ring_cell_du, self.ring_cell_dv = _cell_means(self.ring_cell, self.ring_cells, self.du[ring],
                                                           self.dv[ring])
        self._levels = {}
        self.level(0.0)

    def level(self, sigma: float) -> None:
        """Read the images blurred by ``sigma`` from now on (0: as they are)."""
        if sigma not in self._levels:
            L, R = _blurred(self.left, sigma), _blurred(self.right, sigma)
            # the spline's coefficients are a shift-invariant filter of the image, which commutes with the
            # central differences: the gradients' splines from R's own, the same numbers where samples fall
            R = spline(R)
            Rx, Ry = gradient_x(R), gradient_y(R)
            self._levels[sigma] = (L, R, Rx, Ry, L[self.vi, self.ui])
        self.L, self.R, self.Rx, self.Ry, self.lvals = self._levels[sigma]

    def _pixels(self):
        """(left grey levels, the right image's three splines, its saturated pixels, usable): the first arguments
        of the model's kernels (``surface_fit_numba.normal_equations``)."""
        return self.lvals, (self.R, self.Rx, self.Ry), self.right_saturated, self.usable

    def normal_equations(self, theta, idx):
        """(A (11, 11), b (11,), scale, pixels used): the Huber-weighted system of the model's residuals over the
        usable pixels of ``idx`` (indices), each weighted by its share (``surface_fit_numba.normal_equations``)."""
        return surface_fit_numba.normal_equations(*self._pixels(), self.prior, self.ur, self.v, self.du, self.dv,
                                                  self.m, theta, idx, HUBER_K, 1e-3)

    def jacobian_rows(self, theta):
        """(residuals (n,), Jacobian transposed (11, n), the pixels they are of (n,)) at ``theta`` over the usable
        pixels (``surface_fit_numba.jacobian_rows``)."""
        return surface_fit_numba.jacobian_rows(*self._pixels(), self.ur, self.v, self.du, self.dv, self.m, theta,
                                               np.arange(len(self.u)))

    def gauss_newton(self, theta, free, iterations, select, tolerance):
        """Huber-weighted Gauss-Newton on the parameters ``free`` over the pixels ``select``:
        (theta, moved less than ``tolerance`` px in disparity at the end), or (None, False) (compiled:
        ``surface_fit_numba.gauss_newton``)."""
        return surface_fit_numba.gauss_newton(*self._pixels(), self.prior, self.ur, self.v, self.du, self.dv, self.m,
                                              theta, np.flatnonzero(select), free, iterations, tolerance, HUBER_K,
                                              1e-3, E_PRIOR_PX)


@dataclass(frozen=True)
class RingFit:
    """The ring's plane fitted coarse to fine from the backend's and its cells weighed (``fit_ring``): what every
    fit of the defect's offset from it starts from (``fit_defect``). ``theta`` (11,) the parameters so far,
    ``prior`` (N,) each pixel's share with the ring's cells weighed, ``ring_prior`` the shares before;
    ``problem`` the pixels and the images' levels, ``origin`` and ``right_x0`` the windows it reads
    (``DefectImages``), ``delta0`` and ``search_px`` where the defect's offset is searched."""

    problem: _Problem
    theta: np.ndarray
    prior: np.ndarray
    ring_prior: np.ndarray
    centre: tuple[float, float]
    origin: tuple[int, int]
    right_x0: int
    delta0: float
    search_px: float


def fit_ring(left: np.ndarray, right: np.ndarray, ring: tuple[np.ndarray, np.ndarray],
             defect: tuple[np.ndarray, np.ndarray], plane: tuple[float, float, float], delta0: float = 0.0,
             defect_weights: np.ndarray | None = None, search_px: float = SEARCH_PX) -> RingFit | None:
    """The first stage of ``fit_surface`` (its arguments as there): the ring's plane, exposure and the eyes'
    vertical offset, coarse to fine from ``plane``, moved to the plane most of the ring's cells agree on and
    with the cells that stand off it weighed down. None when too few usable pixels remain or a level does not
    settle."""
    if left.shape != right.shape or left.ndim != 2:
        raise ValueError(f"fit_surface: left {left.shape} and right {right.shape} must be the same HxW")
    if len(ring[0]) != len(ring[1]) or len(defect[0]) != len(defect[1]):
        raise ValueError("fit_surface: ring and defect are (u, v) pairs of equal length")
    if len(defect[0]) == 0 or len(ring[0]) < 10:
        return None
    wd = np.ones(len(defect[0])) if defect_weights is None else np.asarray(defect_weights, dtype=np.float64)
    if wd.shape != (len(defect[0]),):
        raise ValueError(f"fit_surface: defect_weights {wd.shape} must have one weight per defect pixel")
    if wd.sum() <= 0:
        return None
    prior = np.concatenate([np.ones(len(ring[0])), wd])
    centre = (float(np.average(defect[0], weights=wd)), float(np.average(defect[1], weights=wd)))
    a0, b0, c_img = plane
    theta = np.array([a0 * centre[0] + b0 * centre[1] + c_img, a0, b0, delta0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    (x0, y0), right_x0, left, right = _window(left, right, ring, defect, theta, search_px)
    ring = (ring[0] - x0, ring[1] - y0)
    defect = (defect[0] - x0, defect[1] - y0)
    local = (centre[0] - x0, centre[1] - y0)
    p = _Problem(high_pass(left), high_pass(right), ring, defect, prior, left, right, local, (x0, y0), x0 - right_x0)
    on_ring = p.m == 0
    checker = ((p.at_u + p.at_v) % 2) == 0
    for level, (sigma, iterations) in enumerate(zip(BLUR_SIGMAS, ITERATIONS)):
        p.level(sigma)
        if level == 0:
            theta[[4, 7]] = _exposure(p, theta)
        # the coarse levels only bring the start into the fine level's reach: every other ring pixel will do
        theta, _ = p.gauss_newton(theta, RING, iterations, on_ring & checker, 4 * TOLERANCE_PX)
        if theta is None:
            return None
    p.level(0.0)
    theta = _ring_consensus(p, theta)
    weighed = prior.copy()
    weighed[on_ring] *= _ring_cell_weights(p, theta)
    return RingFit(p, theta, weighed, prior, centre, (x0, y0), right_x0, delta0, search_px)


def fit_defect(start: RingFit, rows_from_ring: bool = False) -> SurfaceFit | None:
    """The second stage of ``fit_surface``: the defect's offset searched from ``start.delta0`` at full
    resolution, then fitted with the ring's parameters, the ring's cells weighed again at that fit and the fit
    repeated. ``start`` is left as it was, so that one ring's fit serves more than one (a groove's, with
    ``rows_from_ring``, after the region's). None when the fit leaves the searched minimum or its information
    is singular."""
    p = copy.copy(start.problem)  # shares of its own: the ring's cells are weighed again
    p.prior = prior = start.prior.copy()
    theta, ring_prior = start.theta.copy(), start.ring_prior
    on_ring = p.m == 0
    joint = ALL
    if rows_from_ring:
        theta, _ = p.gauss_newton(theta, RING, ITERATIONS[-1], on_ring, TOLERANCE_PX)
        if theta is None:
            return None
        joint = [i for i in ALL if i != E]
    delta0, search_px = start.delta0, start.search_px
    searched = _search_offset(p, theta, delta0 - search_px, delta0 + search_px)
    if searched is None:
        return None
    theta[3] = searched
    theta, converged = p.gauss_newton(theta, joint, JOINT_ITERATIONS, np.ones_like(on_ring), TOLERANCE_PX)
    if theta is None or abs(theta[3] - searched) > LEFT_SEARCH_PX:  # left the searched minimum: not one surface
        return None
    prior[on_ring] = ring_prior[on_ring] * _ring_cell_weights(p, theta)
    theta, converged = p.gauss_newton(theta, joint, REFIT_ITERATIONS, np.ones_like(on_ring), TOLERANCE_PX)
    if theta is None or abs(theta[3] - searched) > LEFT_SEARCH_PX:  # the refit too (tests/test_surface_fit.py)
        return None
    r, jt, kept = p.jacobian_rows(theta)
    ok = np.zeros(len(p.u), dtype=bool)
    ok[kept] = True
    scale = _robust_scale(r)
    found = sandwich(jt.T, r, scale, prior[kept], p.at_u[ok], p.at_v[ok])
    if found is None:
        return None
    covariance, inflation = found
    ring_weights = np.where(ok[on_ring], prior[on_ring], 0.0)
    signal = _robust_scale(p.lvals[on_ring & p.usable])
    return SurfaceFit(theta, covariance, start.centre, int((ok & on_ring).sum()), int((ok & ~on_ring).sum()),
                      scale, inflation, converged, ring_weights, signal,
                      DefectImages(start.origin, start.right_x0, p.L, p.R, p.Rx))


def fit_surface(left: np.ndarray, right: np.ndarray, ring: tuple[np.ndarray, np.ndarray],
                defect: tuple[np.ndarray, np.ndarray], plane: tuple[float, float, float],
                delta0: float = 0.0, defect_weights: np.ndarray | None = None,
                search_px: float = SEARCH_PX, rows_from_ring: bool = False) -> SurfaceFit | None:
    """Fit the ring's disparity plane and the defect's offset to the grey levels of a rectified pair.

    left, right: HxW float32 grey images of the same shape. ring, defect: (u, v) integer pixel
    coordinates (1-D arrays) of the surrounding surface and of the defect's region. defect_weights:
    (len(defect[0]),) each defect pixel's share of the region (its area inside a region whose border
    cuts pixels), 1 if not given. plane: the starting plane ``d = a * u + b * v + c`` of the ring in
    image coordinates (disparity px, without doffs). delta0: the defect's starting offset, searched
    ``search_px`` either side. rows_from_ring: the eyes' vertical offset ``e`` fitted on the ring alone and
    held there while the defect's offset is fitted, for a region that holds more than one surface (a groove
    across its box), whose single offset is the wrong model: the misfit moved ``e`` by a quarter of a pixel
    along a groove's slanted walls, and with it the groove's depth by a sixth. None when too few usable
    pixels remain or the fit does not settle. ``fit_ring`` followed by ``fit_defect``.
    """
    start = fit_ring(left, right, ring, defect, plane, delta0, defect_weights, search_px)
    return None if start is None else fit_defect(start, rows_from_ring)


def warm_up() -> SurfaceFit | None:
    """Fit a small synthetic pair (a plane 4 px of disparity away) once and measure its region's cells and
    their robust offset, so that the compiled kernels are loaded (0.1 s from numba's cache, 14 s to compile
    without it, with ``depth.warm_up``'s consensus kernel) before the first part rather than during it. Returns
    that fit."""
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (80, 120)).astype(np.float32), (0, 0), 1.5)
    left, right = texture[:, :100].copy(), texture[:, 4:104].copy()  # 4 px of disparity everywhere
    v, u = np.mgrid[20:60, 30:80]
    inside = (u >= 45) & (u < 65) & (v >= 32) & (v < 48)
    fit = fit_surface(left, right, (u[~inside], v[~inside]), (u[inside], v[inside]), (0.0, 0.0, 3.5))
    if fit is not None:
        offsets, sds, _, _ = cell_offsets(left, right, fit, (u[inside], v[inside]))
        robust_offset(offsets, sds, fit.delta)
    return fit


WINDOW_MARGIN_PX = int(3 * HIGH_PASS_SIGMA) + 8  # the filters' reach, the blur's and the interpolation's


def _window(left, right, ring, defect, theta, search_px):
    """The rows and columns a fit reads, cut from each image: (the left window's top-left corner, the right
    window's first column, left crop, right crop). The right image is read where the pixels lie less any
    disparity the fit may reach, and only there: the columns between would be filtered for nothing (a third
    of the window at WVGA, half at 2K)."""
    u = np.concatenate([ring[0], defect[0]])
    v = np.concatenate([ring[1], defect[1]])
    h, w = left.shape
    spread = abs(theta[1]) * (u.max() - u.min()) + abs(theta[2]) * (v.max() - v.min()) + abs(theta[3]) \
        + search_px + 2
    y0 = max(0, int(v.min()) - WINDOW_MARGIN_PX)
    y1 = min(h, int(v.max()) + 1 + WINDOW_MARGIN_PX)
    x0 = max(0, int(u.min()) - WINDOW_MARGIN_PX)
    x1 = min(w, int(u.max()) + 1 + WINDOW_MARGIN_PX)
    right_x0 = min(max(0, int(u.min() - abs(theta[0]) - spread) - WINDOW_MARGIN_PX), w - 1)
    right_x1 = max(min(w, int(u.max() - theta[0] + spread) + 1 + WINDOW_MARGIN_PX), right_x0 + 1)
    return (x0, y0), right_x0, left[y0:y1, x0:x1], right[y0:y1, right_x0:right_x1]


CONSENSUS_SAMPLES = 64
CONSENSUS_SIGMAS = 3.0
CONSENSUS_GAIN = 0.05  # share of the ring's cells that must come to agree (noise alone moves it ~0.04)


def _ring_cells(p: _Problem, theta: np.ndarray):
    """The ring's RING_CELL_PX cells' disparity offsets from the plane of ``theta`` (one Gauss-Newton step),
    their standard deviations and centres relative to the region's: (cell of each ring pixel, usable
    ring pixels, offsets, sds, du, dv)."""
    # compiled: called three times a fit, its NumPy steps over the ring were a tenth of a defect's time
    offset, sd, ok = surface_fit_numba.ring_cell_offsets(p.lvals, (p.R, p.Rx), p.right_saturated, p.usable, p.prior,
                                                         p.ur, p.v, p.du, p.dv, p.m, theta, p.ring_idx, p.ring_cell,
                                                         p.ring_cells, HUBER_K, 1e-3)
    return p.ring_cell, ok, offset, sd, p.ring_cell_du, p.ring_cell_dv


def _ring_consensus(p: _Problem, theta: np.ndarray) -> np.ndarray:
    """``theta`` with the ring's plane moved to the one most of its cells agree on (MSAC over triples of
    cells, deterministic): where part of the ring lies on another surface, a fit to all of it tilts
    between the two until no cell stands out."""
    _, _, offset, sd, du, dv = _ring_cells(p, theta)
    good = np.isfinite(sd)
    if good.sum() < 6:
        return theta
    e = offset[good]
    triples = np.random.default_rng(0).integers(0, len(e), size=(CONSENSUS_SAMPLES, 3))
    # compiled: every triple's plane and cost in one pass instead of NumPy's batched solves and a (triples x cells)
    # array
    shift, moved = surface_fit_numba.plane_consensus(e, sd[good], du[good], dv[good], triples, CONSENSUS_SIGMAS,
                                                     CONSENSUS_GAIN)
    if not moved:
        return theta
    theta = theta.copy()
    theta[[0, 1, 2]] += shift
    return theta


def _ring_cell_weights(p: _Problem, theta: np.ndarray) -> np.ndarray:
    """Tukey's weight of each ring pixel's RING_CELL_PX cell, from the cell's own disparity offset from the
    plane (one Gauss-Newton step from ``theta``) in units of its standard deviation. A cell on another
    surface (a defect's wall the box cut through, a neighbouring defect, the belt within a pixel) or
    where the eyes see the light differently (a sheen, a highlight) stands out of the others and drops.
    Returns (ring pixels,) weights in [0, 1], 0 for pixels the fit cannot use."""
    cell, ok, offset, sd, _, _ = _ring_cells(p, theta)
    z = np.where(np.isfinite(sd), offset / (TUKEY_K * sd), np.inf)
    return np.where(ok, _tukey_weights(z)[cell], 0.0)


def _exposure(p: _Problem, theta: np.ndarray) -> tuple[float, float]:
    """Gain and offset of the ring by least squares at the starting disparities."""
    ring = p.m == 0
    d = theta[0] + theta[1] * p.du[ring] + theta[2] * p.dv[ring]
    rv = sample(p.R, p.ur[ring] - d, p.v[ring], theta[E])
    lv = p.lvals[ring]
    ok = np.isfinite(rv)
    if ok.sum() < 3 or np.std(rv[ok]) < 1e-6:
        return 1.0, 0.0
    x, y = rv[ok], lv[ok]
    dx = x - x.mean()
    # the line's closed form: np.polyfit's SVD of a two-column design was a twentieth of a ring's fit
    g = float(np.dot(dx, y - y.mean()) / np.dot(dx, dx))
    return g, float(y.mean() - g * x.mean())


def _search_offset(p: _Problem, theta: np.ndarray, lo: float, hi: float) -> float | None:
    """The defect's offset in [lo, hi] with the least Huber cost over its pixels, the ring's parameters held
    (steps of SEARCH_STEP_PX, refined by the parabola through the least cost and its neighbours); None where the
    least cost lies beyond an end of the range: no minimum within it is one the images vouch for (a box across a
    pit's edge, its ring fitted tilted, read a 2.04 mm pit as an 8.2 mm bump from just beyond its range's end)."""
    scale = p.normal_equations(theta, np.flatnonzero(p.m == 0))[2]  # the ring's residuals' robust scale
    sel = p.usable & (p.m == 1)
    if not sel.any():
        return float(theta[3])
    u, v, w = p.ur[sel], p.v[sel], p.prior[sel]
    base = theta[0] + theta[1] * p.du[sel] + theta[2] * p.dv[sel]
    gain = theta[4] + theta[5] * p.du[sel] + theta[6] * p.dv[sel] + theta[8]
    lv = p.lvals[sel]

    def costs(deltas: np.ndarray) -> np.ndarray:
        # o + o_m: the defect's own exposure offset
        return surface_fit_numba.offset_costs(lv, p.R, u, v, base, gain, theta[7] + theta[9], w, theta[E], deltas,
                                              scale, HUBER_K)

    # every COARSE_STEP_PX first, then every SEARCH_STEP_PX around the least of those
    coarse = np.arange(lo, hi + COARSE_STEP_PX / 2, COARSE_STEP_PX)
    centre = float(coarse[int(np.argmin(costs(coarse)))])
    candidates = np.arange(centre - COARSE_STEP_PX, centre + COARSE_STEP_PX + SEARCH_STEP_PX / 2, SEARCH_STEP_PX)
    cost = costs(candidates)
    best = int(np.argmin(cost))
    found = float(candidates[best])
    if 0 < best < len(candidates) - 1:
        c0, c1, c2 = cost[best - 1: best + 2]
        curvature = c0 - 2 * c1 + c2
        if curvature > 0:
            found += 0.5 * SEARCH_STEP_PX * (c0 - c2) / curvature
    # the fine steps reach a coarse step past the range's ends: a least cost there lies outside what was searched
    return found if lo <= found <= hi else None


def sandwich(J: np.ndarray, r: np.ndarray, scale: float, p: np.ndarray, u: np.ndarray, v: np.ndarray
             ) -> tuple[np.ndarray, float] | None:
    """The covariance (P x P) of parameters fitted by Huber's M-estimator, and its inflation for correlated
    residuals; None where the information is singular.

    J: (N, P) the residuals' Jacobian; r: (N,) residuals (grey levels) at the solution; scale: their robust
    scale; p: (N,) each pixel's share; u, v: (N,) its integer image position. The M-estimator's sandwich
    ``A^-1 B A^-1``, with ``A = sum p psi' J J^T`` the derivative of its estimating equations (``psi'`` 1 within
    HUBER_K scales, 0 beyond; not the iterations' weights, with which the covariance came out 1.21x too narrow
    for Gaussian noise) and ``B = s^2 sum p^2 J J^T``, ``s^2`` the weighted residuals' mean square (independent
    pixels with one noise level). The eyes' vertical offset ``e`` has its prior (``_e_prior``) in ``A``. Pixels
    in the same CLUSTER_PX block may be correlated: the same sandwich with the block sums of the scores
    ``p h r J`` measures by how much for the surface's disparity ``c`` (the ring gives enough blocks to tell),
    and that factor (never below 1) scales the whole covariance.
    """
    groups = _cell_index(u, v, CLUSTER_PX)
    # compiled, one pass: its NumPy products over (N, P) arrays were a twentieth of a defect's time
    bread, meat, s2, g = surface_fit_numba.sandwich_sums(J.T, r, p, HUBER_K * scale, groups,
                                                         int(groups.max()) + 1 if groups.size else 0)
    bread[E, E] += _e_prior(scale)
    try:
        inv = np.linalg.inv(bread)
    except np.linalg.LinAlgError:
        return None
    if not (np.all(np.isfinite(inv)) and np.all(np.diag(inv) > 0)):
        return None
    dof = max(float(p.sum()) - J.shape[1], 1.0)
    model = inv @ meat @ inv * (s2 / dof)
    clustered = inv @ (g.T @ g) @ inv
    inflation = max(1.0, float(clustered[0, 0] / model[0, 0])) if model[0, 0] > 0 else 1.0
    return model * inflation, inflation


@dataclass(frozen=True)
class DefectImages:
    """The high-passed windows around a defect's region (``origin`` the left one's top-left corner in the image,
    ``right_x0`` the right one's first column; they share their rows): what ``cell_offsets`` and
    ``interior_variance`` read: the fit's own (``SurfaceFit.images``), or ``defect_images``'s for other images.
    ``R`` and ``Rx`` as their splines' coefficients (``spline``)."""

    origin: tuple[int, int]
    right_x0: int
    L: np.ndarray
    R: np.ndarray
    Rx: np.ndarray  # of R's horizontal gradient


def defect_images(left: np.ndarray, right: np.ndarray, fit: SurfaceFit,
                  defect: tuple[np.ndarray, np.ndarray]) -> DefectImages:
    """HxW float32 grey images (as given to ``fit_surface``) -> the high-passed window the defect's pixels
    ``defect`` (u, v) read at the fitted surface (``fit.images`` holds them already for the images the fit
    was given: its window holds the defect's and more)."""
    origin, right_x0, left, right = _window(left, right, defect, defect, fit.params, 1.0)
    R = spline(high_pass(right))
    return DefectImages(origin, right_x0, high_pass(left), R, gradient_x(R))


def cell_offsets(left: np.ndarray, right: np.ndarray, fit: SurfaceFit, defect: tuple[np.ndarray, np.ndarray],
                 weights: np.ndarray | None = None, cell_px: int = CELL_PX, iterations: int = 8,
                 images: DefectImages | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each ``cell_px`` square cell's own offset from the fitted plane, the fit's plane and exposure held.

    left, right: HxW float32 grey images (as given to ``fit_surface``); defect and weights as there;
    images: ``defect_images`` of them, where already built.
    Returns (offsets (K,), standard deviations (K,), inf for a cell with no gradient, centres (K, 2) as
    (u, v) px, settled (K,) bool: the cell's last step within CELL_SETTLED_PX), K the cells the region's pixels
    fall in, by Gauss-Newton per cell on the high-passed images."""
    th = fit.params
    images = images or defect_images(left, right, fit, defect)
    (x0, y0), L, R, Rx = images.origin, images.L, images.R, images.Rx
    u = (defect[0] - images.right_x0).astype(np.float64)
    rows, cols = defect[1] - y0, defect[0] - x0
    p = np.ones(len(u)) if weights is None else np.asarray(weights, dtype=np.float64)
    cell = _cell_index(defect[0], defect[1], cell_px)
    k = cell.max() + 1
    du, dv = defect[0] - fit.centre[0], defect[1] - fit.centre[1]
    plane = th[0] + th[1] * du + th[2] * dv
    gain = th[4] + th[5] * du + th[6] * dv + th[8]
    lv = L[rows, cols].astype(np.float64)
    # compiled: eight Gauss-Newton steps of a few dozen NumPy calls each were a millisecond a defect
    offsets, step, j = surface_fit_numba.cell_steps((R, Rx), u, rows, th[E], plane, gain, lv, (th[7], th[9]), p, cell,
                                                    k, fit.delta, fit.residual_sigma, HUBER_K, iterations, 0.5, 1e-4)
    info = np.bincount(cell, p * j * j, minlength=k)
    sd = np.full(k, np.inf)
    has = info > 0
    sd[has] = np.sqrt(fit.residual_sigma**2 * fit.inflation / info[has])
    centres = np.stack(_cell_means(cell, k, defect[0], defect[1]), axis=1)
    # a cell still stepping after the last iteration has not settled on one offset: on a texture that repeats
    # across the rows (a scratch's lines) it swings between the pattern's copies, a pixel or more apart
    return offsets, sd, centres, np.abs(step) <= CELL_SETTLED_PX


def _right_columns(fit: SurfaceFit, u: np.ndarray, v: np.ndarray, x0: float, on_defect: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the fit maps image pixels (u, v) (1-D) in the right image: (columns of a window whose left edge is
    image column ``x0``, float64; the pixels' offsets du, dv from the region's centre). on_defect: 1 for the
    defect's region, which lies the fitted offset off the ring's plane, 0 for the ring."""
    th = fit.params
    du, dv = u - fit.centre[0], v - fit.centre[1]
    return (u - x0) - (th[0] + th[1] * du + th[2] * dv + th[3] * on_defect), du, dv


def interior_variance(left: np.ndarray, right: np.ndarray, fit: SurfaceFit, defect: tuple[np.ndarray, np.ndarray],
                      weights: np.ndarray | None, box: tuple[float, float, float, float], margin: float,
                      images: DefectImages | None = None) -> float:
    """The variance (px^2) of the defect's offset from a region whose every pixel carried its interior's
    information: the interior the pixels at least ``margin`` px inside ``box`` (x0, y0, x1, y1), whose
    interpolation reads little outside the region. ``fit.residual_sigma^2 * fit.inflation / sum (g * R_x)^2``
    over them, at the fitted offset, times their share of the region's pixels; inf where no interior pixel
    carries a gradient. images: ``defect_images`` of the pair, where already built.

    A region's border may hold the edges of the defect's walls, which each eye sees at other places (their
    shading is view-dependent): where the region has no texture of its own, those edges alone decide the
    fit, and its curvature claims a precision the floor does not have. Where the border carries no more than
    its share, this is the whole region's own variance: its pixels lie on the floor too."""
    u, v = defect
    x0, y0, x1, y1 = box
    keep = (u >= x0 + margin) & (u + 1 <= x1 - margin) & (v >= y0 + margin) & (v + 1 <= y1 - margin)
    p = np.ones(len(u)) if weights is None else np.asarray(weights, dtype=np.float64)
    keep &= p > 0
    if not keep.any():
        return float("inf")
    th = fit.params
    images = images or defect_images(left, right, fit, defect)
    wy, Rx = images.origin[1], images.Rx
    x, du, dv = _right_columns(fit, u[keep], v[keep], images.right_x0, 1.0)
    gx = sample(Rx, x, (v[keep] - wy).astype(np.float64), th[E])
    gain = th[4] + th[5] * du + th[6] * dv + th[8]
    j = np.where(np.isfinite(gx), gain * gx, 0.0)
    information = float(np.sum(p[keep] * j * j))
    share = float(np.sum(p[keep]) / np.sum(p))
    return fit.residual_sigma ** 2 * fit.inflation * share / information if information > 0 else float("inf")


def contrast_ratio(fit: SurfaceFit, ring: tuple[np.ndarray, np.ndarray], defect: tuple[np.ndarray, np.ndarray],
                   defect_weights: np.ndarray | None = None) -> float:
    """How much stronger the left eye sees the defect's texture than the right eye does, against the ring's:
    (std L / std R over the region) / (std L / std R over the ring), each eye's high-passed image read at the
    fitted surface (the right eye's where the fit maps the pixel). 1 where the region is a shifted copy in the
    two eyes, as a plane is; beyond that where one eye sees what the other does not (a wall's sheen, a wall
    seen broad by one eye and edge-on by the other). ring, defect: (u, v) image pixels as given to
    ``fit_surface``, whose window (``fit.images``) holds them; the ring's pixels its cells left out
    (``fit.ring_weights``) and the region's of weight 0 are not read. 0 or inf where one eye sees texture in the
    region (or the ring) and the other none; nan where neither does, or no pixel is read."""
    (x0, y0), L, R = fit.images.origin, fit.images.L, fit.images.R
    right_x0, th = fit.images.right_x0, fit.params

    def ratio(u, v, on_defect, keep):
        u, v = u[keep], v[keep]
        right = sample(R, _right_columns(fit, u, v, right_x0, on_defect)[0], (v - y0).astype(np.float64), th[E])
        ok = np.isfinite(right)
        left, right = L[v - y0, u - x0][ok].astype(np.float64), right[ok]
        if len(right) < 2 or np.std(right) == 0:
            return float("nan") if len(right) < 2 or np.std(left) == 0 else float("inf")
        return np.std(left) / np.std(right)

    ring_keep = np.ones(len(ring[0]), bool) if fit.ring_weights is None else fit.ring_weights > 0.5
    region_keep = np.ones(len(defect[0]), bool) if defect_weights is None else np.asarray(defect_weights) > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        return float(np.float64(ratio(*defect, 1.0, region_keep)) / np.float64(ratio(*ring, 0.0, ring_keep)))


def cell_areas(defect: tuple[np.ndarray, np.ndarray], weights: np.ndarray | None = None,
               cell_px: int = CELL_PX) -> np.ndarray:
    """(K,) each ``cell_px`` cell's share of the region (the sum of its pixels' weights, 1 each if not
    given), in ``cell_offsets``'s order of the cells."""
    p = np.ones(len(defect[0])) if weights is None else np.asarray(weights, dtype=np.float64)
    cell = _cell_index(defect[0], defect[1], cell_px)
    return np.bincount(cell, p, minlength=cell.max() + 1 if cell.size else 0)


def robust_offset(offsets: np.ndarray, sds: np.ndarray, start: float, iterations: int = 20,
                  areas: np.ndarray | None = None) -> RobustOffset:
    """Tukey's M-estimate of the cells' common offset, from ``start``, cutting at TUKEY_K times each cell's
    standard deviation times the cells' robust spread in those units (at least 1).

    offsets, sds: (K,) each cell's offset and standard deviation. The cells are weighed by their
    information (1 / sd^2), or with ``areas`` (K,) by their share of the region. The variance is that of
    the weighted mean with the final weights held, times the Birge ratio (the weighted scatter of the kept
    cells about the estimate over what their standard deviations predict); below 1, its upper bound at
    ``BIRGE_CONFIDENCE_Z`` (between ``BIRGE_MIN`` and 1), so that few cells keep the variance their noise
    gives."""
    if offsets.shape != sds.shape or offsets.ndim != 1 or (areas is not None and np.shape(areas) != offsets.shape):
        raise ValueError(f"robust_offset: offsets {offsets.shape}, sds {sds.shape}"
                         f"{'' if areas is None else f' and areas {np.shape(areas)}'} must be the same (K,)")
    ok = np.isfinite(sds) & (sds > 0)
    if areas is not None:
        ok &= np.asarray(areas) > 0
    x, s = offsets[ok], sds[ok]
    if x.size == 0:
        return RobustOffset(start, np.inf, 0, 0.0, 1.0)
    prior = 1.0 / (s * s) if areas is None else np.asarray(areas, dtype=np.float64)[ok]
    # cells that scatter more than their noise says widen the cut, or good cells would be cut too. Cells that agree
    # better than their noise says: each cell's standard deviation comes from the fit's residuals, which hold the
    # renderer's or the sensor's aliasing as well as noise, and that misfit moves an offset less than noise would;
    # the scatter is believed only up to the upper bound of what so few cells could show at that ratio (compiled: in
    # NumPy's small steps a call took a tenth of a millisecond, eight calls a defect)
    mu, _, variance, weight, birge = surface_fit_numba.tukey_offset(x, s, prior, start, iterations, TUKEY_K,
                                                                    BIRGE_CONFIDENCE_Z, BIRGE_MIN)
    return RobustOffset(mu, variance, int(x.size), weight, birge)


def weighting_variance(offsets: np.ndarray, sds: np.ndarray, areas: np.ndarray, estimate: float,
                       z: float = 2.0) -> float:
    """How far ``estimate`` (the cells weighed by their information, ``robust_offset``) is from the
    region's offset weighed by area (the cells by their share of it), as a variance to add (px^2): the
    square of the difference where it exceeds ``z`` standard deviations of the area-weighed offset, less
    those; 0 where the two agree.

    The truth is the offset over the region's area, while the information-weighed estimate reads it
    where the texture is strongest: on an uneven region (a narrow pit seen slanted, whose wall crosses
    the box) those can be the wall's cells alone. offsets, sds, areas: (K,) as ``cell_offsets`` and
    ``cell_areas`` give them."""
    by_area = robust_offset(offsets, sds, estimate, areas=areas)
    if not np.isfinite(by_area.variance):
        return 0.0
    noise = by_area.variance / max(by_area.birge, 1.0)  # the cells' own noise, not their scatter beyond it
    return max(0.0, (by_area.delta - estimate) ** 2 - z * z * noise)


def bowl(du: np.ndarray, dv: np.ndarray) -> np.ndarray:
    """(K,) the square of each cell's distance (du, dv) (K,) from a centre, in the cells' half-widths along u and
    v: the shape of a round pit seen through a box about its size (``unevenness_variance``, ``band_scan``)."""
    return (du / max(np.abs(du).max(), 1.0)) ** 2 + (dv / max(np.abs(dv).max(), 1.0)) ** 2


def unevenness_variance(offsets: np.ndarray, sds: np.ndarray, centres: np.ndarray, z: float = 2.0) -> float:
    """How much the defect's offset varies over its region beyond what the cells' noise explains, as a
    variance (px^2) to add to the offset's: a surface is fitted to the cells' offsets (weights 1 / sd^2), a
    plane and, with RADIAL_MIN_CELLS cells or more, a bowl (the square of the distance from the region's
    centre, in its half-widths), and each term adds its spread over the region (its rms over the cells)
    where its coefficient is more than ``z`` of its own standard deviations from 0 (those from the cells'
    scatter about the surface where it exceeds their sds); 0 for a flat floor.

    The plane is a box cut through a wall on one side; the bowl a box larger than the defect, whose region
    holds its walls all round: the region's mean then lies between the floor and the surface around it.

    offsets, sds: (K,) as ``cell_offsets`` gives them; centres: (K, 2) their (u, v)."""
    ok = np.isfinite(sds) & (sds > 0)
    if ok.sum() < 4:
        return 0.0
    x, s, c = offsets[ok], sds[ok], centres[ok]
    w = 1.0 / (s * s)
    du, dv = c[:, 0] - np.average(c[:, 0], weights=w), c[:, 1] - np.average(c[:, 1], weights=w)
    terms = [du, dv]
    if len(x) >= RADIAL_MIN_CELLS:
        r2 = bowl(du, dv)
        terms.append(r2 - np.average(r2, weights=w))
    design = np.stack([np.ones_like(x), *terms], axis=1)
    normal = (design * w[:, None]).T @ design
    try:
        cov = np.linalg.inv(normal)
    except np.linalg.LinAlgError:
        return 0.0
    beta = cov @ ((design * w[:, None]).T @ x)
    # the coefficients' uncertainty from the cells' own scatter about the surface where that is the larger
    chi2 = float(np.sum(w * (x - design @ beta) ** 2) / max(len(x) - design.shape[1], 1))
    cov = cov * max(1.0, chi2)
    excess = 0.0
    for i, spread in enumerate(terms, start=1):
        if cov[i, i] > 0 and abs(beta[i]) > z * np.sqrt(cov[i, i]):
            excess += (beta[i] ** 2 - z * z * cov[i, i]) * float(np.mean(spread * spread))
    return float(excess)
