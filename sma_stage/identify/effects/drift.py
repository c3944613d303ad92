"""`drift`: y = GPI(u) + k (t - t0) [+ A (1 - exp(-(t - t0)/tau_c)) when the creep term earns its place].
"""

from __future__ import annotations

import math
import time

import numpy as np

from sma_stage.identify.effects.base import (
    BOUND_MARGIN,
    FITTED_STARTS,
    SEARCH_GRID_POINTS,
    THOROUGH_STARTS,
    Candidate,
    EffectFit,
    NotFitted,
    Progress,
    cold_fit,
    finish_fit,
    fit_or_none,
    lowest_cost,
    pick,
    report,
    scalar_search,
)
from sma_stage.identify.fit import (
    FitResult,
    information_criterion,
)
from sma_stage.model.effects import drift_regressors
from sma_stage.model.parameters import GPIParameters

CREEP_TAU_RANGE_FRACTION = (0.01, 1.0)  # creep time constant bounds, fractions of the duration


class DriftEffect(Candidate):
    """GPI plus a linear drift k (t - t0) [m/s], solved linearly inside the fit; a creep term
    A (1 - exp(-(t - t0)/tau_c)) [m] joins when it lowers the BIC (tau_c searched with the GPI held)."""

    name = "drift"
    relative_cost = 2.0

    def fit(self, t: np.ndarray, u: np.ndarray, y: np.ndarray, base: FitResult, progress: Progress = None,
            starts: tuple[str, ...] = FITTED_STARTS) -> EffectFit:
        started = time.perf_counter()
        return self._fit_at(t, u, y, base.parameters, base.operators, base.parameter_count, started, progress)

    def recount(self, fit: EffectFit, t: np.ndarray, u: np.ndarray, y: np.ndarray,
                progress: Progress = None) -> EffectFit:
        """The count chosen by fit_gpi's rule with the linear drift; the creep decided again at it."""
        started = time.perf_counter()
        counted = fit_or_none(u, y, None, None, fit.gpi_parameters.output_unit, drift_regressors(t - t[0], None),
                               THOROUGH_STARTS)
        if counted is None or counted.operators == fit.operators:
            return fit
        plain_count = fit.parameter_count - len(fit.parameters)
        refit = self._fit_at(t, u, y, counted.parameters, counted.operators, plain_count, started, progress)
        return refit if pick([fit, refit]) is refit else fit

    def _fit_at(self, t: np.ndarray, u: np.ndarray, y: np.ndarray, start: GPIParameters, count: int,
                plain_count: int, started: float, progress: Progress) -> EffectFit:
        """Linear drift, then linear drift and creep, at one operator count; the lower BIC is kept (the
        linear drift alone where the creep cannot be fitted, or where its time constant ends at a bound of
        its search, which the record does not resolve)."""
        unit = start.output_unit
        linear = self._refit(u, y, count, start, unit, drift_regressors(t - t[0], None))
        if linear is None:
            raise NotFitted(f"drift: the GPI with a linear drift cannot be fitted at {count} operators")
        tau_c = _creep_time_constant(t, y, linear)
        low, high = (fraction * float(t[-1] - t[0]) for fraction in CREEP_TAU_RANGE_FRACTION)
        if not (1.0 + BOUND_MARGIN) * low < tau_c < high / (1.0 + BOUND_MARGIN):  # at a bound: not resolved
            return self._finish(t, y, linear, None, plain_count + 1, started, progress)
        creep = self._refit(u, y, count, linear.parameters, unit, drift_regressors(t - t[0], tau_c))
        samples, k = y.size, plain_count
        if creep is not None and (information_criterion(creep.cost, samples, k + 3)
                                  < information_criterion(linear.cost, samples, k + 1)):
            return self._finish(t, y, creep, tau_c, k + 3, started, progress)
        return self._finish(t, y, linear, None, k + 1, started, progress)

    @staticmethod
    def _refit(u: np.ndarray, y: np.ndarray, count: int, start: GPIParameters, unit: str,
               columns: np.ndarray) -> FitResult | None:
        """The better of a warm-started and a cold fit (the warm one may keep what the plain GPI absorbed);
        None when neither can be had."""
        warm = fit_or_none(u, y, count, start, unit, columns)
        return lowest_cost((warm, cold_fit(u, y, count, unit, warm, columns)))

    def _finish(self, t: np.ndarray, y: np.ndarray, gpi: FitResult, tau_c: float | None, parameter_count: int,
                started: float, progress: Progress) -> EffectFit:
        coefficients = gpi.regressor_coefficients
        values = {"drift_m_per_s": float(coefficients[0])}
        if tau_c is not None:
            values.update({"creep_m": float(coefficients[1]), "creep_tau_s": tau_c})
        report(progress, "drift: " + ", ".join(f"{name} = {value:.4g}" for name, value in values.items()))
        return finish_fit(self.name, values, gpi.parameters, gpi.operators, y, gpi.predicted, parameter_count,
                       started)


def _creep_time_constant(t: np.ndarray, y: np.ndarray, linear: FitResult) -> float:
    """tau_c [s] that best explains what the linear-drift fit leaves, with its GPI output held."""
    gpi_part = linear.predicted - drift_regressors(t - t[0], None) @ linear.regressor_coefficients
    duration = float(t[-1] - t[0])

    def cost(log_tau: float, thorough: bool) -> float:
        basis = np.column_stack([gpi_part, np.ones_like(t), drift_regressors(t - t[0], math.exp(log_tau))])
        coefficients, *_ = np.linalg.lstsq(basis, y, rcond=None)
        residual = y - basis @ coefficients
        return float(residual @ residual)

    low, high = (fraction * duration for fraction in CREEP_TAU_RANGE_FRACTION)
    return math.exp(scalar_search(cost, low, high, SEARCH_GRID_POINTS, thorough=False))


EFFECT = DriftEffect()
