"""`rate`: thresholds that grow with the input's rate, in either of the literature's two forms, chosen by
the data: multiplicative r_i(t) = a9 i (1 + c |du/dt|), or additive r_i(t) = a9 i + b |du/dt| (every
operator, the first too). The weights keep their nominal p(a9 i).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from sma_stage.identify.effects.base import (
    FITTED_STARTS,
    THOROUGH_STARTS,
    Candidate,
    EffectFit,
    Progress,
    finish_fit,
    fit_or_none,
    pick,
    report,
)
from sma_stage.identify.fit import (
    OPERATOR_CANDIDATES,
    FitResult,
)
from sma_stage.model.effects import Effect, rate_forward
from sma_stage.model.identified import IdentifiedModel
from sma_stage.model.parameters import GPIParameters

RATE_GAIN_GRID = (0.0, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0)  # scanned c, times 1 / max |du/dt|
RATE_GAIN_LIMIT = 100.0  # largest c, times 1 / max |du/dt|
RATE_MAX_EVALUATIONS = 200


FORMS = {"multiplicative": "rate_gain_s_per_A", "additive": "rate_shift_m_s_per_A"}  # form -> its parameter


def rate_model_output(t: np.ndarray, u: np.ndarray, params: GPIParameters, operators: int,
                      gain_s_per_A: float, form: str = "multiplicative") -> np.ndarray:
    """The rate model's output [output unit] for a record (t [s], u [A]) from an idle stage; gain_s_per_A is
    c [s/A] (multiplicative) or b [output unit s/A] (additive)."""
    return IdentifiedModel(params, operators, (Effect("rate", {FORMS[form]: gain_s_per_A}),)).predict(t, u)


def _rate_record(t: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(u, |du/dt|) [A, A/s] with the idle-start sample ahead of the first, as the rate model runs them."""
    currents, rates, _ = Effect("rate", {"rate_gain_s_per_A": 0.0}).rate_input(t, u)
    return currents, rates



@dataclass(frozen=True)
class _RateFit:
    params: GPIParameters
    operators: int
    gain: float
    cost: float
    form: str


class RateEffect(Candidate):
    """GPI with rate-dependent thresholds, each form fitted and the lower cost kept (both add one
    parameter): the rate coefficient scanned with the GPI held, then a1..a11 and it refitted together
    (trust-region reflective, a10 solved linearly inside)."""

    name = "rate"
    relative_cost = 2.1

    def fit(self, t: np.ndarray, u: np.ndarray, y: np.ndarray, base: FitResult, progress: Progress = None,
            starts: tuple[str, ...] = FITTED_STARTS) -> EffectFit:
        started = time.perf_counter()
        currents, rates = _rate_record(t, u)
        found = min((_rate_fit(currents, rates, y, base.parameters, base.operators, form) for form in FORMS),
                    key=lambda fit: fit.cost)
        return self._finish(found, t, u, y, base.parameter_count + 1, started, progress)

    def recount(self, fit: EffectFit, t: np.ndarray, u: np.ndarray, y: np.ndarray,
                progress: Progress = None) -> EffectFit:
        """Refit from a plain GPI fit of every other candidate operator count; keep the rule's choice."""
        started = time.perf_counter()
        currents, rate = _rate_record(t, u)
        unit = fit.gpi_parameters.output_unit
        fits: list = [fit]
        for count in OPERATOR_CANDIDATES:
            start = None if count == fit.operators else fit_or_none(u, y, count, None, unit, None, THOROUGH_STARTS)
            if start is not None:
                fits.append(_rate_fit(currents, rate, y, start.parameters, count, fit_form(fit)))
        chosen = pick(fits)
        if chosen is fit:
            return fit
        return self._finish(chosen, t, u, y, fit.parameter_count, started, progress)

    def _finish(self, found: _RateFit, t: np.ndarray, u: np.ndarray, y: np.ndarray, parameter_count: int,
                started: float, progress: Progress) -> EffectFit:
        params, operators, gain, name = found.params, found.operators, found.gain, FORMS[found.form]
        report(progress, f"rate ({found.form}): {name} = {gain:.4g}, {operators} operators")
        return finish_fit(self.name, {name: gain}, params, operators, y,
                          rate_model_output(t, u, params, operators, gain, found.form), parameter_count, started)


def fit_form(fit: EffectFit) -> str:
    """The form of a fitted rate effect."""
    return next(form for form, name in FORMS.items() if name in fit.parameters)


def _rate_fit(u: np.ndarray, rate: np.ndarray, y: np.ndarray, start_params: GPIParameters,
              operators: int, form: str) -> _RateFit:
    """The rate model of one form fitted from a GPI start: a scan of its coefficient with the GPI held, then
    everything together. u and rate [A, A/s] carry the idle-start sample ahead of y's first (see
    _rate_record). The coefficient's scale: one over the largest rate (multiplicative), the largest
    threshold over it (additive)."""
    start = start_params.as_array()
    largest_threshold = abs(start[8]) * max(operators - 1, 1)
    scale = (1.0 if form == "multiplicative" else largest_threshold) / max(float(np.max(rate)), np.finfo(float).tiny)
    grid = [factor * scale for factor in RATE_GAIN_GRID]
    scan = [_rate_projection(start, gain, u, rate, y, operators, form)[1] for gain in grid]
    free = [k for k in range(11) if k != 9]

    def residual(x: np.ndarray) -> np.ndarray:
        values = start.copy()
        values[free] = x[:-1]
        return _rate_projection(values, x[-1], u, rate, y, operators, form)[2]

    lower = np.full(len(free) + 1, -np.inf)
    upper = np.full(len(free) + 1, np.inf)
    lower[8], lower[-1], upper[-1] = 1e-8 * abs(start[8]), 0.0, RATE_GAIN_LIMIT * scale
    x0 = np.clip(np.append(start[free], grid[int(np.argmin(scan))]), lower, upper)
    solution = least_squares(residual, x0, bounds=(lower, upper), x_scale="jac", method="trf",
                             max_nfev=RATE_MAX_EVALUATIONS)
    values = start.copy()
    values[free] = solution.x[:-1]
    gain = float(solution.x[-1])
    values[9], cost, _ = _rate_projection(values, gain, u, rate, y, operators, form)
    return _RateFit(GPIParameters.from_array(values, start_params.output_unit), operators, gain, cost, form)


def _rate_projection(values: np.ndarray, gain: float, u: np.ndarray, rate: np.ndarray, y: np.ndarray,
                     operators: int, form: str) -> tuple[float, float, np.ndarray]:
    """(best a10 >= 0, SSR, residual in output spans) for the rate model with a1..a9, a11 from values;
    u and rate have one sample more than y (the idle start), whose output is left out."""
    theta = values.copy()
    theta[9] = 1.0
    multiplied, shifted = (gain, 0.0) if form == "multiplicative" else (0.0, gain)
    shape = rate_forward(u, rate, theta, operators, multiplied, None, shifted)[0][1:]
    with np.errstate(over="ignore", invalid="ignore"):  # a search step can make the shape overflow
        norm, projection = float(shape @ shape), float(shape @ y)
    usable = norm > 0.0 and math.isfinite(norm) and math.isfinite(projection)
    a10 = max(projection / norm, 0.0) if usable else 0.0
    residual = a10 * shape - y if a10 > 0.0 else -y  # an unusable shape predicts nothing (0 * inf is nan)
    return a10, float(residual @ residual), residual / max(float(np.ptp(y)), np.finfo(float).tiny)


EFFECT = RateEffect()
