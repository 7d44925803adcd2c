"""``core.surface_fit`` on exact synthetic pairs: a textured tilted plane with a flat-bottomed step."""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from synthetic_pairs import step_pair

from core import surface_fit as sf
from core import surface_fit_numba as sfn
from core.depth import ring_mask

PLANE = (0.02, -0.01, 40.0)
BOX = (60, 45, 100, 75)
FIXTURES = Path(__file__).parent / "fixtures" / "surface_fit"


def _regions(box=BOX, inner=(68, 51, 92, 69), shape=(120, 160)):
    rv, ru = np.nonzero(ring_mask(shape, box, 3, 12))
    vv, uu = np.mgrid[inner[1]:inner[3], inner[0]:inner[2]]
    return (ru, rv), (uu.ravel(), vv.ravel())


def _plane_at(u, v, plane=PLANE):
    return plane[0] * u + plane[1] * v + plane[2]


def _huber_weights(r, scale):
    """Huber's weights of residuals ``r`` at ``scale``: the NumPy reference of the compiled kernels' own."""
    k = sf.HUBER_K * scale
    a = np.abs(r)
    return np.where(a <= k, 1.0, k / np.maximum(a, 1e-12))


def _floor(left, pixels, noise):
    gx = sf.gradient_x(left)
    return noise * math.sqrt(2) / math.sqrt(float(np.sum(gx[pixels[1], pixels[0]] ** 2)))


class TestHighPass:
    def test_removes_what_varies_slowly_and_keeps_the_shape(self):
        v, u = np.mgrid[0:80, 0:100].astype(np.float32)
        ramp = 100 + 0.5 * u + 0.2 * v
        out = sf.high_pass(ramp)
        assert out.shape == ramp.shape and out.dtype == np.float32
        assert np.abs(out[20:60, 20:80]).max() < 0.5  # a ramp is light, not texture

    def test_keeps_fine_texture(self):
        texture = np.random.default_rng(0).normal(0, 10, (80, 100)).astype(np.float32)
        assert np.corrcoef(sf.high_pass(texture + 50).ravel(), texture.ravel())[0, 1] > 0.95


class TestLowPass:
    @pytest.mark.parametrize("shape", [(170, 270), (171, 273), (33, 300), (376, 672)])
    def test_equals_the_direct_blur_border_included(self, shape):
        # a textured plate under a light that falls off across it, as the evaluation sets render it
        v, u = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float32)
        texture = cv2.GaussianBlur(np.random.default_rng(0).normal(0, 40, shape).astype(np.float32), (0, 0), 1.2)
        image = 120 + 0.3 * u - 0.2 * v + 20 * np.sin(u / 37.0) + texture
        got, want = sf.low_pass(image, 10.0), cv2.GaussianBlur(image, (0, 0), 10.0)
        assert got.shape == image.shape and got.dtype == np.float32
        assert np.abs(got - want).max() < 0.02

    @pytest.mark.parametrize("shape,sigma", [((31, 200), 10.0), ((120, 160), 2.0)])
    def test_small_images_and_narrow_blurs_take_the_direct_filter(self, shape, sigma):
        image = np.random.default_rng(1).normal(100, 20, shape).astype(np.float32)
        assert np.array_equal(sf.low_pass(image, sigma), cv2.GaussianBlur(image, (0, 0), sigma))


class TestSpline:
    def test_passes_through_the_pixels(self):
        image = np.random.default_rng(0).uniform(0, 255, (30, 40)).astype(np.float32)
        c = sf.spline(image)
        assert c.shape == image.shape and c.dtype == np.float32
        v, u = np.mgrid[1:27, 1:37]
        got = sf.sample(c, u.ravel().astype(float), v.ravel(), 0.0)
        np.testing.assert_allclose(got, image[1:27, 1:37].ravel(), atol=1e-3)

    @pytest.mark.parametrize("frequency, spline_within, cubic_beyond", [(0.1, 0.001, 0.02), (0.2, 0.01, 0.015)])
    def test_a_shift_moves_texture_less_than_cubic_convolution(self, frequency, spline_within, cubic_beyond):
        # texture of ``frequency`` cycles a pixel (amplitude 1) read a fraction of a pixel off its pixels: the
        # spline returns it shifted; OpenCV's cubic convolution damps it by another amount at each fraction
        x = np.arange(200, dtype=np.float64)
        image = np.tile(np.sin(2 * np.pi * frequency * x), (12, 1)).astype(np.float32)
        at = np.linspace(20.0, 180.0, 300) + 0.37
        truth = np.sin(2 * np.pi * frequency * at)
        spline = sf.sample(sf.spline(image), at, np.full(at.size, 6), 0.0)
        cubic = cv2.remap(image, at.astype(np.float32)[None], np.full((1, at.size), 6, np.float32),
                          cv2.INTER_CUBIC)[0]
        assert np.abs(spline - truth).max() < spline_within < cubic_beyond < np.abs(cubic - truth).max()

    def test_a_sample_whose_taps_leave_the_image_is_nan_and_no_other(self):
        ramp = np.add.outer(10.0 * np.arange(10), np.arange(10)).astype(np.float32)  # reproduced exactly
        c = sf.spline(ramp)
        out = sf.sample(c, np.array([1.0, 0.5, 4.25, 7.0, 7.5, 3.0]), np.array([5, 5, 2, 5, 5, 7]), 0.0)
        assert out[0] == pytest.approx(51.0, abs=1e-3) and math.isnan(out[1])
        assert out[2] == pytest.approx(24.25, abs=1e-3) and out[3] == pytest.approx(57.0, abs=1e-3)
        assert math.isnan(out[4])
        assert out[5] == pytest.approx(73.0, abs=1e-3)
        assert math.isnan(sf.sample(c, np.array([3.0]), np.array([7]), 0.5)[0])  # row 7.5: beyond h - 3

    def test_samples_on_rows_moved_by_e(self):
        # a ramp, away from the border (the spline mirrors the image beyond it, and bends there)
        ramp = np.add.outer(10.0 * np.arange(30), np.arange(30)).astype(np.float32)
        out = sf.samples((sf.spline(ramp), sf.spline(2 * ramp)), np.array([9.5, 12.0]), np.array([10, 12]), -0.25)
        np.testing.assert_allclose(out, [[107.0, 129.5], [214.0, 259.0]], atol=1e-3)

    def test_a_gradients_spline_is_the_gradient_of_the_images_spline_away_from_the_border(self):
        # the fit reads the gradients' splines as the central differences of the image's own coefficients
        image = np.random.default_rng(4).uniform(0, 255, (80, 90)).astype(np.float32)
        c = sf.spline(image)
        for gradient, border in ((sf.gradient_x, np.s_[:, :2]), (sf.gradient_y, np.s_[:2])):
            of_image, of_spline = sf.spline(gradient(image)), gradient(c)
            np.testing.assert_allclose(of_spline[25:-25, 25:-25], of_image[25:-25, 25:-25], atol=1e-3)
            assert np.abs(of_spline[border] - of_image[border]).max() > 0.1  # not alike at the border itself
        v, u = np.mgrid[30:50, 30:60]
        x = u.ravel() + 0.37
        np.testing.assert_allclose(sf.sample(sf.gradient_x(c), x, v.ravel(), 0.25),
                                   sf.sample(sf.spline(sf.gradient_x(image)), x, v.ravel(), 0.25), atol=1e-3)

    def test_shapes_and_rows_are_checked(self):
        c = sf.spline(np.zeros((10, 10), np.float32))
        with pytest.raises(ValueError, match="whole numbers"):
            sf.sample(c, np.array([3.0]), np.array([4.5]), 0.0)
        with pytest.raises(ValueError, match="alike"):
            sf.sample(c, np.array([3.0, 4.0]), np.array([4]), 0.0)
        with pytest.raises(ValueError, match="float32 of one shape"):
            sf.samples((c, c[:5]), np.array([3.0]), np.array([4]), 0.0)
        with pytest.raises(ValueError, match="HxW"):
            sf.spline(np.zeros((4, 4, 3), np.float32))


def _problem(theta_shift=0.0, saturate=False):
    """A fit's problem on the step pair (its ring and region, the images high-passed), and a theta near the
    truth moved ``theta_shift`` px in disparity."""
    left, right, _ = step_pair(plane=PLANE, step_px=-0.3, seed=3)
    if saturate:  # a bright band in the right image: samples that read it are unusable
        right = right.copy()
        right[60:64] = 255.0
    ring, defect = _regions()
    centre = (80.0, 60.0)
    prior = np.concatenate([np.ones(len(ring[0])), np.linspace(0.2, 1.0, len(defect[0]))])
    p = sf._Problem(sf.high_pass(left), sf.high_pass(right), ring, defect, prior, left, right, centre)
    theta = np.array([_plane_at(*centre) + theta_shift, PLANE[0], PLANE[1], -0.3, 1.05, 1e-3, -1e-3, 3.0, 0.02,
                      0.5, 0.15])
    return p, theta


def _numpy_residuals(p, theta, idx=None):
    """(residuals, Jacobian rows (n, 11), usable) of ``p`` (a ``_Problem``) at ``theta`` on its current level's
    images for the pixels ``idx`` (indices; all if None), from NumPy's arithmetic on the spline's samples: what the
    compiled kernels are held to."""
    idx = slice(None) if idx is None else idx
    du, dv, m, u, v = p.du[idx], p.dv[idx], p.m[idx], p.ur[idx], p.v[idx]
    e = theta[sf.E]
    x = u - (theta[0] + theta[1] * du + theta[2] * dv + theta[3] * m)
    rv, gx, gy = sf.samples((p.R, p.Rx, p.Ry), x, v, e)
    ok = p.usable[idx] & np.isfinite(rv) & np.isfinite(gx) & np.isfinite(gy)
    column = np.clip(np.rint(x), 0, p.R.shape[1] - 1).astype(np.intp)
    row = np.clip(np.rint(v + e), 0, p.R.shape[0] - 1).astype(np.intp)
    ok &= ~p.right_saturated[row, column]
    gain = theta[4] + theta[5] * du + theta[6] * dv + theta[8] * m
    r = p.lvals[idx] - gain * rv - theta[7] - theta[9] * m
    J = np.stack([gain * gx, gain * gx * du, gain * gx * dv, gain * gx * m, -rv, -rv * du, -rv * dv,
                  -np.ones_like(rv), -rv * m, -m, -(gain * gy)], axis=1)
    return r, J, ok


def _numpy_system(p, theta, idx):
    """The Gauss-Newton system as NumPy builds it from ``_numpy_residuals``."""
    r, J, ok = _numpy_residuals(p, theta, idx)
    r, J = r[ok], J[ok]
    scale = sf._robust_scale(r)
    w = _huber_weights(r, scale) * p.prior[idx[ok]]
    return (J.T * w) @ J, -((J.T * w) @ r), scale, int(ok.sum())


class TestNormalEquations:
    def _compiled(self, p, theta, idx, floor=1e-3):
        return sfn.normal_equations(p.lvals, (p.R, p.Rx, p.Ry), p.right_saturated, p.usable, p.prior, p.u, p.v, p.du,
                                    p.dv, p.m, theta, idx, sf.HUBER_K, floor)

    @pytest.mark.parametrize("level", [0.0, 2.0])
    @pytest.mark.parametrize("shift,saturate", [(0.0, False), (60.0, False), (0.0, True)])
    def test_equals_the_numpy_system(self, level, shift, saturate):
        # a shift of 60 px sends a third of the samples out of the image; the band saturates some
        p, theta = _problem(shift, saturate)
        p.level(level)
        idx = np.flatnonzero(np.random.default_rng(0).random(len(p.u)) < 0.7)
        A, b, scale, count = self._compiled(p, theta, idx)
        A_ref, b_ref, scale_ref, count_ref = _numpy_system(p, theta, idx)
        assert 100 < count == count_ref <= len(idx)
        assert (count < 0.95 * len(idx)) == (shift > 0 or saturate)
        assert scale == pytest.approx(scale_ref, rel=1e-5)
        np.testing.assert_allclose(A, A_ref, rtol=1e-5, atol=1e-6 * np.abs(A_ref).max())
        np.testing.assert_allclose(b, b_ref, rtol=1e-5, atol=1e-6 * np.abs(b_ref).max())

    def test_residuals_without_spread_take_the_floor_scale(self):
        p, theta = _problem()
        p.lvals = np.zeros_like(p.lvals)
        # every residual is -(o + o_m m): no spread on the ring alone
        p.R, p.Rx, p.Ry = (np.zeros_like(p.R) for _ in range(3))
        ring = np.flatnonzero(p.m == 0)
        _, _, scale, count = self._compiled(p, theta, ring, floor=0.25)
        assert scale == 0.25 and count > 100

    def test_shape_checks(self):
        p, theta = _problem()
        idx = np.arange(10)
        with pytest.raises(ValueError, match="prior"):
            sfn.normal_equations(p.lvals, (p.R, p.Rx, p.Ry), p.right_saturated, p.usable, p.prior[:-1], p.u, p.v,
                                 p.du, p.dv, p.m, theta, idx, 1.0, 1e-3)
        with pytest.raises(ValueError, match="splines"):
            sfn.normal_equations(p.lvals, (p.R, p.Rx), p.right_saturated, p.usable, p.prior, p.u, p.v, p.du, p.dv, p.m,
                                 theta, idx, 1.0, 1e-3)
        with pytest.raises(ValueError, match="theta"):
            sfn.normal_equations(p.lvals, (p.R, p.Rx, p.Ry), p.right_saturated, p.usable, p.prior, p.u, p.v, p.du,
                                 p.dv, p.m, theta[:4], idx, 1.0, 1e-3)


class TestJacobianRows:
    @pytest.mark.parametrize("shift,saturate", [(0.0, False), (60.0, False), (0.0, True)])
    def test_equals_the_numpy_rows_on_the_usable_pixels(self, shift, saturate):
        p, theta = _problem(shift, saturate)
        idx = np.flatnonzero(np.random.default_rng(1).random(len(p.u)) < 0.7)
        r, jt, kept = sfn.jacobian_rows(p.lvals, (p.R, p.Rx, p.Ry), p.right_saturated, p.usable, p.ur, p.v, p.du,
                                        p.dv, p.m, theta, idx)
        r_ref, J_ref, ok = _numpy_residuals(p, theta, idx)
        assert (len(kept) < 0.95 * len(idx)) == (shift > 0 or saturate)
        np.testing.assert_array_equal(kept, np.flatnonzero(ok))
        # the kernel's samples are float64 where ``sample_rows`` gives float32
        np.testing.assert_allclose(r, r_ref[ok], rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(jt, J_ref[ok].T, rtol=1e-5, atol=1e-5)

    def test_shape_checks(self):
        p, theta = _problem()
        with pytest.raises(ValueError, match="jacobian_rows: du"):
            sfn.jacobian_rows(p.lvals, (p.R, p.Rx, p.Ry), p.right_saturated, p.usable, p.ur, p.v, p.du[1:], p.dv,
                              p.m, theta, np.arange(5))


def _numpy_gauss_newton(p, theta, free, iterations, idx, tolerance):
    """Gauss-Newton as NumPy takes its steps from ``_numpy_system``: the reference of the compiled driver."""
    free = np.asarray(free)
    for _ in range(iterations):
        A, b, scale, count = _numpy_system(p, theta, idx)
        if count < len(free) + 2:
            return None, False
        A, b = A[np.ix_(free, free)], b[free]
        if sf.E in free:
            k = list(free).index(sf.E)
            A[k, k] += sf._e_prior(scale)
            b[k] -= sf._e_prior(scale) * theta[sf.E]
        step = np.linalg.solve(A, b)
        theta = theta.copy()
        theta[free] += step
        if max(abs(step[i]) for i, f in enumerate(free) if f in (0, 3)) < tolerance:
            return theta, True
    return theta, False


class TestGaussNewton:
    @staticmethod
    def _compiled(p, theta, free, iterations, idx, tolerance):
        return sfn.gauss_newton(p.lvals, (p.R, p.Rx, p.Ry), p.right_saturated, p.usable, p.prior, p.ur, p.v, p.du,
                                p.dv, p.m, theta, idx, free, iterations, tolerance, sf.HUBER_K, 1e-3, sf.E_PRIOR_PX)

    @pytest.mark.parametrize("level", [0.0, 2.0])
    @pytest.mark.parametrize("free,ring_only", [(sf.RING, True), (sf.ALL, False), (sf.ALL[:-1], False)])
    def test_takes_the_numpy_steps(self, level, free, ring_only):
        p, theta = _problem(0.4)
        p.level(level)
        idx = np.flatnonzero(p.m == 0) if ring_only else np.arange(len(p.u))
        for iterations in (1, 2, 8):
            got, settled = self._compiled(p, theta, free, iterations, idx, sf.TOLERANCE_PX)
            want, want_settled = _numpy_gauss_newton(p, theta, free, iterations, idx, sf.TOLERANCE_PX)
            assert settled == want_settled
            # NumPy's steps come from float32 samples, the kernel's from float64 ones
            np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7)
        assert settled  # eight steps reach the tolerance
        held = [i for i in sf.ALL if i not in free]
        np.testing.assert_array_equal(got[held], theta[held])

    def test_finds_the_plane_and_the_step(self):
        # the pair's truth: the plane PLANE and a region 0.3 px nearer (step_px=-0.3); started 0.4 px off
        p, theta = _problem(0.4)
        got, settled = self._compiled(p, theta, sf.ALL, 10, np.arange(len(p.u)), sf.TOLERANCE_PX)
        assert settled
        assert got[0] == pytest.approx(_plane_at(80.0, 60.0), abs=0.01)
        assert got[3] == pytest.approx(-0.3, abs=0.01)

    def test_fails_without_pixels_enough_or_information(self):
        p, theta = _problem()
        assert self._compiled(p, theta, sf.ALL, 5, np.arange(12), sf.TOLERANCE_PX) == (None, False)
        p.R, p.Rx, p.Ry = (np.zeros_like(p.R) for _ in range(3))  # no texture: the disparity's rows are 0
        assert self._compiled(p, theta, sf.ALL, 5, np.arange(len(p.u)), sf.TOLERANCE_PX) == (None, False)

    def test_shape_checks(self):
        p, theta = _problem()
        idx = np.arange(len(p.u))
        for free in ([0, 0, 1], [11], []):
            with pytest.raises(ValueError, match="gauss_newton: free"):
                self._compiled(p, theta, free, 3, idx, sf.TOLERANCE_PX)
        with pytest.raises(ValueError, match="gauss_newton: theta"):
            self._compiled(p, theta[:5], sf.ALL, 3, idx, sf.TOLERANCE_PX)


def _numpy_plane_consensus(e, s, x, y, triples, cut_sds, min_gain):
    """MSAC over the triples as NumPy's batched solves and (triples x cells) arrays do it: the kernel's reference."""
    design = np.stack([np.ones_like(x), x, y], axis=1)
    systems = design[triples]
    solvable = np.abs(np.linalg.det(systems)) > 0
    if not solvable.any():
        return np.zeros(3), False
    planes = np.linalg.solve(systems[solvable], e[triples[solvable]][..., None])[..., 0]
    z2 = ((planes[:, :1] + planes[:, 1:2] * x + planes[:, 2:3] * y - e) / s) ** 2
    best = planes[int(np.argmin(np.minimum(z2, cut_sds**2).sum(axis=1)))]
    inliers = np.abs(design @ best - e) <= cut_sds * s
    if inliers.mean() - (np.abs(e) <= cut_sds * s).mean() < min_gain:
        return np.zeros(3), False
    w = 1.0 / s[inliers] ** 2
    return np.linalg.solve((design[inliers] * w[:, None]).T @ design[inliers],
                           (design[inliers] * w[:, None]).T @ e[inliers]), True


class TestPlaneConsensus:
    @staticmethod
    def _cells(seed, other_share):
        """60 ring cells on a plane 0.1 px off the fitted one, ``other_share`` of them (one side) on another surface
        0.8 px away, each read with its noise."""
        rng = np.random.default_rng(seed)
        x, y = rng.uniform(-40, 40, 60), rng.uniform(-30, 30, 60)
        s = rng.uniform(0.02, 0.05, 60)
        e = 0.1 + 0.002 * x - 0.001 * y + rng.normal(0, 1, 60) * s
        e[x > 40 - 80 * other_share] += 0.8
        triples = np.random.default_rng(0).integers(0, 60, size=(sf.CONSENSUS_SAMPLES, 3))
        return e, s, x, y, triples

    @pytest.mark.parametrize("seed", [0, 1, 2])
    def test_moves_to_the_plane_most_cells_agree_on_as_numpy_finds_it(self, seed):
        e, s, x, y, triples = self._cells(seed, 0.3)
        got, moved = sfn.plane_consensus(e, s, x, y, triples, sf.CONSENSUS_SIGMAS, sf.CONSENSUS_GAIN)
        want, want_moved = _numpy_plane_consensus(e, s, x, y, triples, sf.CONSENSUS_SIGMAS, sf.CONSENSUS_GAIN)
        assert moved and want_moved
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
        assert got == pytest.approx([0.1, 0.002, -0.001], abs=0.02)  # the plane, not the other surface

    def test_stays_where_the_fitted_plane_already_holds_the_cells(self):
        e, s, x, y, triples = self._cells(3, 0.0)
        e -= 0.1 + 0.002 * x - 0.001 * y  # the fitted plane is the cells' own
        assert sfn.plane_consensus(e, s, x, y, triples, sf.CONSENSUS_SIGMAS, sf.CONSENSUS_GAIN)[1] is False
        assert _numpy_plane_consensus(e, s, x, y, triples, sf.CONSENSUS_SIGMAS, sf.CONSENSUS_GAIN)[1] is False

    def test_triples_of_one_cell_define_no_plane(self):
        e, s, x, y, _ = self._cells(4, 0.3)
        alike = np.repeat(np.arange(5)[:, None], 3, axis=1)
        plane, moved = sfn.plane_consensus(e, s, x, y, alike, sf.CONSENSUS_SIGMAS, sf.CONSENSUS_GAIN)
        assert not moved and plane.tolist() == [0.0, 0.0, 0.0]

    def test_shape_checks(self):
        e, s, x, y, triples = self._cells(5, 0.3)
        with pytest.raises(ValueError, match="plane_consensus: y"):
            sfn.plane_consensus(e, s, x, y[1:], triples, 3.0, 0.05)
        with pytest.raises(ValueError, match="plane_consensus: triples"):
            sfn.plane_consensus(e, s, x, y, triples + 60, 3.0, 0.05)


class TestSolve:
    def test_equals_numpy_and_says_singular(self):
        rng = np.random.default_rng(0)
        for n in (1, 3, 11):
            a, b = rng.standard_normal((n, n)), rng.standard_normal(n)
            np.testing.assert_allclose(sfn._solve(a, b), np.linalg.solve(a, b), rtol=1e-10, atol=1e-12)
        a = rng.standard_normal((4, 4))
        a[2] = a[0] + a[1]  # one row the sum of two others
        a[:, 3] = 0.0
        assert np.isnan(sfn._solve(a, np.ones(4))).all()


class TestRingCellOffsets:
    """``surface_fit_numba.ring_cell_offsets`` against the ring's cells as NumPy reads them from
    ``_numpy_residuals``."""

    @staticmethod
    def _numpy(p, theta, idx, cell, k):
        r, J, ok = _numpy_residuals(p, theta, idx)
        j, ok = J[:, 0], ok & (p.prior[idx] > 0)
        scale = sf._robust_scale(r[ok])
        h = np.where(ok, _huber_weights(r, scale), 0.0)
        with np.errstate(invalid="ignore"):
            info = np.bincount(cell, h * j * j, minlength=k)
            offset = -np.bincount(cell, h * j * r, minlength=k) / np.maximum(info, 1e-12)
            sd = np.where(info > 0, scale / np.sqrt(np.maximum(info, 1e-12)), np.inf)
        return offset, sd, ok

    @pytest.mark.parametrize("shift,saturate", [(0.0, False), (0.4, False), (60.0, False), (0.0, True)])
    def test_equals_the_numpy_cells(self, shift, saturate):
        # 60 px sends a third of the samples out of the image (their cells have no number); the band saturates some
        p, theta = _problem(shift, saturate)
        p.prior[::7] = 0.0  # pixels of no share
        got = sfn.ring_cell_offsets(p.lvals, (p.R, p.Rx), p.right_saturated, p.usable, p.prior, p.ur, p.v, p.du, p.dv,
                                    p.m, theta, p.ring_idx, p.ring_cell, p.ring_cells, sf.HUBER_K, 1e-3)
        want = self._numpy(p, theta, p.ring_idx, p.ring_cell, p.ring_cells)
        for a, b in zip(got, want):
            np.testing.assert_array_equal(a, b)
        offset, sd, ok = got
        assert not ok[::7].any()
        assert np.isnan(offset).any() == (shift > 1)
        if shift == 0.4:  # the ring's cells see the plane 0.4 px away
            assert np.median(offset[np.isfinite(sd)]) == pytest.approx(-0.4, abs=0.05)

    def test_shape_checks(self):
        p, theta = _problem()
        args = [p.lvals, (p.R, p.Rx), p.right_saturated, p.usable, p.prior, p.ur, p.v, p.du, p.dv, p.m, theta,
                p.ring_idx, p.ring_cell, p.ring_cells, 1.0, 1e-3]
        with pytest.raises(ValueError, match="prior"):
            sfn.ring_cell_offsets(*args[:4], p.prior[:-1], *args[5:])
        with pytest.raises(ValueError, match="splines"):
            sfn.ring_cell_offsets(args[0], (p.R, p.Rx, p.Ry), *args[2:])
        with pytest.raises(ValueError, match="cell"):
            sfn.ring_cell_offsets(*args[:12], p.ring_cell[:-1], *args[13:])


class TestCellIndex:
    def test_numbers_the_cells_present_in_reading_order(self):
        u, v = np.array([7, 0, 8, 30, 2, 31]), np.array([0, 9, 1, 0, 8, 5])
        # cells (column, row) (0, 0), (0, 1), (1, 0), (3, 0): row 0 first, then row 1
        assert sf._cell_index(u, v, 8).tolist() == [0, 3, 1, 2, 3, 2]
        rng = np.random.default_rng(1)
        u, v = rng.integers(0, 700, 2000), rng.integers(0, 400, 2000)
        for px in (1, 3, 12):
            want = np.unique((v // px) * 100_000 + u // px, return_inverse=True)[1]
            assert np.array_equal(sf._cell_index(u, v, px), want)
            assert np.array_equal(sf._cell_index(u.astype(float), v.astype(float), px), want)
        assert sf._cell_index(np.zeros(0, int), np.zeros(0, int), 3).size == 0


class TestRobustScale:
    @staticmethod
    def cases():
        rng = np.random.default_rng(4)
        yield from (rng.standard_normal(n) for n in (1, 2, 3, 4, 9, 100, 101, 4000))
        yield from (np.round(2 * rng.standard_normal(n)) for n in (2, 3, 10, 11, 1000, 1001))  # ties
        # runs along an image, one value, a lone outlier, the middle pair in bins of their own
        yield np.cumsum(rng.standard_normal(3000))
        yield np.full(7, 3.0)
        yield np.r_[np.zeros(500), 1e6]
        yield np.r_[np.zeros(501), 1e6, -1e6]
        yield np.r_[-1e6, np.zeros(3), np.ones(3), 1e6]

    def test_the_median_is_numpys(self):
        for x in self.cases():
            assert sfn._median(x) == np.median(x), x.size
        assert math.isnan(sfn._median(np.zeros(0)))

    def test_the_scale_is_the_mad_of_normal_residuals(self):
        for x in self.cases():
            assert sfn.robust_scale(x) == 1.4826 * np.median(np.abs(x - np.median(x)))
        x = np.random.default_rng(5).normal(0.0, 3.0, 20000)
        x[:400] = 500.0  # a few outliers hardly move it
        assert sfn.robust_scale(x) == pytest.approx(3.0, rel=0.05)


class TestSandwich:
    """``sandwich`` against the spread of Huber's estimates themselves over many noise draws."""

    N, P = 1600, len(sf.PARAMS)

    def _huber_fit(self, J, y, w):
        theta = np.linalg.lstsq(J, y, rcond=None)[0]
        for _ in range(30):
            r = y - J @ theta
            h = _huber_weights(r, sf._robust_scale(r)) * w
            theta = np.linalg.solve((J.T * h) @ J, (J.T * h) @ y)
        return theta, y - J @ theta

    def _draws(self, noise, draws=400, seed=7):
        rng = np.random.default_rng(seed)
        J = rng.normal(size=(self.N, self.P))
        u, v = rng.permutation(np.arange(self.N)) % 40, rng.permutation(np.arange(self.N)) // 40
        w = rng.uniform(0.5, 1.0, self.N)  # pixels' shares, as a region's border cuts them
        estimates, variances = [], []
        for _ in range(draws):
            theta, r = self._huber_fit(J, noise(rng), w)
            cov, _ = sf.sandwich(J, r, sf._robust_scale(r), w, u, v)
            estimates.append(theta[0])
            variances.append(cov[0, 0])
        return np.var(estimates), np.mean(variances)

    def test_gaussian_noise_is_covered_as_it_spreads_the_estimates(self):
        spread, reported = self._draws(lambda rng: rng.normal(0.0, 2.0, self.N))
        # the iterations' weights as the bread reported 0.71 of the spread
        assert reported / spread == pytest.approx(1.0, abs=0.15)

    def test_noise_with_outliers_is_covered_too(self):
        def noise(rng):
            n = rng.normal(0.0, 2.0, self.N)
            wild = rng.random(self.N) < 0.05
            n[wild] = rng.normal(0.0, 30.0, wild.sum())
            return n
        spread, reported = self._draws(noise)
        assert reported / spread == pytest.approx(1.0, abs=0.2)

    def test_residuals_shared_by_neighbours_inflate_it(self):
        rng = np.random.default_rng(3)
        J = rng.normal(size=(self.N, self.P))
        J[:, 0] = np.repeat(rng.normal(size=self.N // 16), 16)  # c's column and the noise alike in blocks of 4 x 4
        u = (np.arange(self.N) // 16 % 10) * 4 + np.arange(self.N) % 4
        v = (np.arange(self.N) // 160) * 4 + np.arange(self.N) // 4 % 4
        w = np.ones(self.N)
        shared = np.repeat(rng.normal(0.0, 2.0, self.N // 16), 16)
        _, r = self._huber_fit(J, shared + rng.normal(0.0, 0.5, self.N), w)
        _, inflation = sf.sandwich(J, r, sf._robust_scale(r), w, u, v)
        assert inflation > 3.0
        _, r = self._huber_fit(J, rng.normal(0.0, 2.0, self.N), w)
        assert sf.sandwich(J, r, sf._robust_scale(r), w, u, v)[1] < 1.5

    def test_a_parameter_the_pixels_do_not_inform_has_no_covariance(self):
        rng = np.random.default_rng(2)
        J = rng.normal(size=(self.N, self.P))
        J[:, 3] = 0.0  # no defect pixel
        r = rng.normal(0.0, 2.0, self.N)
        assert sf.sandwich(J, r, sf._robust_scale(r), np.ones(self.N), np.arange(self.N) % 40,
                           np.arange(self.N) // 40) is None


class TestSandwichSums:
    """``surface_fit_numba.sandwich_sums`` against the NumPy products it replaced."""

    def _inputs(self, n=900, groups=60, seed=4):
        rng = np.random.default_rng(seed)
        jt = rng.normal(size=(len(sf.PARAMS), n))
        r = rng.standard_t(3, size=n)  # tails that Huber's cut reaches
        return jt, r, rng.uniform(0.2, 1.0, n), rng.integers(0, groups, n), groups

    def test_equals_the_numpy_sums(self):
        jt, r, p, groups, k = self._inputs()
        cut = sf.HUBER_K * sf._robust_scale(r)
        h = _huber_weights(r, cut / sf.HUBER_K)
        assert (h < 1).sum() > 50  # the cut is reached
        bread, meat, s2, blocks = sfn.sandwich_sums(jt, r, p, cut, groups, k)
        inside = (np.abs(r) <= cut) * p
        np.testing.assert_allclose(bread, (jt * inside) @ jt.T, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(meat, (jt * p * p) @ jt.T, rtol=1e-12, atol=1e-9)
        assert s2 == pytest.approx(np.sum(p * (h * r) ** 2), rel=1e-12)
        scores = jt * (p * h * r)
        expected = np.stack([np.bincount(groups, scores[i], minlength=k) for i in range(len(sf.PARAMS))], axis=1)
        np.testing.assert_allclose(blocks, expected, rtol=1e-12, atol=1e-9)

    def test_shape_checks(self):
        jt, r, p, groups, k = self._inputs()
        with pytest.raises(ValueError, match=r"jt \(900,\) must be \(P, N\)"):
            sfn.sandwich_sums(jt[0], r, p, 1.0, groups, k)
        with pytest.raises(ValueError, match="r .* must be \\(900,\\) as jt's columns"):
            sfn.sandwich_sums(jt, r[:-1], p, 1.0, groups, k)
        with pytest.raises(ValueError, match="groups must lie in 0 .. 59"):
            sfn.sandwich_sums(jt, r, p, 1.0, groups + 1, k)


class TestOffsetCosts:
    def _numpy(self, lv, image, u, v, base, gain, offset, w, e, delta, scale):
        """The offset search's cost as NumPy sums it, from the spline's samples."""
        rv = sf.sample(image, u - base - delta, v, e)
        r = np.where(np.isfinite(rv), lv - gain * rv - offset, 0.0)
        a, k = np.abs(r), sf.HUBER_K * scale
        return float(np.sum(w * np.where(a <= k, 0.5 * a * a, k * (a - 0.5 * k))))  # Huber's rho

    @pytest.mark.parametrize("e", [0.0, 0.37, -1.6])
    def test_equals_the_numpy_cost_of_each_candidate(self, e):
        image = sf.high_pass(step_pair(seed=4)[1])
        rng = np.random.default_rng(1)
        # the samples of the first forty columns leave the image, and at e = -1.6 those of the first two rows
        v, u = (a.ravel().astype(np.float64) for a in np.mgrid[1:30, 0:160])
        base = 40.0 + 0.02 * u - 0.01 * v
        gain, w = rng.uniform(0.9, 1.1, u.size), rng.uniform(0.0, 1.0, u.size)
        lv = rng.normal(0, 10, u.size)
        deltas = np.arange(-1.5, 1.51, 0.2)
        got = sfn.offset_costs(lv, image, u, v, base, gain, 3.0, w, e, deltas, 4.0, sf.HUBER_K)
        want = [self._numpy(lv, image, u, v, base, gain, 3.0, w, e, d, 4.0) for d in deltas]
        np.testing.assert_allclose(got, want, rtol=1e-6)

    def test_no_pixels_or_candidates_cost_nothing_and_shapes_are_checked(self):
        image = np.zeros((20, 30), np.float32)
        none = np.zeros(0)
        assert sfn.offset_costs(none, image, none, none, none, none, 0.0, none, 0.0, np.array([0.0, 1.0]), 1.0,
                                1.0).tolist() == [0.0, 0.0]
        with pytest.raises(ValueError, match="gain"):
            sfn.offset_costs(np.ones(3), image, np.ones(3), np.ones(3), np.ones(3), np.ones(2), 0.0, np.ones(3), 0.0,
                             np.zeros(1), 1.0, 1.0)
        with pytest.raises(ValueError, match="float32"):
            sfn.offset_costs(np.ones(3), image.astype(np.float64), np.ones(3), np.ones(3), np.ones(3), np.ones(3), 0.0,
                             np.ones(3), 0.0, np.zeros(1), 1.0, 1.0)


class TestWarmUp:
    def test_fits_its_pair(self):
        fit = sf.warm_up()
        assert fit is not None and fit.c == pytest.approx(4.0, abs=0.01) and abs(fit.delta) < 0.01


class TestFitSurface:
    @pytest.mark.parametrize("seed", [0, 1, 2])
    def test_recovers_the_plane_and_the_step_within_their_uncertainty(self, seed):
        left, right, _ = step_pair(plane=PLANE, step_px=-0.3, seed=seed)
        ring, defect = _regions()
        fit = sf.fit_surface(left, right, ring, defect, (PLANE[0], PLANE[1], PLANE[2] + 0.4), -0.1)
        assert fit is not None and fit.converged
        u0, v0 = fit.centre
        sd_c, sd_delta = math.sqrt(fit.covariance[0, 0]), math.sqrt(fit.covariance[3, 3])
        assert abs(fit.c - _plane_at(u0, v0)) <= 3 * sd_c
        # within 3 sigma and the high-pass's pull of a few percent of the step (module docstring)
        assert abs(fit.delta - (-0.3)) <= 3 * sd_delta + 0.015
        assert fit.slopes == pytest.approx(PLANE[:2], abs=0.002)
        assert fit.params[4] == pytest.approx(1 / 1.05, abs=0.02)  # the right eye's exposure

    def test_uncertainty_is_near_the_noise_floor(self):
        left, right, _ = step_pair(plane=PLANE, step_px=-0.3, noise=1.5, seed=3)
        ring, defect = _regions()
        fit = sf.fit_surface(left, right, ring, defect, PLANE, 0.0)
        floor = math.hypot(_floor(left, ring, 1.5), _floor(left, defect, 1.5))
        sd_delta = math.sqrt(fit.covariance[3, 3])
        # below the floor's formula: interpolating the right eye filters its noise. Over 40 seeds of this pair
        # the offsets scatter by 0.68x of the floor and the fit reports 0.83x
        assert 0.7 * floor <= sd_delta <= 2.0 * floor

    @pytest.mark.parametrize("seed", [5, 6, 7])
    def test_the_fit_does_not_depend_on_where_its_window_starts(self, seed):
        # starts 1-4 px of disparity apart cut the window at other columns (it reaches the start's disparity to
        # the left). The ring's cells, the coarse levels' pixels and the residuals' clusters lie on the image's
        # grid, so every start settles at the same surface; on the window's grid these faint pairs scattered
        # by 0.006-0.008 px, and a crop of the matcher's map moved a defect on faint plates by 0.05 mm
        box, inner = (200, 45, 240, 75), (208, 51, 232, 69)
        left, right, _ = step_pair(width=320, plane=PLANE, step_box=box, step_px=-0.4, noise=3.0, contrast=6.0,
                                   seed=seed)
        ring, defect = _regions(box, inner, left.shape)
        fits = [sf.fit_surface(left, right, ring, defect, (PLANE[0], PLANE[1], PLANE[2] + shift), 0.0)
                for shift in (-0.9, 0.1, 1.1, 2.3, 3.4)]
        assert all(f is not None for f in fits)
        for fit in fits[1:]:
            assert fit.c == pytest.approx(fits[0].c, abs=1e-5)
            assert fit.delta == pytest.approx(fits[0].delta, abs=1e-5)
            assert fit.covariance[3, 3] == pytest.approx(fits[0].covariance[3, 3], rel=1e-4)

    def test_a_start_a_pixel_off_still_finds_the_surface(self):
        left, right, _ = step_pair(plane=PLANE, step_px=-0.5, seed=4)
        ring, defect = _regions()
        fit = sf.fit_surface(left, right, ring, defect, (PLANE[0], PLANE[1], PLANE[2] - 1.0), 0.8)
        u0, v0 = fit.centre
        assert fit.c == pytest.approx(_plane_at(u0, v0), abs=0.02)
        assert fit.delta == pytest.approx(-0.5, abs=0.05)

    def test_a_part_of_the_ring_on_another_surface_is_left_out(self):
        # the ring's right side lies on a second, deeper step: a box cut through a neighbouring defect
        left, right, _ = step_pair(plane=PLANE, step_box=(101, 30, 130, 90), step_px=-0.4, seed=5)
        ring, defect = _regions()
        fit = sf.fit_surface(left, right, ring, defect, PLANE, 0.0)
        u0, v0 = fit.centre
        assert abs(fit.c - _plane_at(u0, v0)) < 0.02  # a blend of both would be ~0.07 px off
        assert abs(fit.delta) < 0.03  # and the region inside is on the plane

    @pytest.mark.parametrize("dy", [0.4, -1.0])
    @pytest.mark.parametrize("rows_from_ring", [False, True])
    def test_a_vertical_offset_left_by_rectification_is_fitted_not_read_as_disparity(self, dy, rows_from_ring):
        import cv2

        left, right, _ = step_pair(plane=PLANE, step_px=-0.3, seed=6)
        # the right eye sees every point dy rows lower (Lanczos keeps its texture as sharp as the left's)
        shifted = cv2.warpAffine(right, np.float32([[1, 0, 0], [0, 1, dy]]), right.shape[::-1],
                                 flags=cv2.INTER_LANCZOS4, borderMode=cv2.BORDER_REFLECT)
        ring, defect = _regions()
        # from the ring alone (a region holding more than one surface) or from the whole
        fit = sf.fit_surface(left, shifted, ring, defect, PLANE, 0.0, rows_from_ring=rows_from_ring)
        u0, v0 = fit.centre
        assert fit.params[sf.E] == pytest.approx(dy, abs=0.02)
        assert abs(fit.c - _plane_at(u0, v0)) <= 3 * math.sqrt(fit.covariance[0, 0]) + 0.005
        assert abs(fit.delta - (-0.3)) <= 3 * math.sqrt(fit.covariance[3, 3]) + 0.015

    def test_a_refit_that_leaves_the_searched_minimum_is_not_one_surface(self):
        """A round pit on faint texture whose wall each eye sees as a crescent of another width
        (fixtures/surface_fit/README.md): the offset search finds the pit at -0.25 px, and the refit after
        the ring's cells are weighted again carried it to +0.29 px, a 0.72 mm pit read as a 1.36 mm bump
        at +-0.41 mm."""
        z = np.load(FIXTURES / "round_pit_wall.npz")
        fit = sf.fit_surface(z["left"].astype(np.float32), z["right"].astype(np.float32),
                             (z["ring_u"].astype(np.int64), z["ring_v"].astype(np.int64)),
                             (z["defect_u"].astype(np.int64), z["defect_v"].astype(np.int64)), tuple(z["plane"]),
                             float(z["delta0"]), z["weights"], float(z["search_px"]))
        assert fit is None

    @pytest.mark.parametrize("start, found", [(1.1, True), (1.6, False), (-1.9, False)])
    def test_an_offset_beyond_the_searched_range_is_not_found_at_its_end(self, start, found):
        # the step lies at -0.3 px: 1.4 px from a start at 1.1, within the 1.5 px searched either way; 1.9 and 1.6 px
        # from the others, whose least cost lies past the range's end (a detector's box across a pit's edge, its
        # ring fitted tilted, read a 2.04 mm pit as an 8.2 mm bump from just past the end)
        left, right, _ = step_pair(plane=PLANE, step_px=-0.3, seed=1)
        ring, defect = _regions()
        fit = sf.fit_surface(left, right, ring, defect, PLANE, start)
        if found:
            assert fit.delta == pytest.approx(-0.3, abs=0.03)
        else:
            assert fit is None

    def test_shape_checks(self):
        left, right, _ = step_pair()
        ring, defect = _regions()
        with pytest.raises(ValueError, match="same HxW"):
            sf.fit_surface(left, right[:, :-1], ring, defect, PLANE)
        with pytest.raises(ValueError, match="equal length"):
            sf.fit_surface(left, right, (ring[0], ring[1][:-1]), defect, PLANE)
        with pytest.raises(ValueError, match="one weight per defect pixel"):
            sf.fit_surface(left, right, ring, defect, PLANE, 0.0, np.ones(3))

    def test_nothing_to_fit_is_none(self):
        left, right, _ = step_pair()
        ring, _ = _regions()
        assert sf.fit_surface(left, right, ring, (np.array([], int), np.array([], int)), PLANE) is None
        assert sf.fit_surface(left, right, (ring[0][:5], ring[1][:5]), _regions()[1], PLANE) is None


class TestFitRingThenDefect:
    def test_one_ring_fit_serves_both_defect_fits_as_fit_surface_gives_them(self):
        # a groove's refit (the rows from the ring) starts from the ring the region's fit started from
        left, right, _ = step_pair(plane=PLANE, step_px=-0.3, noise=1.5, seed=8)
        ring, defect = _regions()
        start = sf.fit_ring(left, right, ring, defect, PLANE, 0.1)
        kept = (start.theta.copy(), start.prior.copy(), start.ring_prior.copy())
        for rows_from_ring in (False, True, False):
            fit = sf.fit_defect(start, rows_from_ring)
            whole = sf.fit_surface(left, right, ring, defect, PLANE, 0.1, rows_from_ring=rows_from_ring)
            np.testing.assert_array_equal(fit.params, whole.params)
            np.testing.assert_array_equal(fit.covariance, whole.covariance)
            np.testing.assert_array_equal(fit.ring_weights, whole.ring_weights)
        for before, after in zip(kept, (start.theta, start.prior, start.ring_prior)):
            np.testing.assert_array_equal(before, after)
        # the two kinds differ: holding the rows at the ring's moves the other parameters
        assert not np.array_equal(sf.fit_defect(start).params, sf.fit_defect(start, True).params)

    def test_the_ring_fit_weighs_a_ring_on_another_surface_down(self):
        left, right, _ = step_pair(plane=PLANE, step_box=(101, 30, 130, 90), step_px=-0.4, seed=5)
        ring, defect = _regions()
        start = sf.fit_ring(left, right, ring, defect, PLANE)
        on_ring = start.problem.m == 0
        right_side = ring[0] > 100
        assert start.prior.shape == start.ring_prior.shape == (len(ring[0]) + len(defect[0]),)
        np.testing.assert_array_equal(start.ring_prior[on_ring], 1.0)
        assert start.prior[on_ring][right_side].mean() < 0.2 < 0.8 < start.prior[on_ring][~right_side].mean()

    def test_checks_and_nothing_to_fit_as_fit_surface(self):
        left, right, _ = step_pair()
        ring, defect = _regions()
        with pytest.raises(ValueError, match="same HxW"):
            sf.fit_ring(left, right[:, :-1], ring, defect, PLANE)
        assert sf.fit_ring(left, right, (ring[0][:5], ring[1][:5]), defect, PLANE) is None


class TestMatches:
    def test_a_textured_pair_matches_at_its_surface(self):
        left, right, _ = step_pair(plane=PLANE, step_px=-0.3, seed=4)
        ring, defect = _regions()
        fit = sf.fit_surface(left, right, ring, defect, PLANE, 0.0)
        assert fit.matches and fit.residual_sigma < 0.3 * fit.signal_sigma

    @pytest.mark.parametrize("seed", [1, 3])
    def test_noise_without_texture_matches_nothing(self, seed):
        """On noise alone the fit either does not settle or settles where the right eye's gain goes to 0,
        and says so: either way nothing to vouch for."""
        left, right, _ = step_pair(plane=PLANE, contrast=0.0 if seed == 1 else 0.5, noise=2.0, seed=seed)
        ring, defect = _regions()
        fit = sf.fit_surface(left, right, ring, defect, PLANE, 0.0)
        assert fit is None or not fit.matches

    def test_a_defect_whose_own_gain_goes_to_nothing_does_not_match(self):
        """A defect started far from its surface (a gross mismatch of the matcher) settles where its own
        exposure explains nothing: the fitted fields say so, whatever the ring does."""
        left, right, _ = step_pair(plane=PLANE, step_px=-0.3, seed=4)
        ring, defect = _regions()
        fit = sf.fit_surface(left, right, ring, defect, PLANE, 0.0)
        params = fit.params.copy()
        params[8] = -params[4]  # the defect's gain g + g_m at 0
        assert fit.matches and not dataclasses.replace(fit, params=params).matches

    def test_unrelated_images_give_no_fit_that_matches(self):
        left, _, _ = step_pair(plane=PLANE, seed=1)
        other, _, _ = step_pair(plane=PLANE, seed=9)
        ring, defect = _regions()
        fit = sf.fit_surface(left, other, ring, defect, PLANE, 0.0)
        assert fit is None or not fit.matches


class TestCellOffsets:
    def test_each_cell_sees_the_step(self):
        left, right, _ = step_pair(plane=PLANE, step_px=-0.3, seed=6)
        ring, defect = _regions()
        fit = sf.fit_surface(left, right, ring, defect, PLANE, 0.0)
        offsets, sds, centres, settled = sf.cell_offsets(left, right, fit, defect)
        assert offsets.shape == sds.shape == settled.shape == (centres.shape[0],) and centres.shape[1] == 2
        assert settled.all()
        assert np.all(np.isfinite(sds)) and np.median(np.abs(offsets + 0.3) / sds) < 1.5

    def test_the_fits_own_window_gives_the_cells_of_a_window_cut_for_them(self):
        left, right, _ = step_pair(plane=PLANE, step_px=-0.3, seed=6)
        ring, defect = _regions()
        fit = sf.fit_surface(left, right, ring, defect, PLANE, 0.0)
        own = sf.cell_offsets(left, right, fit, defect, images=fit.images)
        cut = sf.cell_offsets(left, right, fit, defect, images=sf.defect_images(left, right, fit, defect))
        assert fit.images.L.shape != sf.defect_images(left, right, fit, defect).L.shape  # two windows
        # they differ only where the high-pass reaches a window's edge, by far less than the cells' noise
        assert np.max(np.abs(own[0] - cut[0]) / own[1]) < 0.01


    def test_a_cell_still_stepping_at_the_end_has_not_settled(self):
        left, right, _ = step_pair(plane=PLANE, step_px=-0.3, seed=6)
        ring, defect = _regions()
        fit = sf.fit_surface(left, right, ring, defect, PLANE, 0.0)
        # a fit that starts the cells 0.4 px off and stops them after one step leaves them still stepping
        moved = dataclasses.replace(fit, params=fit.params + 0.4 * (np.arange(len(fit.params)) == sf.PARAMS.index("delta")))
        *_, settled = sf.cell_offsets(left, right, moved, defect, iterations=1)
        assert not settled.any()
        offsets, sds, _, settled = sf.cell_offsets(left, right, moved, defect)
        assert settled.all() and np.median(np.abs(offsets + 0.3) / sds) < 1.5


class TestCellSteps:
    """``surface_fit_numba.cell_steps`` against the cells' Gauss-Newton steps as NumPy takes them."""

    @staticmethod
    def _numpy(splines, u, rows, e, plane, gain, lv, o, p, cell, k, start, scale, iterations):
        offsets, j, step = np.full(k, start), np.zeros(len(u)), np.zeros(k)
        for _ in range(iterations):
            rv, gx = sf.samples(splines, u - plane - offsets[cell], rows.astype(np.float64), e)
            ok = np.isfinite(rv) & np.isfinite(gx) & (p > 0)
            r = np.where(ok, lv - gain * rv - o[0] - o[1], 0.0)
            j = np.where(ok, gain * gx, 0.0)
            h = _huber_weights(r, scale) * p
            num = np.bincount(cell, h * j * r, minlength=k)
            den = np.bincount(cell, h * j * j, minlength=k)
            step = np.where(den > 0, -num / np.maximum(den, 1e-12), 0.0)
            offsets = offsets + np.clip(step, -0.5, 0.5)
            if np.all(np.abs(step) < 1e-4):
                break
        return offsets, step, j

    def _inputs(self, e=0.0, shift=0.0):
        left, right, _ = step_pair(plane=PLANE, step_px=-0.3, seed=6)
        R = sf.spline(sf.high_pass(right))
        splines = (R, sf.gradient_x(R))
        vv, uu = np.mgrid[51:69, 68:92]
        u, rows = uu.ravel().astype(np.float64) + shift, vv.ravel()
        plane = _plane_at(uu.ravel(), vv.ravel())
        rng = np.random.default_rng(0)
        gain = rng.uniform(0.95, 1.05, u.size)
        lv = sf.high_pass(left)[rows, uu.ravel()].astype(np.float64)
        p = np.where(rng.random(u.size) < 0.1, 0.0, 1.0)  # a tenth of the pixels carry no share
        cell = sf._cell_index(uu.ravel(), vv.ravel(), sf.CELL_PX)
        return splines, u, rows, e, plane, gain, lv, (0.5, -0.25), p, cell, int(cell.max()) + 1

    @pytest.mark.parametrize("e,shift,iterations", [(0.0, 0.0, 8), (0.4, 0.0, 8), (0.0, 0.0, 1), (0.0, 110.0, 8)])
    def test_equals_the_numpy_steps(self, e, shift, iterations):
        # a shift of 110 px sends some samples out of the image; one iteration stops the cells mid-way
        args = self._inputs(e, shift)
        got = sfn.cell_steps(*args, -0.1, 3.0, sf.HUBER_K, iterations, 0.5, 1e-4)
        want = self._numpy(*args, -0.1, 3.0, iterations)
        for a, b in zip(got, want):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
        offsets, step, j = got
        assert np.all(np.isfinite(offsets)) and np.all(np.abs(offsets - -0.1) <= 0.5 * iterations + 1e-12)
        assert np.all(j[args[8] == 0] == 0)  # pixels of no share carry no gradient
        if shift:
            assert np.any(j[args[8] > 0] == 0)  # nor those whose samples leave the image

    def test_shape_checks(self):
        splines, u, rows, e, plane, gain, lv, o, p, cell, k = self._inputs()
        with pytest.raises(ValueError, match="gain"):
            sfn.cell_steps(splines, u, rows, e, plane, gain[:-1], lv, o, p, cell, k, 0.0, 1.0, 1.0, 8, 0.5, 1e-4)
        with pytest.raises(ValueError, match="splines"):
            sfn.cell_steps(splines[:1], u, rows, e, plane, gain, lv, o, p, cell, k, 0.0, 1.0, 1.0, 8, 0.5, 1e-4)


class TestInteriorVariance:
    INNER = (68, 51, 92, 69)

    def _fit(self, seed=7, noise=1.5):
        left, right, _ = step_pair(plane=PLANE, step_px=-0.3, noise=noise, seed=seed)
        ring, defect = _regions()
        return left, right, defect, sf.fit_surface(left, right, ring, defect, PLANE, 0.0)

    def test_a_textured_region_is_at_the_noise_floor_of_all_its_pixels(self):
        """Where the border carries no more than its share of the texture, the region is known as well as all
        its pixels tell, not only its interior's: a wider margin leaves fewer pixels but the same estimate."""
        left, right, defect, fit = self._fit()
        variance = sf.interior_variance(left, right, fit, defect, None, self.INNER, 1.0)
        floor = _floor(left, defect, 1.5)
        assert 0.7 * floor <= math.sqrt(variance) <= 2.5 * floor
        assert sf.interior_variance(left, right, fit, defect, None, self.INNER, 4.0) == pytest.approx(variance, rel=0.3)

    def test_a_region_whose_only_texture_is_its_border_is_known_poorly(self):
        left, right, defect, fit = self._fit()
        textured = sf.interior_variance(left, right, fit, defect, None, self.INNER, 1.0)
        flat = right.copy()
        x0, y0, x1, y1 = self.INNER
        d = _plane_at(80, 60) - 0.3  # where the interior's pixels are read in the right image
        flat[y0 + 1:y1 - 1, int(x0 + 1 - d - 3):int(x1 - 1 - d + 3)] = 128.0  # no texture, no noise
        assert sf.interior_variance(left, flat, fit, defect, None, self.INNER, 1.0) > 25 * textured

    def test_a_region_with_no_interior_is_unknown(self):
        left, right, defect, fit = self._fit()
        assert sf.interior_variance(left, right, fit, defect, None, (80, 51, 82.5, 69), 1.0) == math.inf
        zero = np.zeros(len(defect[0]))
        assert sf.interior_variance(left, right, fit, defect, zero, self.INNER, 1.0) == math.inf


class TestContrastRatio:
    INNER = (68, 51, 92, 69)

    def _pair(self, right_contrast=1.0, seed=8):
        """A step pair whose right eye sees the region's texture ``right_contrast`` times as strong as the left's
        relative to the ring's, as a wall's sheen seen by one eye makes it."""
        left, right, _ = step_pair(plane=PLANE, step_px=-0.3, seed=seed)
        x0, y0, x1, y1 = self.INNER
        d = _plane_at(80, 60) - 0.3  # where the region's pixels are read in the right image
        read = right[y0:y1, int(x0 - d - 3):int(x1 - d + 3)]
        read[:] = read.mean() + right_contrast * (read - read.mean())
        ring, defect = _regions()
        return ring, defect, sf.fit_surface(left, right, ring, defect, PLANE, 0.0)

    def test_a_region_both_eyes_see_alike_is_one(self):
        for seed in (8, 9, 10):
            ring, defect, fit = self._pair(seed=seed)
            assert abs(math.log(sf.contrast_ratio(fit, ring, defect))) < 0.05

    def test_a_region_one_eye_sees_fainter_reads_how_much(self):
        ring, defect, fit = self._pair(0.7)
        # the sensor's noise, the same in both eyes, pulls the ratio a little towards one
        assert 1.3 < sf.contrast_ratio(fit, ring, defect) < 1 / 0.7 + 0.02
        ring, defect, fit = self._pair(1.3)
        assert 1 / 1.3 - 0.02 < sf.contrast_ratio(fit, ring, defect) < 0.8

    def test_pixels_of_no_weight_are_not_read(self):
        ring, defect, fit = self._pair(0.7)
        # the region's left half alone: the changed contrast lies under all of it
        half = (defect[0] < 80).astype(float)
        assert 1.25 < sf.contrast_ratio(fit, ring, defect, half) < 1 / 0.7 + 0.02
        assert math.isnan(sf.contrast_ratio(fit, ring, defect, np.zeros(len(defect[0]))))

    def test_texture_in_one_eye_alone_is_zero_or_infinity(self):
        ring, defect, fit = self._pair()
        (x0, y0), images = fit.images.origin, fit.images
        x, y = self.INNER[0] - x0, self.INNER[1] - y0
        d = int(_plane_at(80, 60) - 0.3)
        xr = self.INNER[0] - images.right_x0  # the right eye's window starts further left
        flat = images.R.copy()  # the right eye's spline: constant where the region is read, a plain patch
        flat[y - 3:y + 22, xr - d - 4:xr - d + 28] = 7.0
        assert sf.contrast_ratio(dataclasses.replace(fit, images=dataclasses.replace(images, R=flat)), ring,
                                 defect) == math.inf
        blank = images.L.copy()
        blank[y:y + 18, x:x + 24] = 0.0
        assert sf.contrast_ratio(dataclasses.replace(fit, images=dataclasses.replace(images, L=blank)), ring,
                                 defect) == 0.0


class TestRobustOffset:
    def test_cells_off_by_much_more_than_their_noise_do_not_pull(self):
        offsets = np.r_[np.full(30, -0.30), np.full(8, 0.20)]  # a quarter of the cells on a wall
        sds = np.full(38, 0.02)
        result = sf.robust_offset(offsets + np.random.default_rng(0).normal(0, 0.02, 38), sds, -0.2)
        assert result.delta == pytest.approx(-0.30, abs=0.01)
        assert result.weight < 31

    def test_scatter_beyond_the_cells_noise_widens_the_uncertainty(self):
        rng = np.random.default_rng(1)
        sds = np.full(40, 0.02)
        calm = sf.robust_offset(-0.3 + rng.normal(0, 0.02, 40), sds, -0.3)
        wild = sf.robust_offset(-0.3 + rng.normal(0, 0.06, 40), sds, -0.3)
        assert calm.birge < 1.6 < wild.birge
        assert wild.variance > 4 * calm.variance

    def test_cells_that_agree_better_than_their_noise_narrow_it_to_the_bound_of_their_scatter(self):
        # each cell's sd comes from residuals that hold aliasing as well as noise: cells scattering at 0.7
        # of it say the offset is known better, but only as well as 100 cells can show it
        rng = np.random.default_rng(2)
        sds = np.full(100, 0.02)
        model = 0.02**2 / 100
        calm = sf.robust_offset(-0.3 + rng.normal(0, 0.014, 100), sds, -0.3)
        assert 0.5 < calm.birge < 0.75
        assert calm.variance == pytest.approx(model * calm.birge, rel=0.01)  # Tukey weights near 1

    def test_few_cells_that_agree_keep_the_variance_their_noise_gives(self):
        sds = np.full(4, 0.02)
        few = sf.robust_offset(np.array([-0.31, -0.29, -0.30, -0.312]), sds, -0.3)  # at half their noise
        assert few.birge == 1.0
        assert few.variance == pytest.approx(0.02**2 / 4, rel=0.01)

    def test_cells_that_agree_to_the_digit_keep_a_quarter_of_it(self):
        same = sf.robust_offset(np.full(400, -0.3), np.full(400, 0.02), -0.3)
        assert same.birge == sf.BIRGE_MIN
        assert same.variance == pytest.approx(sf.BIRGE_MIN * 0.02**2 / 400)

    def test_by_area_each_cell_counts_by_its_share_of_the_region(self):
        # a quarter of the cells, on a wall's strongly textured edge, hold most of the information
        offsets = np.r_[np.full(30, -0.36), np.full(10, -0.18)]
        sds = np.r_[np.full(30, 0.25), np.full(10, 0.04)]
        noisy = offsets + np.random.default_rng(3).normal(0, 1, 40) * sds
        assert sf.robust_offset(noisy, sds, -0.2).delta == pytest.approx(-0.19, abs=0.03)
        by_area = sf.robust_offset(noisy, sds, -0.2, areas=np.full(40, 16.0))
        assert by_area.delta == pytest.approx(-0.315, abs=0.05)

    def test_shape_check(self):
        with pytest.raises(ValueError, match="same"):
            sf.robust_offset(np.zeros(3), np.ones(4), 0.0)
        with pytest.raises(ValueError, match="areas"):
            sf.robust_offset(np.zeros(3), np.ones(3), 0.0, areas=np.ones(2))


class TestTukeyOffset:
    """``surface_fit_numba.tukey_offset`` against the reweighting and the variance as NumPy computes them."""

    @staticmethod
    def _numpy(x, s, prior, start, iterations, cut_k, birge_z=sf.BIRGE_CONFIDENCE_Z, birge_min=sf.BIRGE_MIN):
        mu, w = start, np.ones_like(x)
        for _ in range(iterations):
            spread = max(1.0, float(1.4826 * np.median(np.abs(x - mu) / s)))
            w = sf._tukey_weights((x - mu) / (cut_k * s * spread))
            if w.sum() <= 0:
                w = np.ones_like(x)
            new = float(np.sum(w * prior * x) / np.sum(w * prior))
            done = abs(new - mu) < 1e-6
            mu = new
            if done:
                break
        alpha = w * prior / np.sum(w * prior)
        variance = float(np.sum(alpha * alpha * s * s))
        kept = w > 0
        birge = 1.0
        if kept.sum() >= 2:
            dof = float(w[kept].sum()) - 1 + 1e-12
            birge = float(np.sum(w[kept] * ((x[kept] - mu) / s[kept]) ** 2) / dof)
            if birge < 1.0:
                a = 2.0 / (9.0 * dof)
                birge = min(1.0, max(birge_min, birge / max(1.0 - a - birge_z * math.sqrt(a), 1e-6) ** 3))
        return mu, w, variance * birge, float(w.sum()), birge

    @pytest.mark.parametrize("n,iterations,wall_sd", [(40, 20, 0.03), (41, 20, 0.03), (7, 2, 0.03), (1, 20, 0.03),
                                                      (100, 20, 0.01)])
    def test_equals_the_numpy_reweighting_and_variance(self, n, iterations, wall_sd):
        rng = np.random.default_rng(n)
        # a quarter on a wall; with wall_sd 0.01 the rest scatter at a third of their sds (a Birge ratio below 1)
        x = np.r_[rng.normal(-0.3, wall_sd, n - n // 4), rng.normal(0.2, 0.03, n // 4)]
        s, prior = rng.uniform(0.01, 0.05, n), rng.uniform(0.5, 2.0, n)
        got = sfn.tukey_offset(x, s, prior, -0.2, iterations, sf.TUKEY_K, sf.BIRGE_CONFIDENCE_Z, sf.BIRGE_MIN)
        want = self._numpy(x, s, prior, -0.2, iterations, sf.TUKEY_K)
        assert got[0] == pytest.approx(want[0], rel=1e-12, abs=1e-15)
        np.testing.assert_allclose(got[1], want[1], rtol=1e-9, atol=1e-12)
        assert got[2:] == pytest.approx(want[2:], rel=1e-9)
        if n >= 40:
            assert np.sum(got[1] == 0) >= n // 4 - 1  # the wall's cells cut
        if wall_sd < 0.02:
            assert sf.BIRGE_MIN <= got[4] < 1.0

    def test_a_cut_that_keeps_no_value_weighs_them_all_alike(self):
        x, s, prior = np.array([0.0, 1.0, 3.0]), np.full(3, 0.01), np.array([1.0, 1.0, 2.0])
        mu, w, _, weight, _ = sfn.tukey_offset(x, s, prior, 10.0, 20, 1e-9, 1.28, 0.25)
        assert w.tolist() == [1.0, 1.0, 1.0] and weight == 3.0 and mu == pytest.approx(7.0 / 4.0)

    def test_shape_checks(self):
        with pytest.raises(ValueError, match="prior"):
            sfn.tukey_offset(np.zeros(3), np.ones(3), np.ones(2), 0.0, 20, 1.0, 1.28, 0.25)
        with pytest.raises(ValueError, match="at least 1"):
            sfn.tukey_offset(np.zeros(0), np.ones(0), np.ones(0), 0.0, 20, 1.0, 1.28, 0.25)


class TestMedian:
    @pytest.mark.parametrize("n", [1, 2, 7, 40, 41, 1000])
    def test_is_numpys(self, n):
        rng = np.random.default_rng(n)
        for x in (rng.normal(0, 1, n), np.round(rng.normal(0, 1, n), 1), np.full(n, 0.3)):  # ties, all alike
            assert sfn.median(x) == np.median(x)


class TestCellAreas:
    def test_each_cell_sums_its_pixels_weights_in_the_order_of_cell_offsets(self):
        v, u = np.mgrid[10:16, 21:27]  # cells of columns 21-23 / 24-26, rows 10-11 / 12-15
        weights = np.where(u.ravel() == 21, 0.5, 1.0)
        areas = sf.cell_areas((u.ravel(), v.ravel()), weights)
        np.testing.assert_allclose(areas, [2 * 0.5 + 4, 6, 4 * 0.5 + 8, 12])
        assert sf.cell_areas((u.ravel(), v.ravel())).sum() == 36


class TestWeightingVariance:
    def test_agreeing_weightings_add_nothing_an_uneven_region_their_difference(self):
        rng = np.random.default_rng(4)
        sds = np.r_[np.full(30, 0.25), np.full(10, 0.04)]
        areas = np.full(40, 16.0)
        even = -0.36 + rng.normal(0, 1, 40) * sds
        estimate = sf.robust_offset(even, sds, -0.3).delta
        assert sf.weighting_variance(even, sds, areas, estimate) == 0.0
        uneven = np.r_[np.full(30, -0.36), np.full(10, -0.18)] + rng.normal(0, 1, 40) * sds
        estimate = sf.robust_offset(uneven, sds, -0.2).delta
        added = sf.weighting_variance(uneven, sds, areas, estimate)
        # the difference of the two weightings (about 0.13 px) less twice the area estimate's noise
        assert 0.05**2 < added < 0.15**2


class TestUnevennessVariance:
    def test_a_flat_floor_adds_nothing_a_slanted_one_its_spread(self):
        v, u = np.mgrid[0:6, 0:8].astype(float)
        centres = np.stack([4 * u.ravel(), 4 * v.ravel()], axis=1)
        sds = np.full(48, 0.02)
        rng = np.random.default_rng(2)
        flat = -0.3 + rng.normal(0, 0.02, 48)
        assert sf.unevenness_variance(flat, sds, centres) < 0.02**2 / 4
        ramp = flat + 0.01 * (centres[:, 0] - centres[:, 0].mean())  # a wall across the region
        spread = float(np.std(0.01 * centres[:, 0]))
        assert sf.unevenness_variance(ramp, sds, centres) == pytest.approx(spread**2, rel=0.3)

    def test_a_bowl_adds_the_spread_of_its_depth(self):
        # a box larger than the defect: its region holds the walls all round, shallower than the floor
        v, u = np.mgrid[0:6, 0:8].astype(float)
        centres = np.stack([4 * u.ravel(), 4 * v.ravel()], axis=1)
        sds = np.full(48, 0.02)
        r2 = ((u.ravel() - 3.5) / 3.5) ** 2 + ((v.ravel() - 2.5) / 2.5) ** 2
        bowl = -0.4 + 0.15 * r2 + np.random.default_rng(3).normal(0, 0.02, 48)
        # a plane alone sees no slope in it: the variance is the bowl's own spread over the region
        assert sf.unevenness_variance(bowl, sds, centres) == pytest.approx(float(np.var(0.15 * r2)), rel=0.3)
        # too few cells to tell a bowl: the plane's terms alone, which see nothing here
        few = np.flatnonzero((np.abs(u.ravel() - 3.5) < 2) & (np.abs(v.ravel() - 2.5) < 1))[:5]
        assert len(few) < sf.RADIAL_MIN_CELLS
        assert sf.unevenness_variance(bowl[few], sds[few], centres[few]) < 0.02**2
