"""Bounded Levenberg-Marquardt for the fit's small, QR-compressed least-squares problems: plain arrays in,
an `scipy.optimize.OptimizeResult` out, as `scipy.optimize.least_squares`."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy.optimize import OptimizeResult

from sma_stage.identify.cancel import check_cancelled

TOLERANCE = 1e-10
_LM_MESSAGES = {0: "The maximum number of function evaluations is exceeded.",
                1: "`gtol` termination condition is satisfied.",
                2: "`ftol` termination condition is satisfied.",
                3: "`xtol` termination condition is satisfied."}


_LM_LARGEST_DAMPING = 1e16


def levenberg_marquardt(fun: Callable[[np.ndarray], np.ndarray], jac: Callable[[np.ndarray], np.ndarray],
                        x0: np.ndarray, bounds: tuple[np.ndarray, np.ndarray], max_nfev: int,
                        tolerance: float = TOLERANCE) -> OptimizeResult:
    """Minimise ||fun(x)||^2 within bounds: Levenberg-Marquardt with More's column scaling, the step
    clipped to the box and the parameters held at a bound the gradient pushes against. For the fit's
    small compressed problems, where scipy's TRF spent more time in its own Python than in fun.

    Stops (status as least_squares's) after max_nfev evaluations (0), when every free column is within
    tolerance of orthogonal to the residual (1), when an accepted step lowers the cost by at most
    tolerance of it, or no step lowers it (2), or an accepted step moves x by at most tolerance of it (3).
    Returns an OptimizeResult: x, cost (half the sum of squares), fun, jac, nfev, status, message."""
    low, high = (np.asarray(bound, dtype=float) for bound in bounds)
    inner_low, inner_high = low + 1e-9 * (high - low), high - 1e-9 * (high - low)
    x = np.clip(np.asarray(x0, dtype=float), inner_low, inner_high)
    residual, jacobian = fun(x), jac(x)
    cost = float(residual @ residual)
    if not (math.isfinite(cost) and np.all(np.isfinite(jacobian))):
        raise ValueError("the residual or its Jacobian is not finite at the start")
    evaluations, status = 1, 0
    column_scale = np.zeros(x.size)
    damping, growth = 1e-3, 2.0
    at_new_point = True
    while evaluations < max_nfev:
        check_cancelled()
        if at_new_point:
            gradient = jacobian.T @ residual
            normal = jacobian.T @ jacobian
            column_scale = np.maximum(column_scale, np.sqrt(np.diag(normal)))
            scale = np.where(column_scale > 0.0, column_scale, 1.0)
            free = ~(((x <= inner_low) & (gradient > 0.0)) | ((x >= inner_high) & (gradient < 0.0)))
            if not free.any() or np.max(np.abs(gradient[free]) / scale[free]) <= tolerance * math.sqrt(cost):
                status = 1
                break
            at_new_point = False
        every = bool(free.all())
        system = normal.copy() if every else normal[np.ix_(free, free)]
        system.flat[::system.shape[0] + 1] += damping * scale[free] ** 2
        try:
            step = np.linalg.solve(system, -gradient[free])
        except np.linalg.LinAlgError:
            step = np.zeros(system.shape[0])
        if np.all(np.isfinite(step)):
            if every:
                trial = np.clip(x + step, inner_low, inner_high)
            else:
                trial = x.copy()
                trial[free] = np.clip(x[free] + step, inner_low[free], inner_high[free])
            moved = trial - x
            predicted = cost - float(np.sum((residual + jacobian @ moved) ** 2))
            trial_residual = fun(trial)
            evaluations += 1
            trial_cost = float(trial_residual @ trial_residual)
            if predicted > 0.0 and trial_cost < cost:
                lowered = cost - trial_cost
                x, residual, cost, jacobian = trial, trial_residual, trial_cost, jac(trial)
                damping *= max(1.0 / 3.0, 1.0 - (2.0 * lowered / predicted - 1.0) ** 3)
                growth, at_new_point = 2.0, True
                if lowered <= tolerance * (cost + lowered):
                    status = 2
                    break
                if _norm(moved * scale) <= tolerance * (tolerance + _norm(x * scale)):
                    status = 3
                    break
                continue
        damping *= growth
        growth *= 2.0
        if damping > _LM_LARGEST_DAMPING:
            status = 2
            break
    return OptimizeResult(x=x, cost=0.5 * cost, fun=residual, jac=jacobian, nfev=evaluations, status=status,
                          message=_LM_MESSAGES[status], success=status > 0)


def _norm(vector: np.ndarray) -> float:
    return math.sqrt(float(vector @ vector))
