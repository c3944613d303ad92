"""The shared base of the candidate effects: the fitted candidate (EffectFit), the Candidate interface,
and the machinery every effect's fit uses (GPI refits warm-started along a parameter, bounded scalar
searches, the operator-count rule over several fits).

Time t is in s (or samples for quasi-static data), u in A, y in the output unit (m). Every record starts
from an idle stage unless a start is given (see sma_stage.model.effects).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from scipy.optimize import minimize_scalar

from sma_stage.errors import InputError
from sma_stage.identify.cancel import Progress, report
from sma_stage.identify.fit import (
    PROFILE_TOLERANCE,
    TOLERANCE,
    FitResult,
    choose_operator_count,
    fit_gpi,
    information_criterion,
)
from sma_stage.identify.metrics import ErrorMetrics, error_metrics
from sma_stage.model.effects import Effect
from sma_stage.model.identified import IdentifiedModel, Start
from sma_stage.model.parameters import GPIParameters

SEARCH_GRID_POINTS = 6
LOG_TOLERANCE = 1e-3  # tolerance of the scalar searches on the log of the parameter (0.1 %)
COARSE_LOG_TOLERANCE = 5e-2  # tolerance of the thorough stage of a search (5 %)
LAG_RANGE_FRACTION = 0.1  # largest tau or delay, as a fraction of the record's duration
MIN_LAG_SAMPLES = 0.25  # smallest tau or delay, in sample periods: the samples do not resolve less
BOUND_MARGIN = 0.01  # a tau or delay found within 1 % of that bound is refused (not resolved)
FITTED_STARTS = ("rest", "held")  # how an identification record may start, tried by every input effect's fit
THOROUGH_STARTS = 2  # data-derived starts of the cold fit in a thorough evaluation
SEARCH_SAMPLES = 500  # the wide search of tau or d runs on a thinned copy of about this many samples
SCREEN_SAMPLES = 3000  # the fine search on one of about this many; the GPI is then refitted on all samples
NARROW_FACTOR = 1.1  # after a change of operator count, x is searched again within x / 1.1 .. 1.1 x
REFIT_FACTOR = 1.5  # backfitting searches x again within x / 1.5 .. 1.5 x (the other effects moved a little)

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
    start: str = "rest"

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

    def predict(self, t: np.ndarray, u: np.ndarray, start: str = "rest") -> np.ndarray:
        """Model output [output unit] for another record (time t [s], input u [A]) from rest or held."""
        t, u = check_record(t, u)
        return self.model.predict_from(t, u, Start(start))

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

# ---- fitting machinery ---------------------------------------------------------------------------


def fit_or_none(v: np.ndarray, y: np.ndarray, operators: int | None, initial: GPIParameters | None, unit: str,
                regressors: np.ndarray | None = None, starts: int | None = None,
                tolerance: float = TOLERANCE) -> FitResult | None:
    """fit_gpi, or None where the data cannot be fitted (e.g. a delay so long that the output falls as
    the input rises)."""
    result = attempt("GPI", lambda: fit_gpi(v, y, operators=operators, initial=initial, output_unit=unit,
                                            regressors=regressors, starts=starts, tolerance=tolerance))
    return None if isinstance(result, NotFitted) else result


def cold_fit(u: np.ndarray, y: np.ndarray, operators: int, unit: str, warm: FitResult | None,
             regressors: np.ndarray | None = None, tolerance: float = TOLERANCE) -> FitResult | None:
    """fit_gpi from THOROUGH_STARTS data-derived starts (None where it cannot be fitted). On a record longer
    than SCREEN_SAMPLES they run on a copy thinned to that many (their survey and finalists run on thinned
    copies anyway), and the best is polished on all samples only where it beats `warm` (a fit of the same
    data from elsewhere) on that copy; None where it does not. tolerance: fit_gpi's."""
    keep = even_indices(u.size, SCREEN_SAMPLES)
    if keep.size == u.size:
        return fit_or_none(u, y, operators, None, unit, regressors, THOROUGH_STARTS, tolerance)
    thinned_regressors = None if regressors is None else regressors[keep]
    cold = fit_or_none(u[keep], y[keep], operators, None, unit, thinned_regressors, THOROUGH_STARTS, tolerance)
    if cold is None:
        return None
    if warm is not None:
        residual = y[keep] - warm.predicted[keep]
        if float(residual @ residual) <= cold.cost:
            return None
    return fit_or_none(u, y, operators, cold.parameters, unit, regressors, tolerance=tolerance)


def pick(fits: Sequence) -> object:
    """fit_gpi's operator-count rule (choose_operator_count) over fits of several counts (anything with
    .cost and .operators; None for one that failed); of the count chosen, the lowest cost. The first fit
    must exist (the one the others are compared with)."""
    found = [fit for fit in fits if fit is not None and math.isfinite(fit.cost)]
    costs: dict[int, float] = {}
    for fit in found:
        costs[fit.operators] = min(fit.cost, costs.get(fit.operators, math.inf))
    count = choose_operator_count(costs)
    return lowest_cost(fit for fit in found if fit.operators == count)


class Refits:
    """GPI fits (one operator count) on a transformed input u_of(x), x the effect parameter. Each is
    warm-started from the fit at the nearest x so far (the optimum moves smoothly with x) and, when
    thorough, also from fit_gpi's data-derived starts (a start far away can sit in the basin where the
    plain GPI absorbed the effect); the lower cost is kept. The fits behind `cost` only compare costs along x:
    they stop at PROFILE_TOLERANCE, a fit asked for at the fit's own TOLERANCE."""

    def __init__(self, u_of: Callable[[float], np.ndarray], y: np.ndarray, base: FitResult) -> None:
        self.u_of, self.y, self.base = u_of, y, base
        self.fits: dict[float, FitResult | None] = {}

    def fit(self, value: float, thorough: bool = False, tolerance: float = TOLERANCE) -> FitResult | None:
        """The best fit found at this x (None if it cannot be fitted); one found before unless thorough."""
        if value not in self.fits or thorough:
            u, count, unit = self.u_of(value), self.base.operators, self.base.parameters.output_unit
            warm = fit_or_none(u, self.y, count, self._nearest(value).parameters, unit, tolerance=tolerance)
            tries = [self.fits.get(value), warm]
            if thorough:
                tries.append(cold_fit(u, self.y, count, unit, warm, tolerance=tolerance))
            self.fits[value] = lowest_cost(tries)
        return self.fits[value]

    def cost(self, log_value: float, thorough: bool = False) -> float:
        """SSR of the fit at exp(log_value) (inf where it cannot be fitted)."""
        result = self.fit(math.exp(log_value), thorough, PROFILE_TOLERANCE)
        return math.inf if result is None else float(result.cost)

    def _nearest(self, value: float) -> FitResult:
        fitted = [(abs(math.log(key / value)), fit) for key, fit in self.fits.items() if fit is not None]
        return min(fitted, key=lambda pair: pair[0])[1] if fitted else self.base


def scalar_search(cost: Callable[[float, bool], float], low: float, high: float, grid_points: int,
                   thorough: bool = True) -> float:
    """The log x in [log low, log high] of least cost(log x, thorough): a log-spaced grid, then a bounded
    Brent search between the best grid point's neighbours (to COARSE_LOG_TOLERANCE when thorough, else
    to LOG_TOLERANCE). The GPI fit has local minima, so a wide search needs thorough grid evaluations: a
    local polish alone stops where the plain GPI absorbed the effect."""
    grid = np.linspace(math.log(low), math.log(high), grid_points)
    costs = [cost(x, thorough) for x in grid]
    best = int(np.argmin(costs))
    x, fun = _brent(lambda x: cost(x, thorough), grid[max(best - 1, 0)], grid[min(best + 1, grid.size - 1)],
                    COARSE_LOG_TOLERANCE if thorough else LOG_TOLERANCE)
    return float(x) if fun <= costs[best] else float(grid[best])


def fine_search(cost: Callable[[float, bool], float], log_value: float, low: float, high: float) -> float:
    """A quick Brent search (warm starts only) to LOG_TOLERANCE within 2 COARSE_LOG_TOLERANCE of log_value."""
    margin = 2.0 * COARSE_LOG_TOLERANCE
    x, fun = _brent(lambda z: cost(z, False), max(log_value - margin, math.log(low)),
                    min(log_value + margin, math.log(high)), LOG_TOLERANCE)
    return x if fun < cost(log_value, False) else log_value


def _brent(cost: Callable[[float], float], left: float, right: float, tolerance: float) -> tuple[float, float]:
    found = minimize_scalar(cost, bounds=(left, right), method="bounded", options={"xatol": tolerance})
    return float(found.x), float(found.fun)


def finish_fit(effect: str, values: dict[str, float], gpi: GPIParameters, operators: int, y: np.ndarray,
               predicted: np.ndarray, parameter_count: int, started: float, start: str = "rest") -> EffectFit:
    residual = y - predicted
    return EffectFit(
        effect=effect, parameters=values, gpi_parameters=gpi, operators=int(operators),
        identification=error_metrics(y, predicted), cost=float(residual @ residual), samples=int(y.size),
        parameter_count=int(parameter_count), seconds=time.perf_counter() - started, start=start,
    )


class Candidate:
    """A candidate effect: `fit` from the base GPI fit (its operator count), the record starting as one
    of `starts` says (an effect without a state of its own starts the same from each); `recount` to
    choose the operator count again for the model with the effect."""

    name = ""
    relative_cost = 1.0  # about how many seconds its fit takes on 20,000 samples (bench_diagnosis): the
    # costliest candidates go to the worker processes first, so that a round ends sooner

    def fit(self, t: np.ndarray, u: np.ndarray, y: np.ndarray, base: FitResult, progress: Progress = None,
            starts: tuple[str, ...] = FITTED_STARTS) -> EffectFit:
        raise NotImplementedError

    def recount(self, fit: EffectFit, t: np.ndarray, u: np.ndarray, y: np.ndarray,
                progress: Progress = None) -> EffectFit:
        raise NotImplementedError

    def refit(self, fit: EffectFit, t: np.ndarray, u: np.ndarray, y: np.ndarray, base: FitResult,
              progress: Progress = None) -> EffectFit:
        """The effect fitted again on other data (the record less the other effects, after they changed:
        backfitting), from base and from where `fit` was, the record starting as fit's did. By default
        the whole fit; an effect that can search near its last values does."""
        return self.fit(t, u, y, base, progress, (fit.start,))


class InputTransformEffect(Candidate):
    """The GPI driven by what an input effect makes of the current, the effect `spec_of(x)` with one
    parameter x [s] found by a bounded search over log x, the GPI refitted at every x. The record's start
    is one of `starts` (rest, held: see sma_stage.model.identified.Start): the wide search runs from
    each, and the search goes on from the one that fits best."""

    def __init__(self, name: str, parameter: str, spec_of: Callable[[float], Effect], relative_cost: float = 1.0):
        self.name, self.parameter, self.spec_of = name, parameter, spec_of
        self.relative_cost = relative_cost

    def transform(self, t: np.ndarray, u: np.ndarray, value: float, start: str) -> np.ndarray:
        """What the GPI sees [A] at x = value, the record starting as `start` says."""
        spec = self.spec_of(value)
        return spec.transform(t, u, spec.start_state(t, u, start))[0]

    def fit(self, t: np.ndarray, u: np.ndarray, y: np.ndarray, base: FitResult, progress: Progress = None,
            starts: tuple[str, ...] = FITTED_STARTS) -> EffectFit:
        started = time.perf_counter()
        bounds = lag_range(t)
        keep = even_indices(t.size)
        searched = []
        for start in distinct_starts(u, starts):
            wide = Refits(lambda x, start=start: self.transform(t[keep], u[keep], x, start), y[keep], base)
            log_value = scalar_search(wide.cost, *bounds, SEARCH_GRID_POINTS)
            searched.append((wide.cost(log_value), start, log_value, wide.fit(math.exp(log_value)) or base))
        _, start, log_value, found = min(searched, key=lambda entry: entry[0])
        screen = even_indices(t.size, SCREEN_SAMPLES)
        fits = Refits(lambda x: self.transform(t[screen], u[screen], x, start), y[screen], found)
        value = math.exp(fine_search(fits.cost, log_value, *bounds))
        if value <= (1.0 + BOUND_MARGIN) * bounds[0]:
            raise NotFitted(f"{self.name}: {self.parameter} = {value:.4g} is at the search's lower bound "
                            f"({MIN_LAG_SAMPLES:g} of a sample period): the samples do not resolve it")
        if screen.size < t.size:
            fits = Refits(lambda x: self.transform(t, u, x, start), y, fits.fit(value) or found)
        gpi = fits.fit(value, thorough=True)
        return self._finish(value, gpi, y, base.parameter_count + 1, started, progress, start)

    def recount(self, fit: EffectFit, t: np.ndarray, u: np.ndarray, y: np.ndarray,
                progress: Progress = None) -> EffectFit:
        started = time.perf_counter()
        value = fit.parameters[self.parameter]
        counted = fit_or_none(self.transform(t, u, value, fit.start), y, None, None, fit.gpi_parameters.output_unit,
                              starts=THOROUGH_STARTS)
        if counted is None or pick([fit, counted]) is fit:
            return fit
        fits = Refits(lambda x: self.transform(t, u, x, fit.start), y, counted)
        fits.fits[value] = counted
        low, high = lag_range(t)
        narrow = (max(value / NARROW_FACTOR, low), min(value * NARROW_FACTOR, high))
        value = math.exp(scalar_search(fits.cost, *narrow, 3, thorough=False))
        return self._finish(value, fits.fit(value, thorough=True), y, fit.parameter_count, started, progress,
                            fit.start)

    def refit(self, fit: EffectFit, t: np.ndarray, u: np.ndarray, y: np.ndarray, base: FitResult,
              progress: Progress = None) -> EffectFit:
        """x searched again within x / REFIT_FACTOR .. REFIT_FACTOR x on the SCREEN_SAMPLES copy (warm fits
        from base), the GPI then refitted on all samples (thorough)."""
        started = time.perf_counter()
        low, high = lag_range(t)
        value = fit.parameters[self.parameter]
        screen = even_indices(t.size, SCREEN_SAMPLES)
        fits = Refits(lambda x: self.transform(t[screen], u[screen], x, fit.start), y[screen], base)
        narrow = (max(value / REFIT_FACTOR, low), min(value * REFIT_FACTOR, high))
        value = math.exp(scalar_search(fits.cost, *narrow, 3, thorough=False))
        if screen.size < t.size:
            fits = Refits(lambda x: self.transform(t, u, x, fit.start), y, fits.fit(value) or base)
        return self._finish(value, fits.fit(value, thorough=True), y, fit.parameter_count, started, progress,
                            fit.start)

    def _finish(self, value: float, gpi: FitResult | None, y: np.ndarray, parameter_count: int, started: float,
                progress: Progress, start: str) -> EffectFit:
        if gpi is None:
            raise NotFitted(f"{self.name}: the GPI cannot be fitted at {self.parameter} = {value:.4g}")
        report(progress, f"{self.name}: {self.parameter} = {value:.4g}, {gpi.operators} operators, "
                         f"record from {start}")
        return finish_fit(self.name, dict(self.spec_of(value).parameters), gpi.parameters, gpi.operators, y,
                          gpi.predicted, parameter_count, started, start)


def distinct_starts(u: np.ndarray, starts: tuple[str, ...]) -> tuple[str, ...]:
    """The starts that give an input effect different inputs for this record (held is rest when u[0] is 0)."""
    return starts[:1] if len(starts) > 1 and u[0] == 0.0 else starts


def even_indices(samples: int, budget: int = SEARCH_SAMPLES) -> np.ndarray:
    """Indices of an evenly thinned copy of at most about `budget` samples (the record on that coarser grid
    is what the searches fit: the wide one on SEARCH_SAMPLES, the fine one on SCREEN_SAMPLES)."""
    return np.arange(0, samples, max(1, round(samples / budget)))


def lag_range(t: np.ndarray) -> tuple[float, float]:
    """Bounds [s] of a lag or delay search: MIN_LAG_SAMPLES of a sample period to a tenth of the record."""
    step = float(np.median(np.diff(t)))
    return MIN_LAG_SAMPLES * step, max(LAG_RANGE_FRACTION * float(t[-1] - t[0]), step)


