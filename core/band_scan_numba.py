"""The central bands' scan compiled with numba: every band's step from the Schur complement of the surface's block,
one pass over the cells per band instead of the (angles x widths x shifts x cells) arrays NumPy builds and sums
(most of ``band_scan.central_band``'s time). ``tests/test_band_scan.py`` holds it to NumPy's arithmetic."""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _best_band(x, w, surface, du, dv, sins, coss, widths, shifts, inverse, r0, solved_r, normalised, min_cells,
               rest_sds):
    n, p = x.size, surface.shape[1]
    w_all, wx_all, wxx, fitted_r = 0.0, 0.0, 0.0, 0.0
    for k in range(n):
        w_all += w[k]
        wx_all += w[k] * x[k]
        wxx += w[k] * x[k] * x[k]
    for i in range(p):
        fitted_r += r0[i] * solved_r[i]
    dof = max(n - 5, 1)
    best, best_z = -1, -np.inf
    out = np.zeros(4)  # the best band's z, its mean, the rest's mean, its mean's variance
    u = np.empty(p)
    across = np.empty(n)
    band = 0
    for a in range(sins.size):
        for k in range(n):
            across[k] = -du[k] * sins[a] + dv[k] * coss[a]
        for h in range(widths.size):
            for s in range(shifts.size):
                u[:] = 0.0
                n_in, w_in, wx_in = 0, 0.0, 0.0
                for k in range(n):
                    if abs(across[k] - shifts[s]) <= widths[h]:
                        n_in += 1
                        w_in += w[k]
                        wx_in += w[k] * x[k]
                        for i in range(p):
                            u[i] += w[k] * surface[k, i]
                here = band
                band += 1
                if n_in < min_cells or n - n_in < min_cells:
                    continue
                # the band's step and its variance from the Schur complement of the surface's block:
                # s = w_in - u' S^-1 u, without a 5x5 solve per band
                u_solved_u, u_r = 0.0, 0.0
                for i in range(p):
                    total = 0.0
                    for j in range(p):
                        total += inverse[i, j] * u[j]
                    u_solved_u += u[i] * total
                    u_r += u[i] * solved_r[i]
                schur = w_in - u_solved_u
                # a step the surface's terms take up: the 5x5 system's normalised determinant is the block's times
                # schur / w_in
                if not abs(normalised * schur / w_in) > 1e-9:
                    continue
                step = (wx_in - u_r) / schur
                scatter = max((wxx - (fitted_r + step * step * schur)) / dof, 1.0)
                z = step / np.sqrt(scatter / schur)
                m_in, m_out = wx_in / w_in, (wx_all - wx_in) / (w_all - w_in)
                sd_out = np.sqrt(scatter / (w_all - w_in))
                direction = np.sign(m_in)
                # the band stands beyond the rest, away from the surface, and the rest lies on its side or on it
                if not (abs(m_in) > abs(m_out) and np.sign(z) == direction and np.isfinite(z)
                        and m_out * direction >= -rest_sds * sd_out):
                    continue
                if abs(z) > best_z:
                    best, best_z = here, abs(z)
                    out[0], out[1], out[2], out[3] = z, m_in, m_out, scatter / w_in
    return best, out


def best_band(x: np.ndarray, w: np.ndarray, surface: np.ndarray, du: np.ndarray, dv: np.ndarray, angles: np.ndarray,
              widths: np.ndarray, shifts: np.ndarray, inverse: np.ndarray, r0: np.ndarray, solved_r: np.ndarray,
              normalised: float, min_cells: int, rest_sds: float) -> tuple[int, float, float, float, float]:
    """Of the straight bands through the cells' centre at ``angles`` (A,, radians), half-widths ``widths`` (W,) and
    shifts ``shifts`` (S,), the one whose step beyond the ``surface`` model stands out most, as
    ``band_scan.central_band`` (which says why) ranks them.

    x, w: (K,) the cells' offsets and weights (1 / sd^2); surface: (K, P) the surface model's columns; du, dv: (K,)
    the cells' centres from the region's; inverse: (P, P) the inverse of ``sum w surface surface^T``; r0: (P,)
    ``sum w surface x``; solved_r: (P,) the inverse times r0; normalised: that block's determinant normalised by its
    diagonal. Returns (the band's index in (A, W, S) order, -1 for none; its z; its cells' weighted mean; the rest's;
    its mean's variance)."""
    n = len(x)
    for name, array in (("w", w), ("du", du), ("dv", dv)):
        if np.shape(array) != (n,):
            raise ValueError(f"best_band: {name} {np.shape(array)} must be ({n},) as x")
    p = np.shape(surface)[1] if np.ndim(surface) == 2 else -1
    if np.shape(surface) != (n, p) or np.shape(inverse) != (p, p) or np.shape(r0) != (p,) \
            or np.shape(solved_r) != (p,):
        raise ValueError(f"best_band: surface {np.shape(surface)} must be ({n}, P), inverse {np.shape(inverse)} "
                         f"(P, P), r0 {np.shape(r0)} and solved_r {np.shape(solved_r)} (P,)")
    f64 = np.float64
    angles = np.asarray(angles, f64)
    index, out = _best_band(np.asarray(x, f64), np.asarray(w, f64), np.ascontiguousarray(surface, f64),
                            np.asarray(du, f64), np.asarray(dv, f64), np.sin(angles), np.cos(angles),
                            np.asarray(widths, f64), np.asarray(shifts, f64), np.ascontiguousarray(inverse, f64),
                            np.asarray(r0, f64), np.asarray(solved_r, f64), float(normalised), int(min_cells),
                            float(rest_sds))
    return int(index), float(out[0]), float(out[1]), float(out[2]), float(out[3])
