"""The GPI fit's search problem: the free parameters, their box, and variable projection of the linear
ones (the normalised scale and any regressor columns), QR-compressed to a problem of a few rows."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from sma_stage.errors import InputError
from sma_stage.identify._sensitivity import SENSITIVITY_COLUMNS, householder_r, normalise_rows
from sma_stage.identify.uncertainty import sensitivities
from sma_stage.model.parameters import GPIParameters

PROGRESS_INTERVAL_S = 1.0
# Searched: a2..a9 and the density decay per operator a11*a9 (bounded, so that no operator's weight
# runs away from the others); a1 is held (the scale symmetry) and a10 projected.
FREE_NAMES = ("a2", "a3", "a4", "a5", "a6", "a7", "a8", "a9", "a11*a9")
HOLDABLE = FREE_NAMES[:8]  # what fit_gpi's hold may name: the searched parameters a2..a9 (index = their column)
DECAY_LIMITS = (-3.0, 30.0)  # bounds of a11 * largest threshold: the last weight is e^3 .. e^-30 of the first
FREE_COLUMNS = [1, 2, 3, 4, 5, 6, 7, 8, 9]  # their columns among the sensitivities (a1..a9, a11)
SCALE_LIMIT = 1e3  # normalised a1, a5 and largest threshold: at most this many output spans each
OFFSET_LIMIT = 2 * SCALE_LIMIT  # |a4|, |a8| from the output's mid-range, in output spans (an active
# envelope lies within a1 (or a5) plus the largest threshold of the output)


class ProjectedProblem:
    """The variable-projection problem over the free parameters, QR-compressed.

    One Householder QR of [regressors, Ŝ, dŜ/d(free), y] (y ~ s Ŝ + regressors c, Ŝ the output with
    densities summing to 1) gives the linear coefficients (c, 0 <= s <= scale_limit), the projected
    residual and Kaufman's Jacobian P_perp s dŜ/dθ in the same orthonormal basis, so the search works on an
    11-row problem with the same cost, gradient and Gauss-Newton model as the N-row one.
    """

    def __init__(self, v: np.ndarray, y: np.ndarray, regressors: np.ndarray, operators: int, a1: float,
                 span: float, progress: Callable[[str], None] | None = None):
        self.v, self.y, self.regressors, self.operators, self.a1 = v, y, regressors, operators, a1
        self.span = span
        self.progress, self._reported = progress, time.perf_counter()
        m = regressors.shape[1]
        self._rows = np.empty((m + 2 + SENSITIVITY_COLUMNS, v.size))
        skip_a1 = [m + 1 + c for c in FREE_COLUMNS]
        self._order = np.array([*range(m), m, *skip_a1, m + 1 + SENSITIVITY_COLUMNS], dtype=np.int64)
        self._x: np.ndarray | None = None
        self.evaluations = 0

    def _evaluate(self, x: np.ndarray) -> None:
        if self._x is not None and np.array_equal(x, self._x):
            return
        self.evaluations += 1
        m = self.regressors.shape[1]
        rows = self._rows
        rows[:m] = self.regressors.T
        sensitivities(self.v, theta_of(self.a1, x), self.operators, out=rows[m:m + 1 + SENSITIVITY_COLUMNS])
        to_normalised_rows(rows[m:m + 1 + SENSITIVITY_COLUMNS], x, self.operators)
        rows[-1] = self.y
        r = householder_r(rows, self._order)
        limit, limit_gradient = scale_limit(self.a1, x, self.operators, self.span)
        self.coefficients, self.residual, self.jacobian = projection(r, m, limit, limit_gradient)
        self._x = x.copy()
        if self.progress is not None and time.perf_counter() - self._reported >= PROGRESS_INTERVAL_S:
            self._reported = time.perf_counter()
            self.progress(f"{self.operators} operators on {self.v.size} samples: evaluation {self.evaluations}, "
                          f"cost {float(self.residual @ self.residual):.6g}")

    def fun(self, x: np.ndarray) -> np.ndarray:
        self._evaluate(x)
        return self.residual

    def jac(self, x: np.ndarray) -> np.ndarray:
        self._evaluate(x)
        return self.jacobian


def theta_of(a1: float, x: np.ndarray, a10: float = 1.0) -> np.ndarray:
    """a1..a11 from the held a1, the searched (a2..a9, a11*a9) and a10."""
    return np.concatenate([[a1], x[:8], [a10, x[8] / x[7]]])


def to_normalised_rows(rows: np.ndarray, x: np.ndarray, operators: int) -> None:
    """Rows (S, dS/d(a1..a9), dS/d(a11)) at fixed a11, S = sum_i w_i z_i, in place to (Ŝ, dŜ/d(a1..a8),
    dŜ/d(a9) at fixed d, dŜ/dd) with Ŝ = S / sum_i w_i and d = a11*a9: the output is then s Ŝ, s the
    normalised scale (what a1, a4, a5, a8, a9 are multiplied by when the densities are made to sum 1)."""
    a9, decay = x[7], x[8]
    indices = np.arange(operators)
    weights = np.exp(-decay * indices)
    total = weights.sum()
    normalise_rows(rows, float(decay / a9**2), float(a9), float(total), float(indices @ weights / total))


def scale_limit(a1: float, x: np.ndarray, operators: int, span: float) -> tuple[float, np.ndarray]:
    """Largest normalised scale s allowed, SCALE_LIMIT * span / (a1 + a5 + a9 (n - 1)), so that s times
    each of them stays within SCALE_LIMIT output spans; and its gradient over the searched parameters."""
    steps = operators - 1
    size = a1 + x[3] + x[7] * steps
    limit = SCALE_LIMIT * span / size
    gradient = np.zeros(x.size)
    gradient[3] = -limit / size
    gradient[7] = -limit * steps / size
    return limit, gradient


def projection(r: np.ndarray, m: int, limit: float, limit_gradient: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """From the R factor of [regressors (m), Ŝ, dŜ/d(searched), y]: the linear coefficients [c, s] with
    0 <= s <= limit, the residual (model - data) and its Jacobian, both in the basis orthogonal to the
    regressors. With s inside its bounds the Jacobian is Kaufman's (zero along Ŝ, whose coefficient
    follows); with s at limit it carries d limit/dθ."""
    linear = m + 1
    triangle, rhs = r[:linear, :linear], r[:linear, -1]
    diagonal = np.abs(np.diag(triangle))
    if diagonal.min() > 1e-12 * diagonal.max():
        coefficients = np.linalg.solve(triangle, rhs)
    else:
        coefficients = np.linalg.lstsq(triangle, rhs, rcond=None)[0]
    scale = coefficients[-1]
    bounded = not 0.0 <= scale <= limit
    if bounded:
        scale = min(max(scale, 0.0), limit)
        coefficients[-1] = scale
        if m:
            others = rhs[:m] - scale * triangle[:m, m]
            coefficients[:m] = np.linalg.lstsq(triangle[:m, :m], others, rcond=None)[0]
    shape = r[m:, m]
    residual = scale * shape - r[m:, -1]
    jacobian = scale * r[m:, linear:-1]
    if not bounded:
        jacobian[0] = 0.0
    elif scale > 0.0:
        jacobian += np.outer(shape, limit_gradient)
    return coefficients, residual, jacobian


def search_bounds(u: np.ndarray, y: np.ndarray, a1: float, operators: int) -> tuple[np.ndarray, np.ndarray]:
    """Box for (a2..a9, a11*a9): increasing envelopes, positive thresholds, ranges from the data scale,
    weights within DECAY_LIMITS of each other."""
    half_range = 0.5 * float(np.ptp(u))
    centre = 0.5 * float(np.max(u) + np.min(u))
    shift = 100.0 * (abs(centre) / half_range + 10.0)
    middle = 0.5 * float(np.max(y) + np.min(y))
    gain = (1e-2 / half_range, 1e2 / half_range)
    offset = (middle - 100.0 * a1, middle + 100.0 * a1)
    a9_high = 10.0 * a1 / max(operators - 1, 1)
    steps = max(operators - 1, 1)
    low = [gain[0], -shift, offset[0], 1e-2 * a1, gain[0], -shift, offset[0], 1e-8 * a1, DECAY_LIMITS[0] / steps]
    high = [gain[1], shift, offset[1], 1e2 * a1, gain[1], shift, offset[1], a9_high, DECAY_LIMITS[1] / steps]
    return np.array(low), np.array(high)


def free_start(params: GPIParameters) -> tuple[float, np.ndarray]:
    """(a1 to hold, free start) with the envelope signs in the increasing convention a1, a2, a5, a6 > 0."""
    a = params.as_array()
    for scale, gain, shift in ((0, 1, 2), (4, 5, 6)):
        if a[scale] < 0.0 and a[gain] < 0.0:
            a[scale], a[gain], a[shift] = -a[scale], -a[gain], -a[shift]
        a[scale], a[gain] = abs(a[scale]), abs(a[gain])
    if a[0] == 0.0:
        raise InputError("the warm start has a1 = 0 (a flat loading envelope)")
    return float(a[0]), np.concatenate([a[1:9], [a[10] * a[8]]])
