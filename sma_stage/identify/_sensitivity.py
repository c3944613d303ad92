"""Compiled forward-mode sensitivities of the GPI play operators (numba) for the fit's Jacobian.

One pass over the samples gives s_k = sum_i w_i z_{i,k} with w_i = exp(-a11 r_i) (so y = a10 s) and
ds_k/d(a1..a9, a11). dz_i/dθ is d(gl - r_i)/dθ while the lower clamp is active, d(gr + r_i)/dθ while
the upper one is, and is carried from the previous sample otherwise (zero from the initial states).
"""

import numba
import numpy as np

from sma_stage.model._kernels import _tanh, envelopes

SENSITIVITY_COLUMNS = 10  # a1..a9, a11 (a10 is the linear scale: dy/da10 = s)
_LOWER, _UPPER = -1, 1


@numba.njit(cache=True, nogil=True)
def _envelope_derivatives(v: float, scale: float, gain: float, shift: float) -> tuple[float, float, float]:
    """d/d(scale, gain, shift) of scale tanh(gain v + shift) + offset (d/d(offset) is 1)."""
    t = _tanh(gain * v + shift)
    slope = scale * (1.0 - t * t)
    return t, slope * v, slope


@numba.njit(cache=True, nogil=True)
def play_sensitivities(v: np.ndarray, theta: np.ndarray, operators: int, states: np.ndarray,
                       out: np.ndarray) -> None:
    """s_k = sum_i exp(-a11 r_i) z_{i,k} into out[0, k] and ds_k/d(a1..a9, a11) into out[1:11, k].

    theta holds a1..a11; states are the operator states before the first sample, updated in place. The
    sums are kept in scalars and no array is handed to a helper inside the loop over samples, so that they
    stay in registers (an array there cost two reference counts per call, a sum kept in an array a store
    and a load per operator: 1.3-1.5 times the time: bench/bench_kernels.py).
    """
    a9, a11 = theta[8], theta[10]
    low = np.empty(v.size)
    high = np.empty(v.size)
    envelopes(v, theta, low, high)
    r = np.empty(operators)
    w = np.empty(operators)
    for i in range(operators):
        r[i] = a9 * i
        w[i] = np.exp(-a11 * r[i])
    side = np.zeros(operators, dtype=np.int8)
    held = np.zeros((operators, 3))  # the envelope's derivatives at the operator's last clamp
    for k in range(v.size):
        lower_scale, lower_gain, lower_shift = _envelope_derivatives(v[k], theta[0], theta[1], theta[2])
        upper_scale, upper_gain, upper_shift = _envelope_derivatives(v[k], theta[4], theta[5], theta[6])
        d1 = d2 = d3 = d4 = d5 = d6 = d7 = d8 = d9 = d11 = 0.0
        total = 0.0
        for i in range(operators):
            z = states[i]
            low_edge = low[k] - r[i]
            high_edge = high[k] + r[i]
            if z > high_edge:
                z = high_edge
                side[i] = _UPPER
                held[i, 0], held[i, 1], held[i, 2] = upper_scale, upper_gain, upper_shift
            if low_edge > z:
                z = low_edge
                side[i] = _LOWER
                held[i, 0], held[i, 1], held[i, 2] = lower_scale, lower_gain, lower_shift
            states[i] = z
            weight = w[i]
            wz = weight * z
            total += wz
            if side[i] == _LOWER:
                d1 += weight * held[i, 0]
                d2 += weight * held[i, 1]
                d3 += weight * held[i, 2]
                d4 += weight
                d9 -= weight * i
            elif side[i] == _UPPER:
                d5 += weight * held[i, 0]
                d6 += weight * held[i, 1]
                d7 += weight * held[i, 2]
                d8 += weight
                d9 += weight * i
            d9 -= a11 * i * wz
            d11 -= r[i] * wz
        out[0, k] = total
        for j, value in enumerate((d1, d2, d3, d4, d5, d6, d7, d8, d9, d11)):
            out[1 + j, k] = value


@numba.njit(cache=True, nogil=True)
def normalise_rows(rows: np.ndarray, tail_slope: float, a9: float, total: float, mean_index: float) -> None:
    """In place, rows (S, dS/d(a1..a9), dS/d(a11)) -> (S, dS/d(a1..a8), dS/d(a9) - tail_slope dS/d(a11),
    dS/d(a11) / a9) / total, then the last row plus mean_index times the first; each element through the
    same operations in the same order as the NumPy expressions it replaces (one row per loop, so it
    vectorises)."""
    s, slope, tail = rows[0], rows[9], rows[10]
    for t in range(s.size):
        slope[t] = (slope[t] - tail[t] * tail_slope) / total
    for i in range(9):
        row = rows[i]
        for t in range(row.size):
            row[t] = row[t] / total
    for t in range(s.size):
        tail[t] = tail[t] / a9 / total + s[t] * mean_index


@numba.njit(cache=True, nogil=True)
def householder_r(rows: np.ndarray, order: np.ndarray) -> np.ndarray:
    """Upper-triangular R of the QR factorisation of the matrix whose columns are rows[order] (each row
    of `rows` one column of length N >= k); `rows` is overwritten. Single-threaded, so a tall-skinny QR costs
    about 2 N k^2 flops whatever the BLAS threading does. Each reflection's dot products are taken four
    columns per pass over the samples (the sums are sequential, so their latency sets the pace) and its
    updates one column per pass (which vectorises); every sum runs in the order of one column at a time,
    so R is the same to the bit (bench/bench_kernels.py)."""
    k = order.size
    n = rows.shape[1]
    r = np.zeros((k, k))
    unused = np.zeros(n)  # stands in, in the dot products, for the columns missing from the last group of four
    norm_sq = _sum_of_squares(rows[order[0]])
    for j in range(k):
        x = rows[order[j], j:]
        norm = np.sqrt(norm_sq)
        alpha = -norm if x[0] >= 0.0 else norm
        r[j, j] = alpha
        if j + 1 == k:
            break
        if norm == 0.0:
            for c in range(j + 1, k):
                r[j, c] = rows[order[c], j]
            norm_sq = _sum_of_squares(rows[order[j + 1], j + 1:])
            continue
        x[0] -= alpha
        vv = 0.0
        for first in range(j + 1, k, 4):
            c0 = rows[order[first], j:]
            c1 = rows[order[first + 1], j:] if first + 1 < k else unused[j:]
            c2 = rows[order[first + 2], j:] if first + 2 < k else unused[j:]
            c3 = rows[order[first + 3], j:] if first + 3 < k else unused[j:]
            square, d0, d1, d2, d3 = _dots_four(x, c0, c1, c2, c3)
            if first == j + 1:
                vv = square
                norm_sq = _reflect_and_square(c0, 2.0 * d0 / vv, x)
            else:
                _reflect(c0, 2.0 * d0 / vv, x)
            if first + 1 < k:
                _reflect(c1, 2.0 * d1 / vv, x)
            if first + 2 < k:
                _reflect(c2, 2.0 * d2 / vv, x)
            if first + 3 < k:
                _reflect(c3, 2.0 * d3 / vv, x)
            for c in range(first, min(first + 4, k)):
                r[j, c] = rows[order[c], j]
    return r


@numba.njit(cache=True, nogil=True)
def _sum_of_squares(x: np.ndarray) -> float:
    total = 0.0
    for t in range(x.size):
        total += x[t] * x[t]
    return total


@numba.njit(cache=True, nogil=True)
def _dots_four(x: np.ndarray, c0: np.ndarray, c1: np.ndarray, c2: np.ndarray, c3: np.ndarray
               ) -> tuple[float, float, float, float, float]:
    """(x.x, x.c0, x.c1, x.c2, x.c3), each summed in sample order."""
    xx = d0 = d1 = d2 = d3 = 0.0
    for t in range(x.size):
        xt = x[t]
        xx += xt * xt
        d0 += xt * c0[t]
        d1 += xt * c1[t]
        d2 += xt * c2[t]
        d3 += xt * c3[t]
    return xx, d0, d1, d2, d3


@numba.njit(cache=True, nogil=True)
def _reflect(column: np.ndarray, factor: float, x: np.ndarray) -> None:
    """column -= factor x, in place (indices from 0, so that the loop vectorises)."""
    for t in range(x.size):
        column[t] -= factor * x[t]


@numba.njit(cache=True, nogil=True)
def _reflect_and_square(column: np.ndarray, factor: float, x: np.ndarray) -> float:
    """column -= factor x, in place; returns the sum of squares of the reflected column[1:] (the next
    step's norm, in sample order)."""
    column[0] -= factor * x[0]
    total = 0.0
    for t in range(1, x.size):
        reflected = column[t] - factor * x[t]
        column[t] = reflected
        total += reflected * reflected
    return total
