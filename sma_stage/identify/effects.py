"""Candidate effects the plain GPI lacks, each a model with the GPI inside, fitted from the base fit.

- `thermal_lag`: the hysteresis sees the first-order lag v of the current (or of its Joule heating),
  the current held between samples (sma_stage.model.effects).
- `delay`: the hysteresis sees u(t - d) (dead time d, linear interpolation between samples).
- `rate`: thresholds r_i(t) = a9 i (1 + c |du/dt|) (the weights keep their nominal p(a9 i)).
- `drift`: y = GPI(u) + k (t - t0) [+ A (1 - exp(-(t - t0)/tau_c)) when the creep term earns its place].

Every effect has `fit(t, u, y, base)` (at the base fit's operator count) and `recount(fit, t, u, y)`
(the operator count chosen again, by fit_gpi's rule, for the model with the effect). Time t is in s
(or samples for quasi-static data), u in A, y in the output unit (m). Every record starts from an idle
stage: the current switched on one sample period before the first sample (zero before; the filter
state and the delay line at zero) and the operator states at zero, as in the model core. The forward
model of each effect is sma_stage.model.effects, the code the compensator runs too; each fit is an
EffectFit whose `model` is the IdentifiedModel it found.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from scipy.optimize import least_squares, minimize_scalar

from sma_stage.errors import InputError
from sma_stage.identify.fit import (
    OPERATOR_CANDIDATES,
    FitResult,
    choose_operator_count,
    fit_gpi,
    information_criterion,
)
from sma_stage.identify.metrics import ErrorMetrics, error_metrics
from sma_stage.model.effects import EFFECT_KINDS, Effect, drift_regressors, rate_forward
from sma_stage.model.identified import IdentifiedModel
from sma_stage.model.parameters import GPIParameters

EFFECT_NAMES: tuple[str, ...] = EFFECT_KINDS
SEARCH_GRID_POINTS = 6
LOG_TOLERANCE = 1e-3  # tolerance of the scalar searches on the log of the parameter (0.1 %)
COARSE_LOG_TOLERANCE = 5e-2  # tolerance of the thorough stage of a search (5 %)
LAG_RANGE_FRACTION = 0.1  # largest tau or delay, as a fraction of the record's duration
MIN_LAG_SAMPLES = 0.02  # smallest tau or delay, in sample periods
THOROUGH_STARTS = 2  # data-derived starts of the cold fit in a thorough evaluation
SEARCH_SAMPLES = 500  # the wide search of tau or d runs on a thinned copy of about this many samples
NARROW_FACTOR = 1.1  # after a change of operator count, x is searched again within x / 1.1 .. 1.1 x
RATE_GAIN_GRID = (0.0, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0)  # scanned c, times 1 / max |du/dt|
RATE_GAIN_LIMIT = 100.0  # largest c, times 1 / max |du/dt|
RATE_MAX_EVALUATIONS = 200
CREEP_TAU_RANGE_FRACTION = (0.01, 1.0)  # creep time constant bounds, fractions of the duration

Progress = Callable[[str], None] | None
Fitted = TypeVar("Fitted")
# What a fit that cannot be had raises: refused data (InputError) or a numerical failure on the way
# (an overflow, a singular matrix, scipy refusing a non-finite residual).
FIT_FAILURES = (InputError, ArithmeticError, np.linalg.LinAlgError, ValueError)


class NotFitted(InputError):
    """No fit could be found for a candidate effect (or one form of it); the message says why."""


def attempt(what: str, action: Callable[[], Fitted]) -> Fitted | NotFitted:
    """action()'s result, or NotFitted("what: why") when it could not be fitted: the one place where a
    candidate that cannot be fitted becomes a reported outcome instead of an error."""
    try:
        return action()
    except FIT_FAILURES as error:
        reason = " ".join(str(error).split()) or type(error).__name__
        return NotFitted(reason if reason.startswith(f"{what}:") else f"{what}: {reason}")


def lowest_cost(fits: Iterable[Fitted | None]) -> Fitted | None:
    """The fit of least finite .cost among those found (None entries are fits that failed); None if none."""
    found = [fit for fit in fits if fit is not None and math.isfinite(fit.cost)]
    return min(found, key=lambda fit: fit.cost) if found else None


@dataclass(frozen=True)
class EffectFit:
    """A fitted candidate: its extra parameters (name -> value, units in the name), the GPI inside,
    identification errors and the sum of squared residuals `cost` [output unit^2]; "none" for the plain
    GPI in the same form."""

    effect: str
    parameters: dict[str, float]
    gpi_parameters: GPIParameters
    operators: int
    identification: ErrorMetrics
    cost: float
    samples: int
    parameter_count: int
    seconds: float

    @property
    def spec(self) -> Effect | None:
        """The effect as the model carries it (None for the plain GPI)."""
        return None if self.effect == "none" else Effect(self.effect, self.parameters)

    @property
    def model(self) -> IdentifiedModel:
        """The GPI with this effect."""
        spec = self.spec
        return IdentifiedModel(self.gpi_parameters, self.operators, () if spec is None else (spec,))

    @property
    def composable(self) -> bool:
        """Whether a further effect can be fitted on top: not after `rate` (it changes the GPI itself)."""
        return self.spec is None or self.spec.role != "gpi"

    def predict(self, t: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Model output [output unit] for another record (time t [s], input u [A]) from an idle stage."""
        t, u = check_record(t, u)
        return self.model.predict(t, u)

    @property
    def bic(self) -> float:
        """Bayesian information criterion on the identification data: N ln(SSR/N) + k ln N."""
        return information_criterion(self.cost, self.samples, self.parameter_count)


def check_record(t: np.ndarray, u: np.ndarray, y: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """Float copies of (t, u[, y]), refused unless 1-D, equally long, finite, and t increasing."""
    arrays = [np.array(a, dtype=float).reshape(-1) for a in ((t, u) if y is None else (t, u, y))]
    if len({a.size for a in arrays}) != 1 or arrays[0].size < 3:
        raise InputError(f"t, u (and y) must be equally long with at least 3 samples, got {[a.size for a in arrays]}")
    if not all(np.all(np.isfinite(a)) for a in arrays):
        raise InputError("t, u and y must be finite")
    if np.any(np.diff(arrays[0]) <= 0.0):
        raise InputError("time must increase from sample to sample")
    return tuple(arrays)


# ---- transforms and the rate model --------------------------------------------------------------


def lagged_input(t: np.ndarray, u: np.ndarray, tau_s: float, joule_reference_a: float = 0.0) -> np.ndarray:
    """The lag v [A] of the current (of its Joule heating u |u| / joule_reference_a when that is above 0)
    from an idle stage: the thermal_lag effect's input transform."""
    parameters = {"tau_s": tau_s, **({"joule_reference_a": joule_reference_a} if joule_reference_a > 0.0 else {})}
    return Effect("thermal_lag", parameters).transform(t, u)[0]


def delayed_input(t: np.ndarray, u: np.ndarray, delay_s: float) -> np.ndarray:
    """u(t - d) [A], linear between samples, from an idle stage (zero before the current was switched
    on): the delay effect's input transform."""
    return Effect("delay", {"delay_s": delay_s}).transform(t, u)[0]


def rate_model_output(t: np.ndarray, u: np.ndarray, params: GPIParameters, operators: int,
                      gain_s_per_A: float) -> np.ndarray:
    """The rate model's output [output unit] for a record (t [s], u [A]) from an idle stage."""
    return IdentifiedModel(params, operators, (Effect("rate", {"rate_gain_s_per_A": gain_s_per_A}),)).predict(t, u)


def _rate_record(t: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(u, |du/dt|) [A, A/s] with the idle-start sample ahead of the first, as the rate model runs them."""
    currents, rates, _ = Effect("rate", {"rate_gain_s_per_A": 0.0}).rate_input(t, u)
    return currents, rates


# ---- fitting machinery ---------------------------------------------------------------------------


def _fit_or_none(v: np.ndarray, y: np.ndarray, operators: int | None, initial: GPIParameters | None, unit: str,
                 regressors: np.ndarray | None = None, starts: int | None = None) -> FitResult | None:
    """fit_gpi, or None where the data cannot be fitted (e.g. a delay so long that the output falls as
    the input rises)."""
    result = attempt("GPI", lambda: fit_gpi(v, y, operators=operators, initial=initial, output_unit=unit,
                                             regressors=regressors, starts=starts))
    return None if isinstance(result, NotFitted) else result


def _pick(fits: Sequence) -> object:
    """fit_gpi's operator-count rule (choose_operator_count) over fits of several counts (anything with
    .cost and .operators; None for one that failed); of the count chosen, the lowest cost. The first fit
    must exist (the one the others are compared with)."""
    found = [fit for fit in fits if fit is not None and math.isfinite(fit.cost)]
    costs: dict[int, float] = {}
    for fit in found:
        costs[fit.operators] = min(fit.cost, costs.get(fit.operators, math.inf))
    count = choose_operator_count(costs)
    return lowest_cost(fit for fit in found if fit.operators == count)


class _Refits:
    """GPI fits (one operator count) on a transformed input u_of(x), x the effect parameter. Each is
    warm-started from the fit at the nearest x so far (the optimum moves smoothly with x) and, when
    thorough, also from fit_gpi's data-derived starts (a start far away can sit in the basin where the
    plain GPI absorbed the effect); the lower cost is kept."""

    def __init__(self, u_of: Callable[[float], np.ndarray], y: np.ndarray, base: FitResult) -> None:
        self.u_of, self.y, self.base = u_of, y, base
        self.fits: dict[float, FitResult | None] = {}

    def fit(self, value: float, thorough: bool = False) -> FitResult | None:
        """The best fit found at this x (None if it cannot be fitted)."""
        if value not in self.fits or thorough:
            tries = [self.fits.get(value), self._try(value, self._nearest(value).parameters)]
            if thorough:
                tries.append(self._try(value, None, THOROUGH_STARTS))
            self.fits[value] = lowest_cost(tries)
        return self.fits[value]

    def cost(self, log_value: float, thorough: bool = False) -> float:
        """SSR of the fit at exp(log_value) (inf where it cannot be fitted)."""
        result = self.fit(math.exp(log_value), thorough)
        return math.inf if result is None else float(result.cost)

    def _nearest(self, value: float) -> FitResult:
        fitted = [(abs(math.log(key / value)), fit) for key, fit in self.fits.items() if fit is not None]
        return min(fitted, key=lambda pair: pair[0])[1] if fitted else self.base

    def _try(self, value: float, initial: GPIParameters | None, starts: int | None = None) -> FitResult | None:
        return _fit_or_none(self.u_of(value), self.y, self.base.operators, initial,
                            self.base.parameters.output_unit, starts=starts)


def _scalar_search(cost: Callable[[float, bool], float], low: float, high: float, grid_points: int,
                   thorough: bool = True) -> float:
    """The log x in [log low, log high] of least cost(log x, thorough): a log-spaced grid, then a bounded
    Brent search between the best grid point's neighbours (to COARSE_LOG_TOLERANCE when thorough, else
    to LOG_TOLERANCE). The GPI fit has local minima, so a wide search needs thorough evaluations: a
    local polish alone stops where the plain GPI absorbed the effect."""
    grid = np.linspace(math.log(low), math.log(high), grid_points)
    costs = [cost(x, thorough) for x in grid]
    best = int(np.argmin(costs))
    x, fun = _brent(lambda x: cost(x, thorough), grid[max(best - 1, 0)], grid[min(best + 1, grid.size - 1)],
                    COARSE_LOG_TOLERANCE if thorough else LOG_TOLERANCE)
    return float(x) if fun <= costs[best] else float(grid[best])


def _fine_search(cost: Callable[[float, bool], float], log_value: float, low: float, high: float) -> float:
    """A quick Brent search (warm starts only) to LOG_TOLERANCE within 2 COARSE_LOG_TOLERANCE of log_value."""
    margin = 2.0 * COARSE_LOG_TOLERANCE
    x, fun = _brent(lambda z: cost(z, False), max(log_value - margin, math.log(low)),
                    min(log_value + margin, math.log(high)), LOG_TOLERANCE)
    return x if fun < cost(log_value, False) else log_value


def _brent(cost: Callable[[float], float], left: float, right: float, tolerance: float) -> tuple[float, float]:
    found = minimize_scalar(cost, bounds=(left, right), method="bounded", options={"xatol": tolerance})
    return float(found.x), float(found.fun)


def _finish(effect: str, values: dict[str, float], gpi: GPIParameters, operators: int, y: np.ndarray,
            predicted: np.ndarray, parameter_count: int, started: float) -> EffectFit:
    residual = y - predicted
    return EffectFit(
        effect=effect, parameters=values, gpi_parameters=gpi, operators=int(operators),
        identification=error_metrics(y, predicted), cost=float(residual @ residual), samples=int(y.size),
        parameter_count=int(parameter_count), seconds=time.perf_counter() - started,
    )


def _report(progress: Progress, message: str) -> None:
    if progress is not None:
        progress(message)


# ---- the effects ---------------------------------------------------------------------------------


class Candidate:
    """A candidate effect: `fit` from the base GPI fit (its operator count), `recount` to choose the
    operator count again for the model with the effect."""

    name = ""

    def fit(self, t: np.ndarray, u: np.ndarray, y: np.ndarray, base: FitResult,
            progress: Progress = None) -> EffectFit:
        raise NotImplementedError

    def recount(self, fit: EffectFit, t: np.ndarray, u: np.ndarray, y: np.ndarray,
                progress: Progress = None) -> EffectFit:
        raise NotImplementedError


class InputTransformEffect(Candidate):
    """The GPI driven by a transformed input transform(t, u, x), x [s] found by a bounded search over
    log x with the GPI refitted at every x."""

    def __init__(self, name: str, parameter: str, transform: Callable[[np.ndarray, np.ndarray, float], np.ndarray]):
        self.name, self.parameter, self.transform = name, parameter, transform

    def fit(self, t: np.ndarray, u: np.ndarray, y: np.ndarray, base: FitResult,
            progress: Progress = None) -> EffectFit:
        started = time.perf_counter()
        bounds = _lag_range(t)
        keep = _even_indices(t.size)
        wide = _Refits(lambda x: self.transform(t[keep], u[keep], x), y[keep], base)
        log_value = _scalar_search(wide.cost, *bounds, SEARCH_GRID_POINTS)
        found = wide.fit(math.exp(log_value)) or base
        fits = _Refits(lambda x: self.transform(t, u, x), y, found)
        value = math.exp(_fine_search(fits.cost, log_value, *bounds))
        gpi = fits.fit(value, thorough=True)
        return self._finish(value, gpi, y, base.parameter_count + 1, started, progress)

    def recount(self, fit: EffectFit, t: np.ndarray, u: np.ndarray, y: np.ndarray,
                progress: Progress = None) -> EffectFit:
        started = time.perf_counter()
        value = fit.parameters[self.parameter]
        counted = _fit_or_none(self.transform(t, u, value), y, None, None, fit.gpi_parameters.output_unit,
                               starts=THOROUGH_STARTS)
        if counted is None or _pick([fit, counted]) is fit:
            return fit
        fits = _Refits(lambda x: self.transform(t, u, x), y, counted)
        fits.fits[value] = counted
        low, high = _lag_range(t)
        narrow = (max(value / NARROW_FACTOR, low), min(value * NARROW_FACTOR, high))
        value = math.exp(_scalar_search(fits.cost, *narrow, 3, thorough=False))
        return self._finish(value, fits.fit(value, thorough=True), y, fit.parameter_count, started, progress)

    def _finish(self, value: float, gpi: FitResult | None, y: np.ndarray, parameter_count: int, started: float,
                progress: Progress) -> EffectFit:
        if gpi is None:
            raise NotFitted(f"{self.name}: the GPI cannot be fitted at {self.parameter} = {value:.4g}")
        _report(progress, f"{self.name}: {self.parameter} = {value:.4g}, {gpi.operators} operators")
        return _finish(self.name, {self.parameter: value}, gpi.parameters, gpi.operators, y, gpi.predicted,
                       parameter_count, started)


def _even_indices(samples: int) -> np.ndarray:
    """Indices of an evenly thinned copy of at most about SEARCH_SAMPLES samples, for the wide search."""
    return np.arange(0, samples, max(1, round(samples / SEARCH_SAMPLES)))


def _lag_range(t: np.ndarray) -> tuple[float, float]:
    """Bounds [s] of a lag or delay search: MIN_LAG_SAMPLES of a sample period to a tenth of the record."""
    step = float(np.median(np.diff(t)))
    return MIN_LAG_SAMPLES * step, max(LAG_RANGE_FRACTION * float(t[-1] - t[0]), step)


class DriftEffect(Candidate):
    """GPI plus a linear drift k (t - t0) [m/s], solved linearly inside the fit; a creep term
    A (1 - exp(-(t - t0)/tau_c)) [m] joins when it lowers the BIC (tau_c searched with the GPI held)."""

    name = "drift"

    def fit(self, t: np.ndarray, u: np.ndarray, y: np.ndarray, base: FitResult,
            progress: Progress = None) -> EffectFit:
        started = time.perf_counter()
        return self._fit_at(t, u, y, base.parameters, base.operators, base.parameter_count, started, progress)

    def recount(self, fit: EffectFit, t: np.ndarray, u: np.ndarray, y: np.ndarray,
                progress: Progress = None) -> EffectFit:
        """The count chosen by fit_gpi's rule with the linear drift; the creep decided again at it."""
        started = time.perf_counter()
        counted = _fit_or_none(u, y, None, None, fit.gpi_parameters.output_unit, drift_regressors(t - t[0], None),
                               THOROUGH_STARTS)
        if counted is None or counted.operators == fit.operators:
            return fit
        plain_count = fit.parameter_count - len(fit.parameters)
        refit = self._fit_at(t, u, y, counted.parameters, counted.operators, plain_count, started, progress)
        return refit if _pick([fit, refit]) is refit else fit

    def _fit_at(self, t: np.ndarray, u: np.ndarray, y: np.ndarray, start: GPIParameters, count: int,
                plain_count: int, started: float, progress: Progress) -> EffectFit:
        """Linear drift, then linear drift and creep, at one operator count; the lower BIC is kept (the
        linear drift alone where the creep cannot be fitted)."""
        unit = start.output_unit
        linear = self._refit(u, y, count, start, unit, drift_regressors(t - t[0], None))
        if linear is None:
            raise NotFitted(f"drift: the GPI with a linear drift cannot be fitted at {count} operators")
        tau_c = _creep_time_constant(t, y, linear)
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
        return lowest_cost((_fit_or_none(u, y, count, start, unit, columns),
                            _fit_or_none(u, y, count, None, unit, columns, THOROUGH_STARTS)))

    def _finish(self, t: np.ndarray, y: np.ndarray, gpi: FitResult, tau_c: float | None, parameter_count: int,
                started: float, progress: Progress) -> EffectFit:
        coefficients = gpi.regressor_coefficients
        values = {"drift_m_per_s": float(coefficients[0])}
        if tau_c is not None:
            values.update({"creep_m": float(coefficients[1]), "creep_tau_s": tau_c})
        _report(progress, "drift: " + ", ".join(f"{name} = {value:.4g}" for name, value in values.items()))
        return _finish(self.name, values, gpi.parameters, gpi.operators, y, gpi.predicted, parameter_count,
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
    return math.exp(_scalar_search(cost, low, high, SEARCH_GRID_POINTS, thorough=False))


@dataclass(frozen=True)
class _RateFit:
    params: GPIParameters
    operators: int
    gain: float
    cost: float


class RateEffect(Candidate):
    """GPI with rate-dependent thresholds a9 i (1 + c |du/dt|): c [s/A] scanned with the GPI held, then
    a1..a11 and c refitted together (trust-region reflective, a10 solved linearly inside)."""

    name = "rate"

    def fit(self, t: np.ndarray, u: np.ndarray, y: np.ndarray, base: FitResult,
            progress: Progress = None) -> EffectFit:
        started = time.perf_counter()
        currents, rates = _rate_record(t, u)
        found = _rate_fit(currents, rates, y, base.parameters, base.operators)
        return self._finish(found, t, u, y, base.parameter_count + 1, started, progress)

    def recount(self, fit: EffectFit, t: np.ndarray, u: np.ndarray, y: np.ndarray,
                progress: Progress = None) -> EffectFit:
        """Refit from a plain GPI fit of every other candidate operator count; keep the rule's choice."""
        started = time.perf_counter()
        currents, rate = _rate_record(t, u)
        unit = fit.gpi_parameters.output_unit
        fits: list = [fit]
        for count in OPERATOR_CANDIDATES:
            start = None if count == fit.operators else _fit_or_none(u, y, count, None, unit, None, THOROUGH_STARTS)
            if start is not None:
                fits.append(_rate_fit(currents, rate, y, start.parameters, count))
        chosen = _pick(fits)
        if chosen is fit:
            return fit
        return self._finish(chosen, t, u, y, fit.parameter_count, started, progress)

    def _finish(self, found: _RateFit, t: np.ndarray, u: np.ndarray, y: np.ndarray, parameter_count: int,
                started: float, progress: Progress) -> EffectFit:
        params, operators, gain = found.params, found.operators, found.gain
        _report(progress, f"rate: rate_gain_s_per_A = {gain:.4g}, {operators} operators")
        return _finish(self.name, {"rate_gain_s_per_A": gain}, params, operators, y,
                       rate_model_output(t, u, params, operators, gain), parameter_count, started)


def _rate_fit(u: np.ndarray, rate: np.ndarray, y: np.ndarray, start_params: GPIParameters,
              operators: int) -> _RateFit:
    """The rate model fitted from a GPI start: a scan of c with the GPI held, then everything together.
    u and rate [A, A/s] carry the idle-start sample ahead of y's first (see _rate_record)."""
    scale = 1.0 / max(float(np.max(rate)), np.finfo(float).tiny)
    start = start_params.as_array()
    grid = [factor * scale for factor in RATE_GAIN_GRID]
    scan = [_rate_projection(start, gain, u, rate, y, operators)[1] for gain in grid]
    free = [k for k in range(11) if k != 9]

    def residual(x: np.ndarray) -> np.ndarray:
        values = start.copy()
        values[free] = x[:-1]
        return _rate_projection(values, x[-1], u, rate, y, operators)[2]

    lower = np.full(len(free) + 1, -np.inf)
    upper = np.full(len(free) + 1, np.inf)
    lower[8], lower[-1], upper[-1] = 1e-8 * abs(start[8]), 0.0, RATE_GAIN_LIMIT * scale
    x0 = np.clip(np.append(start[free], grid[int(np.argmin(scan))]), lower, upper)
    solution = least_squares(residual, x0, bounds=(lower, upper), x_scale="jac", method="trf",
                             max_nfev=RATE_MAX_EVALUATIONS)
    values = start.copy()
    values[free] = solution.x[:-1]
    gain = float(solution.x[-1])
    values[9], cost, _ = _rate_projection(values, gain, u, rate, y, operators)
    return _RateFit(GPIParameters.from_array(values, start_params.output_unit), operators, gain, cost)


def _rate_projection(values: np.ndarray, gain: float, u: np.ndarray, rate: np.ndarray, y: np.ndarray,
                     operators: int) -> tuple[float, float, np.ndarray]:
    """(best a10 >= 0, SSR, residual in output spans) for the rate model with a1..a9, a11 from values;
    u and rate have one sample more than y (the idle start), whose output is left out."""
    theta = values.copy()
    theta[9] = 1.0
    shape = rate_forward(u, rate, theta, operators, gain)[0][1:]
    norm = float(shape @ shape)
    a10 = max(float(shape @ y) / norm, 0.0) if norm > 0.0 else 0.0
    residual = a10 * shape - y
    return a10, float(residual @ residual), residual / max(float(np.ptp(y)), np.finfo(float).tiny)


class ThermalLagEffect(Candidate):
    """The GPI driven by a first-order lag (tau [s]) of either the current or of the Joule heating
    u |u| / u_ref (u_ref [A]: the record's largest |u|), whichever fits the identification data better
    (the wires heat as i^2 R, so the second is the physical reading; the first is exact for a plant whose
    drive is filtered linearly). The heating reading reports joule_reference_a = u_ref."""

    name = "thermal_lag"
    PARAMETER = "joule_reference_a"

    def fit(self, t: np.ndarray, u: np.ndarray, y: np.ndarray, base: FitResult,
            progress: Progress = None) -> EffectFit:
        reference = float(np.max(np.abs(u)))
        readings = [self._reading(None)]
        if reference > 0.0:
            readings.append(self._reading(reference))
        outcomes = [attempt(self.name, lambda reading=reading: reading.fit(t, u, y, base, progress))
                    for reading in readings]
        best = lowest_cost(outcome for outcome in outcomes if not isinstance(outcome, NotFitted))
        if best is None:
            raise NotFitted("thermal_lag: the GPI cannot be fitted on the lagged current nor on the lagged "
                            f"heating ({'; '.join(str(outcome) for outcome in outcomes)})")
        return best

    def recount(self, fit: EffectFit, t: np.ndarray, u: np.ndarray, y: np.ndarray,
                progress: Progress = None) -> EffectFit:
        return self._reading(fit.parameters.get(self.PARAMETER)).recount(fit, t, u, y, progress)

    def _reading(self, reference_a: float | None) -> InputTransformEffect:
        if reference_a is None:
            return InputTransformEffect(self.name, "tau_s", lagged_input)
        return _HeatingLag(self.name, "tau_s", lambda t, u, tau: lagged_input(t, u, tau, reference_a),
                           {self.PARAMETER: reference_a})


class _HeatingLag(InputTransformEffect):
    """The lag of the Joule heating: an InputTransformEffect that also reports the heating's reference."""

    def __init__(self, name: str, parameter: str, transform: Callable[[np.ndarray, np.ndarray, float], np.ndarray],
                 fixed: dict[str, float]) -> None:
        super().__init__(name, parameter, transform)
        self.fixed = fixed

    def _finish(self, value: float, gpi: FitResult | None, y: np.ndarray, parameter_count: int, started: float,
                progress: Progress) -> EffectFit:
        fit = super()._finish(value, gpi, y, parameter_count, started, progress)
        return dataclasses.replace(fit, parameters={**fit.parameters, **self.fixed})


EFFECTS: dict[str, Candidate] = {
    "thermal_lag": ThermalLagEffect(),
    "delay": InputTransformEffect("delay", "delay_s", delayed_input),
    "rate": RateEffect(),
    "drift": DriftEffect(),
}


def fit_effect(name: str, t: np.ndarray, u: np.ndarray, y: np.ndarray, base: FitResult,
               progress: Progress = None) -> EffectFit:
    """Fit the candidate effect `name` on (t [s], u [A], y) from the base GPI fit (its operator count)."""
    if name not in EFFECTS:
        raise InputError(f"unknown effect {name!r}; known: {', '.join(EFFECT_NAMES)}")
    t, u, y = check_record(t, u, y)
    return EFFECTS[name].fit(t, u, y, base, progress)


def recount_effect(fit: EffectFit, t: np.ndarray, u: np.ndarray, y: np.ndarray,
                   progress: Progress = None) -> EffectFit:
    """The fitted effect with its operator count chosen again (fit_gpi's rule); fit itself if unchanged."""
    t, u, y = check_record(t, u, y)
    return EFFECTS[fit.effect].recount(fit, t, u, y, progress)


def no_effect(t: np.ndarray, u: np.ndarray, y: np.ndarray, base: FitResult) -> EffectFit:
    """The plain GPI in the same form as the candidates (no extra parameter)."""
    t, u, y = check_record(t, u, y)
    return _finish("none", {}, base.parameters, base.operators, y, base.predicted, base.parameter_count,
                   time.perf_counter())
