"""Small linear algebra for the numba kernels (``planes_numba``, ``refine_numba``)."""
from __future__ import annotations

from numba import njit


@njit(cache=True, inline="always")
def solve3(m, r, out):
    """``m x = r`` (3x3) into ``out`` by Gaussian elimination with partial pivoting, as LAPACK's getrf/getrs;
    False where a pivot is exactly zero (LAPACK's info != 0). m and r are overwritten."""
    for col in range(3):
        pivot = col
        for row in range(col + 1, 3):
            if abs(m[row, col]) > abs(m[pivot, col]):
                pivot = row
        if m[pivot, col] == 0.0:
            return False
        if pivot != col:
            for c in range(3):
                m[col, c], m[pivot, c] = m[pivot, c], m[col, c]
            r[col], r[pivot] = r[pivot], r[col]
        for row in range(col + 1, 3):
            f = m[row, col] / m[col, col]
            for c in range(col, 3):
                m[row, c] -= f * m[col, c]
            r[row] -= f * r[col]
    out[2] = r[2] / m[2, 2]
    out[1] = (r[1] - m[1, 2] * out[2]) / m[1, 1]
    out[0] = (r[0] - m[0, 1] * out[1] - m[0, 2] * out[2]) / m[0, 0]
    return True
