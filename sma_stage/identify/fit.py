"""GPI identification: bounded nonlinear least squares (the paper's lsqnonlin; here a bounded
Levenberg-Marquardt, `levenberg_marquardt`) with an analytic Jacobian and variable projection of the
linear parameters.

The model has one exact scale symmetry: multiplying a1, a4, a5, a8, a9 by s and dividing a10, a11 by s
leaves the output unchanged. The search holds a1 fixed to remove it, and the result is reported in the
normalised form where the densities sum to 1 (so the envelopes are in the output's unit and scale), see
`normalized`. The output is linear in that normalised scale s and in any extra regressor columns, so
those are solved by linear least squares at every step and the search runs over the nonlinear
parameters only (Kaufman's approximation of the projected Jacobian).

The scale is bounded: s (a1 + a5 + a9 (n - 1)) <= SCALE_LIMIT output spans. Without the bound, data
that the exponential tail of a saturated tanh (or a nearly flat tanh) fits slightly better drove a1 and
a4 to huge opposite values (a1 = 1.1e11 on a 1 mm stroke was seen): the same output, but computed by a
cancellation that leaves rounding noise in it and extrapolates absurdly over the input range. With the
bound such shapes are fitted with tanh arguments a few units nearer zero, at a cost in error of order
exp(-2 x), x the argument given up. fit_gpi refuses (InputError) a result whose normalised parameters
still exceed the limits of scale_problems.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass, field

import numpy as np

from sma_stage.errors import InputError
from sma_stage.identify.cancel import report
from sma_stage.identify.checks import check_data, check_regressors
from sma_stage.identify.initial_guess import start_points
from sma_stage.identify.least_squares import TOLERANCE, levenberg_marquardt
from sma_stage.identify.metrics import ErrorMetrics, error_metrics
from sma_stage.identify.projection import (
    FREE_NAMES,
    HOLDABLE,
    OFFSET_LIMIT,
    SCALE_LIMIT,
    ProjectedProblem,
    free_start,
    search_bounds,
    theta_of,
)
from sma_stage.identify.uncertainty import standard_errors
from sma_stage.model.forward import forward
from sma_stage.model.parameters import DEFAULT_OPERATORS, GPIParameters, check_operators

OPERATOR_CANDIDATES = (5, 10, 15, 20, 25, 30)
OPERATOR_MARGIN = 0.02  # operators=None: smallest count whose RMS error is within 2 % of the best
DEFAULT_MAX_ITERATIONS = 200
SURVEY_SAMPLES = 1000  # every start runs SURVEY_STEPS steps on a thinned copy of about this size,
SURVEY_STEPS = 15
FINALISTS = 3  # the best few then converge on a thinned copy of about SCREEN_SAMPLES samples
SCREEN_SAMPLES = 3000
SCREEN_MAX_ITERATIONS = 100
PROFILE_TOLERANCE = 1e-7  # a fit that only compares costs at several values of an effect's parameter


@dataclass(frozen=True)
class FitResult:
    """A GPI fit: parameters (densities normalised to sum 1), standard errors, the fitted output and
    its error on the identification data, the cost (SSR [output unit^2]) and how the search went."""

    parameters: GPIParameters
    operators: int
    standard_errors: dict[str, float]
    regressor_coefficients: np.ndarray
    predicted: np.ndarray
    residual: np.ndarray
    identification: ErrorMetrics
    iterations: int
    seconds: float
    cost: float
    parameter_count: int
    success: bool
    message: str
    regressor_standard_errors: np.ndarray = field(default_factory=lambda: np.zeros(0))
    by_count: dict[int, GPIParameters] = field(default_factory=dict)  # operators None: each well-scaled count's fit

    @property
    def samples(self) -> int:
        """Number of samples fitted."""
        return int(self.residual.size)


def normalized(params: GPIParameters, operators: int) -> GPIParameters:
    """The same model (identical output) scaled so that its densities sum to 1."""
    total = float(np.sum(params.densities(operators)))
    if not math.isfinite(total) or total <= 0.0:
        return params
    return _scaled(params, total)


def _scaled(params: GPIParameters, s: float) -> GPIParameters:
    """The output-preserving rescaling: a1, a4, a5, a8, a9 times s; a10, a11 divided by s."""
    return params.replace(a1=params.a1 * s, a4=params.a4 * s, a5=params.a5 * s, a8=params.a8 * s,
                          a9=params.a9 * s, a10=params.a10 / s, a11=params.a11 / s)


def information_criterion(cost: float, samples: int, parameter_count: int, kind: str = "bic") -> float:
    """N log(SSR/N) + k * (2 for "aic", log N for "bic") for Gaussian errors (lower is better); SSR = cost
    [output unit^2], N samples, k parameters."""
    penalties = {"aic": 2.0, "bic": math.log(samples)}
    if kind not in penalties:
        raise InputError(f"information criterion must be 'aic' or 'bic', got {kind!r}")
    mean_square = max(cost / samples, np.finfo(float).tiny)
    return samples * math.log(mean_square) + parameter_count * penalties[kind]


def predict(result: FitResult, u: np.ndarray, regressors: np.ndarray | None = None,
            initial: np.ndarray | None = None) -> np.ndarray:
    """Model output [output unit] for a new input u [A] (e.g. validation data), with the fitted
    regressor coefficients applied to the given regressor columns."""
    output = forward(u, result.parameters, result.operators, initial)
    coefficients = result.regressor_coefficients
    if coefficients.size == 0:
        if regressors is not None and np.size(regressors):
            raise InputError("this fit has no regressors, but regressor columns were given")
        return output
    if regressors is None:
        raise InputError(f"this fit has {coefficients.size} regressor columns: give them to predict")
    return output + check_regressors(regressors, output.size, coefficients.size) @ coefficients


@dataclass
class _Search:
    x: np.ndarray
    a1: float
    cost: float
    iterations: int
    status: int
    message: str


def _search(u: np.ndarray, y: np.ndarray, regressors: np.ndarray, operators: int, start: GPIParameters,
            max_iterations: int, progress: Callable[[str], None] | None = None,
            tolerance: float = TOLERANCE, held: frozenset[str] = frozenset()) -> _Search:
    """Bounded Levenberg-Marquardt (levenberg_marquardt) from start, to tolerance or max_iterations evaluations;
    the parameters named in held (of HOLDABLE) stay at start's values."""
    return _converge(u, y, regressors, operators, start, max_iterations, tolerance, progress, held)


def _glance(u: np.ndarray, y: np.ndarray, regressors: np.ndarray, operators: int, start: GPIParameters,
            steps: int) -> _Search:
    """A few steps from start: a cheap look at where a start leads, for ranking starts."""
    return _converge(u, y, regressors, operators, start, steps + 1, 0.0)


def _converge(u: np.ndarray, y: np.ndarray, regressors: np.ndarray, operators: int, start: GPIParameters,
              evaluations: int, tolerance: float, progress: Callable[[str], None] | None = None,
              held: frozenset[str] = frozenset()) -> _Search:
    problem, a1, x0, low, high, free = _setup(u, y, regressors, operators, start, progress)
    free[[HOLDABLE.index(name) for name in held]] = False

    def full(z: np.ndarray) -> np.ndarray:
        x = x0.copy()
        x[free] = z
        return x

    solution = levenberg_marquardt(lambda z: problem.fun(full(z)), lambda z: problem.jac(full(z))[:, free],
                                   x0[free], (low[free], high[free]), evaluations, tolerance)
    return _Search(full(solution.x), a1, 2.0 * float(solution.cost), int(solution.nfev), int(solution.status),
                   str(solution.message))


def _setup(u: np.ndarray, y: np.ndarray, regressors: np.ndarray, operators: int, start: GPIParameters,
           progress: Callable[[str], None] | None = None) -> tuple:
    """(problem, held a1, start x inside the bounds, low, high, mask of the searched parameters)."""
    a1, x0 = free_start(start)
    low, high = search_bounds(u, y, a1, operators)
    span = high - low
    x0 = np.clip(x0, low + 1e-9 * span, high - 1e-9 * span)
    free = np.ones(x0.size, dtype=bool)
    if operators == 1:
        free[7:] = False  # one operator: r_0 = 0 and p_0 = a10, so a9 and a11 do nothing
    return ProjectedProblem(u, y, regressors, operators, a1, float(np.ptp(y)), progress), a1, x0, low, high, free


def _parameters(problem_a1: float, x: np.ndarray, a10: float, operators: int, unit: str) -> GPIParameters:
    theta = theta_of(problem_a1, x, a10)
    return normalized(GPIParameters.from_array(theta, output_unit=unit), operators)


def thinned(u: np.ndarray, budget: int) -> np.ndarray:
    """Indices of at most ~budget samples: the input's turning points (when there are few) and an even
    stride. Between kept turning points the input is monotone, so by rate independence the model's
    output at the kept samples is (nearly) unchanged."""
    if u.size <= budget:
        return np.arange(u.size)
    slope = np.diff(u)
    turning = np.flatnonzero(slope[:-1] * slope[1:] < 0.0) + 1
    if turning.size > budget // 2:
        turning = turning[:0]
    stride = math.ceil(u.size / (budget - turning.size))
    return np.union1d(np.union1d(np.arange(0, u.size, stride), turning), [u.size - 1])


def _survey(u: np.ndarray, y: np.ndarray, regressors: np.ndarray, operators: int,
            starts: Sequence[GPIParameters], progress: Callable[[str], None] | None) -> tuple[list[GPIParameters], int]:
    """Run every start SURVEY_STEPS steps on a small thinned copy; the best FINALISTS become the
    start points (and the iterations spent)."""
    if len(starts) == 1:
        return list(starts), 0
    survey = thinned(u, SURVEY_SAMPLES)
    surveyed = [_glance(u[survey], y[survey], regressors[survey], operators, start, SURVEY_STEPS)
                for start in starts]
    report(progress, f"{operators} operators: surveyed {len(starts)} starts on {survey.size} samples")
    finalists = sorted(surveyed, key=lambda found: found.cost)[:FINALISTS]
    return [_start_from(found) for found in finalists], sum(found.iterations for found in surveyed)


def _carried(starts: Sequence[GPIParameters], operators: int, new_operators: int) -> list[GPIParameters]:
    """Starts for another operator count: each with the same largest threshold, and as it is (the same
    threshold step)."""
    if new_operators == operators:
        return list(starts)
    ratio = max(operators - 1, 1) / max(new_operators - 1, 1)
    return [params.replace(a9=params.a9 * ratio) for params in starts] + list(starts)


def _starts(u: np.ndarray, y: np.ndarray, operators: int, starts: int | Sequence[GPIParameters] | None,
            unit: str) -> list[GPIParameters]:
    if starts is None:
        return start_points(u, y, operators, output_unit=unit)
    if isinstance(starts, (int, np.integer)) and not isinstance(starts, bool):
        if starts < 1:
            raise InputError(f"starts must be at least 1, got {starts}")
        return start_points(u, y, operators, int(starts), output_unit=unit)
    chosen = list(starts)
    if not chosen or not all(isinstance(s, GPIParameters) for s in chosen):
        raise InputError("starts must be a count or a non-empty sequence of GPIParameters")
    return chosen


def _fit_count(u: np.ndarray, y: np.ndarray, regressors: np.ndarray, operators: int,
               starts: Sequence[GPIParameters], max_iterations: int,
               progress: Callable[[str], None] | None, refine: bool = True,
               tolerance: float = TOLERANCE, held: frozenset[str] = frozenset()) -> tuple[_Search, int]:
    """Converge several starts on a thinned copy and refine the best on all samples (one start: straight
    to all samples); refine False: the best on the thinned copy (its cost on that copy), for comparing
    operator counts before only the chosen one is refined. Returns the search and the iterations spent."""
    screen = thinned(u, SCREEN_SAMPLES)
    whole = screen.size == u.size
    spent = 0
    start = starts[0]
    if len(starts) > 1:
        best = None
        for number, candidate in enumerate(starts, 1):
            found = _search(u[screen], y[screen], regressors[screen], operators, candidate,
                            max_iterations if whole else SCREEN_MAX_ITERATIONS, tolerance=tolerance, held=held)
            spent += found.iterations
            report(progress, f"{operators} operators, finalist {number}/{len(starts)} on {screen.size} "
                    f"samples: cost {found.cost:.6g}")
            if best is None or found.cost < best.cost:
                best = found
        if whole or not refine:
            return best, spent
        start = _start_from(best)
    found = _search(u, y, regressors, operators, start, max_iterations, progress, tolerance, held)
    report(progress, f"{operators} operators on {u.size} samples: cost {found.cost:.6g}, "
            f"{found.iterations} iterations")
    return found, spent + found.iterations


def _start_from(found: _Search) -> GPIParameters:
    """The parameters a search reached, in its own scale (a1 held, a10 a placeholder: it is projected)."""
    return GPIParameters.from_array(theta_of(found.a1, found.x))


def fit_gpi(u: np.ndarray, y: np.ndarray, operators: int | None = None, initial: GPIParameters | None = None,
            output_unit: str = "m", regressors: np.ndarray | None = None,
            starts: int | Sequence[GPIParameters] | None = None, max_iterations: int = DEFAULT_MAX_ITERATIONS,
            progress: Callable[[str], None] | None = None, tolerance: float = TOLERANCE,
            hold: Collection[str] = ()) -> FitResult:
    """Fit a1..a11 to input u [A] and output y [output_unit] (y ~ GPI(u) + regressors @ c).

    regressors: (N, m) columns entering linearly (e.g. time for a drift), solved with a10 at every
    step. A constant column duplicates a common shift of a4 and a8 (their standard errors and its own
    come out infinite); leave it out unless the envelope offsets are held some other way.

    operators None: each of OPERATOR_CANDIDATES is fitted and the smallest count whose RMS error is
    within OPERATOR_MARGIN of the best is kept (every count has the same parameter count, so an
    information criterion would just take the best). initial: a warm start (no multi-start).
    starts: how many data-derived starts to survey (default: all of initial_guess.start_points), or the
    start points themselves. The survey runs once (10 operators, or the given count); its best few
    starts, carried to each other count (same largest threshold; same threshold step), are converged
    on a thinned copy and the best is refined on all samples.

    tolerance: where each search stops (levenberg_marquardt's, relative); a looser one for a fit that
    only compares costs, e.g. PROFILE_TOLERANCE.

    hold: names among HOLDABLE (a2..a9) kept at initial's values (initial required; with operators None a
    held a9 is carried to each count as the same largest threshold), e.g. the envelopes' slopes a2, a6 where
    the data do not reach the envelopes' knees; their standard errors are 0 and they do not count as
    parameters.

    The normalised a1, a5 and largest threshold are held within SCALE_LIMIT output spans during the
    search; a count whose result still fails scale_problems is passed over (the message says so), and
    InputError is raised when every count fails.
    """
    matrix = check_regressors(regressors, np.size(u))
    u, y = check_data(u, y, matrix)
    if initial is not None and not isinstance(initial, GPIParameters):
        raise InputError(f"initial must be GPIParameters, got {type(initial).__name__}")
    held = _checked_hold(hold, initial)
    scale = float(np.ptp(y))
    if not math.isfinite(scale) or scale == 1.0:
        return _fit_gpi(u, y, operators, initial, output_unit, matrix, starts, max_iterations, progress, tolerance,
                        held)
    if isinstance(starts, Sequence):
        starts = [output_scaled(start, 1.0 / scale) if isinstance(start, GPIParameters) else start
                  for start in starts]
    initial = None if initial is None else output_scaled(initial, 1.0 / scale)
    found = _fit_gpi(u, y / scale, operators, initial, output_unit, matrix, starts, max_iterations, progress,
                     tolerance, held)
    return _output_scaled_result(found, scale, y)


def _checked_hold(hold: Collection[str], initial: GPIParameters | None) -> frozenset[str]:
    """fit_gpi's hold as a set; InputError for a name outside HOLDABLE or a hold without a warm start."""
    if isinstance(hold, str):
        hold = (hold,)
    held = frozenset(hold)
    unknown = sorted(held - set(HOLDABLE))
    if unknown:
        raise InputError(f"hold may name {', '.join(HOLDABLE)}; got {', '.join(map(str, unknown))}")
    if held and initial is None:
        raise InputError("hold keeps parameters at the warm start's values: give initial")
    return held


OUTPUT_SCALE_POWERS = {"a1": 1, "a4": 1, "a5": 1, "a8": 1, "a9": 1, "a11": -1}  # how each parameter scales with y


def output_scaled(params: GPIParameters, factor: float) -> GPIParameters:
    """The model whose output is `factor` times this one's: a1, a4, a5, a8 (the envelopes) and a9 (the
    thresholds) times factor, a11 divided by it, the others unchanged (OUTPUT_SCALE_POWERS)."""
    return params.replace(**{name: getattr(params, name) * factor**power for name, power in OUTPUT_SCALE_POWERS.items()})


def _output_scaled_result(found: FitResult, scale: float, y: np.ndarray) -> FitResult:
    """A fit made on y / scale, given back for y: parameters, errors and outputs in y's unit."""
    predicted = found.predicted * scale
    return dataclasses.replace(
        found, parameters=output_scaled(found.parameters, scale),
        standard_errors={name: error * scale ** OUTPUT_SCALE_POWERS.get(name, 0)
                         for name, error in found.standard_errors.items()},
        regressor_coefficients=found.regressor_coefficients * scale, predicted=predicted, residual=y - predicted,
        identification=error_metrics(y, predicted), cost=found.cost * scale**2,
        regressor_standard_errors=found.regressor_standard_errors * scale)


def _fit_gpi(u: np.ndarray, y: np.ndarray, operators: int | None, initial: GPIParameters | None, output_unit: str,
             matrix: np.ndarray, starts: int | Sequence[GPIParameters] | None, max_iterations: int,
             progress: Callable[[str], None] | None, tolerance: float = TOLERANCE,
             held: frozenset[str] = frozenset()) -> FitResult:
    """fit_gpi on checked data, y of any scale (fit_gpi gives it one of unit span)."""
    clock = time.perf_counter()
    if isinstance(max_iterations, bool) or not isinstance(max_iterations, (int, np.integer)) or max_iterations < 1:
        raise InputError(f"max_iterations must be a positive integer, got {max_iterations!r}")
    if isinstance(tolerance, bool) or not isinstance(tolerance, (float, int)) or not 0.0 < tolerance < 1.0:
        raise InputError(f"tolerance must be a number in (0, 1), got {tolerance!r}")
    counts = OPERATOR_CANDIDATES if operators is None else (check_operators(operators),)
    reference = DEFAULT_OPERATORS if DEFAULT_OPERATORS in counts else counts[0]
    if initial is None:
        finalists, iterations = _survey(u, y, matrix, reference, _starts(u, y, reference, starts, output_unit),
                                        progress)
    else:
        finalists, iterations, reference = [initial], 0, None
    fits = {}
    several = len(counts) > 1
    order = sorted(counts, key=lambda count: count != reference)  # the reference count first
    for count in order:
        if reference is None:
            count_starts = finalists
        elif count == reference or thinned(u, SCREEN_SAMPLES).size == u.size:
            count_starts = _carried(finalists, reference, count)
        else:  # a large record: the other counts start from where the reference count's finalists led
            count_starts = _carried([_start_from(fits[reference][0])], reference, count)
        fits[count] = _fit_count(u, y, matrix, count, count_starts, int(max_iterations), progress,
                                 refine=not several, tolerance=tolerance, held=held)
    fits = {count: fits[count] for count in counts}
    costs = {count: found.cost for count, (found, _) in fits.items()}
    searches = {count: found for count, (found, _) in fits.items()}
    chosen, params, coefficients, refused, by_count = _well_scaled_choice(u, y, matrix, searches, output_unit)
    found = fits[chosen][0]
    iterations += sum(spent for _, spent in fits.values())
    compared = thinned(u, SCREEN_SAMPLES).size if several else u.size  # the samples the counts were compared on
    if compared < u.size:
        found = _search(u, y, matrix, chosen, _start_from(found), int(max_iterations), progress, tolerance, held)
        iterations += found.iterations
        params, coefficients = _final_parameters(u, y, matrix, chosen, found, output_unit)
        if scale_problems(params, chosen, y):
            raise InputError(f"the fit found no well-scaled GPI parameters for these data ({chosen} operators: "
                             f"{', '.join(scale_problems(params, chosen, y))})")
    note = found.message
    if len(costs) > 1:
        rms = ", ".join(f"{count}: {100 * math.sqrt(cost / compared) / np.ptp(y):.4g}" for count, cost in costs.items())
        where = "" if compared == u.size else f" on a {compared}-sample thinned copy"
        note += f" Operators chosen: {chosen} (RMS % by count{where} {rms})."
    if refused:
        note += f" Refused as badly scaled: {' / '.join(refused)}."
    if held:
        note += f" Held at the warm start: {', '.join(sorted(held))}."
    result = _result(u, y, matrix, chosen, found, params, coefficients, iterations, time.perf_counter() - clock,
                     note, held)
    return dataclasses.replace(result, by_count=by_count) if len(counts) > 1 else result


def choose_operator_count(costs: dict[int, float]) -> int:
    """The operator-count rule: the smallest count whose RMS error is within OPERATOR_MARGIN of the best
    (costs: SSR by count, all on the same data)."""
    best = min(costs.values())
    return min(count for count, cost in costs.items() if math.sqrt(cost) <= (1 + OPERATOR_MARGIN) * math.sqrt(best))


def scale_problems(params: GPIParameters, operators: int, y: np.ndarray) -> list[str]:
    """Why normalised parameters are too large for the output y they were fitted to (empty when they are
    not): a1, a5 and the largest threshold beyond SCALE_LIMIT output spans, a4 or a8 beyond OFFSET_LIMIT
    spans from the output's mid-range (where gl or gr would be computed by cancellation)."""
    params = normalized(params, operators)
    span = float(np.ptp(y))
    middle = 0.5 * float(np.max(y) + np.min(y))
    sizes = {"a1": (abs(params.a1), SCALE_LIMIT), "a5": (abs(params.a5), SCALE_LIMIT),
             "a9*(n-1)": (params.a9 * (operators - 1), SCALE_LIMIT),
             "a4": (abs(params.a4 - middle), OFFSET_LIMIT), "a8": (abs(params.a8 - middle), OFFSET_LIMIT)}
    return [f"{name} is {size / span:.3g} output spans (limit {limit:g})"
            for name, (size, limit) in sizes.items() if not size <= limit * (1.0 + 1e-9) * span]


def _well_scaled_choice(u: np.ndarray, y: np.ndarray, regressors: np.ndarray, fits: dict[int, _Search],
                        unit: str) -> tuple[int, GPIParameters, np.ndarray, list[str], dict[int, GPIParameters]]:
    """The operator count by choose_operator_count among the fits whose parameters pass scale_problems; its
    normalised parameters and regressor coefficients; why the counts passed over were refused; every
    passing count's parameters. InputError when none passes."""
    costs = {count: found.cost for count, found in fits.items() if math.isfinite(found.cost)}
    refused = [f"{count} operators: the search ended on a non-finite cost" for count in fits if count not in costs]
    final = {count: _final_parameters(u, y, regressors, count, fits[count], unit) for count in costs}
    passing = {count: params for count, (params, _) in final.items() if not scale_problems(params, count, y)}
    while costs:
        chosen = choose_operator_count(costs)
        params, coefficients = final[chosen]
        problems = scale_problems(params, chosen, y)
        if not problems:
            return chosen, params, coefficients, refused, passing
        refused.append(f"{chosen} operators: {', '.join(problems)}")
        del costs[chosen]
    raise InputError(f"the fit found no well-scaled GPI parameters for these data ({' / '.join(refused)})")


def _final_parameters(u: np.ndarray, y: np.ndarray, regressors: np.ndarray, operators: int, found: _Search,
                      unit: str) -> tuple[GPIParameters, np.ndarray]:
    """Normalised parameters and regressor coefficients where the search ended."""
    problem = ProjectedProblem(u, y, regressors, operators, found.a1, float(np.ptp(y)))
    problem.fun(found.x)
    scale, coefficients = float(problem.coefficients[-1]), problem.coefficients[:-1].copy()
    a10 = scale / float(np.exp(-found.x[8] * np.arange(operators)).sum())
    return _parameters(found.a1, found.x, a10, operators, unit), coefficients


def _result(u: np.ndarray, y: np.ndarray, regressors: np.ndarray, operators: int, found: _Search,
            params: GPIParameters, coefficients: np.ndarray, iterations: int, seconds: float,
            message: str, held: frozenset[str] = frozenset()) -> FitResult:
    predicted = forward(u, params, operators) + regressors @ coefficients
    residual = y - predicted
    cost = float(residual @ residual)
    errors, regressor_errors = standard_errors(u, params, operators, regressors, cost, held)
    return FitResult(
        parameters=params, operators=operators, standard_errors=errors,
        regressor_coefficients=coefficients, predicted=predicted, residual=residual,
        identification=error_metrics(y, predicted), iterations=iterations, seconds=seconds, cost=cost,
        parameter_count=len(FREE_NAMES) + 1 - len(held) + regressors.shape[1], success=found.status > 0,
        message=message, regressor_standard_errors=regressor_errors,
    )


