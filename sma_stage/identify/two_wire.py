"""Identification of the two-wire model (sma_stage.model.two_wire) from a record: bounded nonlinear least
squares (scipy's trust-region reflective) on the output error, from several starts searched on a thinned copy of
the record, the best polished on all of it. Plain arrays in, a result object out.

The tension coupling (each wire's transformation shifted by the other's transformed share) is judged like a
diagnosis's effect: with a held-out record the starts are searched again with it free and each leader without
it polished again from COUPLED_START, and the best of those is kept when it lowers the BIC and the held-out RMS
error by the diagnosis's first-round margins (diagnosis.judge), on the held-out record it predicts worst where
there are several (HeldOut.others); without one it stays at 0.

`shapes`: "shared" (the default) gives both wires one transformation shape (width, hysteresis width, weights),
each wire keeping its own time constant, centre, coupling and stroke; "per_wire" frees them all. Per-wire shapes
predict the stage simulator better and the second physical stage worse in its worst records
(docs/families.md gives the figures).

`onset`: "tanh" (the default) or "compact", the shape of each wire's transformation curve (compact_onset in
sma_stage.model.two_wire), set for the fit, not fitted; the `two_wire_compact` family fits the compact one.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares

from sma_stage.errors import InputError
from sma_stage.identify._two_wire_sensitivity import rest_with_sensitivities, run_with_sensitivities
from sma_stage.identify.cancel import check_cancelled
from sma_stage.identify.checks import check_data
from sma_stage.identify.counts import COUNT_FIT_MARGIN
from sma_stage.identify.diagnosis import judge
from sma_stage.identify.fit import information_criterion
from sma_stage.identify.metrics import ErrorMetrics, error_metrics, worst
from sma_stage.identify.workers import Pending, Workers
from sma_stage.model.checks import checked_record
from sma_stage.model.two_wire import FIXED, ONSETS, SCALARS, TwoWireModel, TwoWireParameters

WIRE_OPERATORS = 4
OUTPUT_OPERATORS = 5
STARTS = 6
POLISHED = 2  # the best starts polished on more samples (with a held-out record, the best fit and this many more)
SEARCH_SAMPLES = 2500  # the starts run on a copy thinned to about this many samples
POLISH_SAMPLES = 10_000  # the best starts are polished on a copy thinned to at most this many
SEARCH_EVALUATIONS = 1500
POLISH_EVALUATIONS = 1500
DEFAULT_TOLERANCE = 1e-8  # scipy's: the polish of the leaders
SEARCH_TOLERANCE = 1e-4  # the search only ranks the starts; the leaders' polish converges
STALL_ITERATIONS = 100  # a run stops when its RMS error fell by less than STALL_FRACTION over this many iterations:
STALL_FRACTION = 0.005  # a crawl (a record no two-wire model fits) that no choice between fits would notice
START_FIT_MARGIN = COUNT_FIT_MARGIN  # with a held-out record: starts whose RMS error on the record is within this
# (relative) of the best are told apart there, as the GPI's operator counts are (the record does not tell them apart)
MIN_HEATED_SAMPLES = 10  # each wire must be heated in at least this many samples
TAU_RANGE_S = (0.05, 500.0)
RESISTANCE_DROP_RANGE = (0.0, 0.9)  # NiTi's resistance falls by about a fifth from martensite to austenite
RESISTANCE_DROP_START = (0.05, 0.3)
TENSION_COUPLING_RANGE = 2.0  # the tension coupling's bound, times the heating reference
TENSION_COUPLING_START = (0.0, 0.3)  # its random starts, times the heating reference
COUPLED_START = 0.1  # and where the polish from each leader without it starts


@dataclass(frozen=True)
class TwoWireFit:
    """A fitted two-wire model, its prediction of the record [output unit], its errors, the residual sum of
    squares `cost` [output unit^2], the BIC, the evaluations spent and the seconds taken."""

    model: TwoWireModel
    predicted: np.ndarray
    errors: ErrorMetrics
    cost: float
    bic: float
    evaluations: int
    seconds: float
    parameter_count: int  # free parameters fitted (shared shapes count once)
    admitted: int = 0  # starts that fitted within START_FIT_MARGIN of the best, the held-out error chose among (0: none;
    # counted without the tension coupling)
    tension: str = ""  # why the tension coupling was kept or left at 0 ("": not judged, no held-out record)


def fit_two_wire(t: np.ndarray, u: np.ndarray, y: np.ndarray, wire_operators: int = WIRE_OPERATORS,
                 output_operators: int = OUTPUT_OPERATORS, starts: int = STARTS, seed: int = 0,
                 output_unit: str = "m", shapes: str = "shared", pool: Workers | None = None,
                 held_out: HeldOut | None = None, onset: str = "tanh") -> TwoWireFit:
    """The two-wire model that best predicts y [output unit] from u [A] at times t [s], the record starting
    from a stage at rest. InputError (one line) when the record cannot identify it. pool: its processes search
    the starts and polish the leaders at once (the result is the same without). held_out: a record the starts
    that fit within START_FIT_MARGIN of the best are told apart on, and the tension coupling judged on
    (TwoWireFitting.result). onset: the transformation curve's shape (ONSETS)."""
    return TwoWireFitting(t, u, y, wire_operators, output_operators, starts, seed, output_unit, shapes, pool,
                          held_out, onset).result()


@dataclass(frozen=True)
class HeldOut:
    """Records to choose between fits on: times [s], input [A], output [output unit], run from a stage at rest,
    its errors counted from sample `scored_from`; `others`, further (t, u, y) records scored whole, each from rest.
    A fit is scored on the record it predicts worst, as the diagnosis judges an effect (chain.Validation)."""

    t: np.ndarray
    u: np.ndarray
    y: np.ndarray
    scored_from: int = 0
    others: tuple[tuple[np.ndarray, np.ndarray, np.ndarray], ...] = ()

    def errors(self, model: TwoWireModel) -> ErrorMetrics:
        """The model's errors on the record it predicts worst (the largest RMS % of the record's span)."""
        errors = [error_metrics(self.y[self.scored_from:], model.predict(self.t, self.u)[self.scored_from:])]
        errors += [error_metrics(y, model.predict(t, u)) for t, u, y in self.others]
        return worst(errors)

    def rms_pct(self, model: TwoWireModel) -> float:
        """The model's RMS error on the record it predicts worst [% of its span]."""
        return self.errors(model).rms_pct


class TwoWireFitting:
    """A two-wire fit under way (fit_two_wire's arguments): the record checked and the starts submitted to the
    pool's processes when it is made (with a held-out record, the starts with the tension coupling free too), so
    that other work goes on meanwhile; `result()` waits for them, polishes the leaders and gives the
    TwoWireFit."""

    def __init__(self, t: np.ndarray, u: np.ndarray, y: np.ndarray, wire_operators: int = WIRE_OPERATORS,
                 output_operators: int = OUTPUT_OPERATORS, starts: int = STARTS, seed: int = 0,
                 output_unit: str = "m", shapes: str = "shared", pool: Workers | None = None,
                 held_out: HeldOut | None = None, onset: str = "tanh") -> None:
        self.started = time.perf_counter()
        if onset not in ONSETS:
            raise InputError(f"onset must be one of {', '.join(ONSETS)}, got {onset!r}")
        compact = onset == "compact"
        t, u = checked_record(t, u)
        u, y = check_data(u, y)
        for name, count in (("wire_operators", wire_operators), ("output_operators", output_operators),
                            ("starts", starts)):
            if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or not 1 <= count <= 50:
                raise InputError(f"{name} must be an integer from 1 to 50, got {count!r}")
        for wire, heated in (("a (u > 0)", u > 0.0), ("b (u < 0)", u < 0.0)):
            if np.count_nonzero(heated) < MIN_HEATED_SAMPLES:
                raise InputError(f"the two-wire model needs both wires heated: wire {wire} is heated in "
                                 f"{np.count_nonzero(heated)} samples (at least {MIN_HEATED_SAMPLES})")
        self.t, self.u, self.y, self.output_unit, self.shapes, self.held_out = t, u, y, output_unit, shapes, held_out
        self.pool = pool or Workers()
        fine = -(-t.size // POLISH_SAMPLES)
        self.problem = _Problem(t[::fine], u[::fine], y[::fine], wire_operators, output_operators, shapes,
                                compact=compact)
        thin = max(1, t.size // SEARCH_SAMPLES)
        self.search = _Problem(t[::thin], u[::thin], y[::thin], wire_operators, output_operators,
                               shapes, compact=compact) if thin > fine else self.problem
        self.coupled = _Problem(self.problem.t, self.problem.u, self.problem.y, wire_operators, output_operators,
                                shapes, tension=True, compact=compact)
        self.coupled_search = _Problem(self.search.t, self.search.u, self.search.y, wire_operators,
                                       output_operators, shapes, tension=True, compact=compact)
        self.starts, self.seed = starts, seed
        self.searching = self._search(self.search)
        self._coupled_searching = self._search(self.coupled_search) if held_out is not None else []
        self._polishing: list[Pending] | None = None
        self._coupled_polishing: list[Pending] = []
        self._searched_evaluations, self._admitted = 0, []

    def _search(self, problem: _Problem) -> list[Pending]:
        """The starts' searches of a problem, handed to the pool (the same starts for a seed)."""
        rng = np.random.default_rng(self.seed)
        return [self.pool.submit(_solve, problem, problem.random_start(rng), SEARCH_EVALUATIONS, SEARCH_TOLERANCE)
                for _ in range(self.starts)]

    def polish(self) -> None:
        """Wait for the starts and hand the polish of the leaders to the pool (once; `result` does it when it was
        not done): the POLISHED best fits, or with a held-out record the best fit and the POLISHED other starts
        within START_FIT_MARGIN of it that predict it best (so too of the starts with the tension coupling)."""
        if self._polishing is not None:
            return
        searched = _finished(self.searching, "start's search")
        leaders, self._admitted = self._leaders(searched, self.search)
        self._searched_evaluations = sum(found.nfev for found in searched)
        self._polishing = [self.pool.submit(_solve, self.problem, found.x, POLISH_EVALUATIONS, DEFAULT_TOLERANCE)
                           for found in leaders]
        if self._coupled_searching:
            coupled_searched = _ranked(self._coupled_searching)
            self._searched_evaluations += sum(found.nfev for found in coupled_searched)
            starts = [found.x for found in self._leaders(coupled_searched, self.coupled_search)[0]
                      ] if coupled_searched else []
            starts += [self.coupled.coupled_start(self.search, found.x) for found in leaders]
            self._coupled_polishing = [self.pool.submit(_solve, self.coupled, start, POLISH_EVALUATIONS,
                                                        DEFAULT_TOLERANCE) for start in starts]

    def _leaders(self, searched: list, problem: _Problem) -> tuple[list, list]:
        """The searched starts (ranked by cost) to polish and those admitted (within START_FIT_MARGIN of the
        best; none without a held-out record)."""
        if self.held_out is None:
            return searched[:POLISHED], []
        admitted = _admitted(searched)
        return searched[:1] + sorted(admitted[1:], key=_held_out_error(self.held_out, problem))[:POLISHED], admitted

    def result(self) -> TwoWireFit:
        """The fitted model: the polished leaders (`polish`) and the best of them kept; with a held-out record,
        of those still within START_FIT_MARGIN of the best fit, the one that predicts it best, and the same of
        the fits with the tension coupling kept instead when it passes the diagnosis's rule there (judge)."""
        self.polish()
        held_out = self.held_out
        polishing, evaluations, admitted = self._polishing, self._searched_evaluations, self._admitted
        leaders = _finished(polishing, "leader's polish")
        evaluations += sum(found.nfev for found in leaders)
        best = leaders[0]
        if held_out is not None:
            best = min(_admitted(leaders), key=_held_out_error(held_out, self.problem))
        fitted, tension = self._fitted(self.problem, best), ""
        coupled = _ranked(self._coupled_polishing)
        if coupled:
            evaluations += sum(found.nfev for found in coupled)
            candidate = self._fitted(self.coupled, min(_admitted(coupled), key=_held_out_error(held_out, self.coupled)))
            kept, reason = judge(candidate.bic - fitted.bic, held_out.errors(candidate.model),
                                 held_out.errors(fitted.model))
            tension = f"tension coupling {'kept' if kept else 'left at 0'}: {reason}"
            fitted = candidate if kept else fitted
        elif held_out is not None:
            tension = "tension coupling left at 0: every fit with it met values that are not finite"
        return replace(fitted, evaluations=evaluations, seconds=time.perf_counter() - self.started,
                       admitted=len(admitted), tension=tension)

    def _fitted(self, problem: _Problem, found: object) -> TwoWireFit:
        """The TwoWireFit of a least-squares result of `problem`, run on the whole record (its evaluations and
        seconds left to the caller)."""
        t, u, y = self.t, self.u, self.y
        model = TwoWireModel(problem.parameters(found.x), self.output_unit)
        predicted, end = model.run(t, u)
        cost = float(np.sum((predicted - y) ** 2))
        count = problem.tie.shape[1]
        model = TwoWireModel(model.parameters, self.output_unit, end,
                             {"identified_samples": int(t.size), "shapes": self.shapes})
        return TwoWireFit(model, predicted, error_metrics(y, predicted), cost,
                          information_criterion(cost, t.size, count), 0, 0.0, count)


def _held_out_error(held_out: HeldOut, problem: _Problem) -> Callable[[object], float]:
    """A least-squares result's RMS error on held_out [% of its span], as the model `problem` makes of it."""
    return lambda found: held_out.rms_pct(TwoWireModel(problem.parameters(found.x)))


def _admitted(ranked: list) -> list:
    """The least-squares results (ranked by cost) whose RMS error is within START_FIT_MARGIN of the first's."""
    return [found for found in ranked if found.cost <= ranked[0].cost * (1.0 + START_FIT_MARGIN) ** 2]


def _solve(problem: _Problem, start: np.ndarray, evaluations: int, tolerance: float) -> object | None:
    """One least-squares run of the problem from a start (a job of the pool's processes); None when the run met
    values that are not finite (a start whose model overflows: scipy refuses the Jacobian)."""
    try:
        # scipy's step search overflows where its trust region is tiny (cubed damping terms): warnings no user can
        # act on; a run it leaves at values that are not finite is dropped below
        with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
            found = problem.solve(start, evaluations, tolerance)
    except (ValueError, np.linalg.LinAlgError):
        return None
    return found if np.isfinite(found.cost) and np.all(np.isfinite(found.x)) else None


def _finished(pending: list[Pending], what: str) -> list:
    """The least-squares results of the runs that finished, ranked by cost; InputError when none did."""
    found = _ranked(pending)
    if not found:
        raise InputError(f"the two-wire fit failed: every {what} met values that are not finite")
    return found


def _ranked(pending: list[Pending]) -> list:
    """The least-squares results of the runs that finished (none may have), ranked by cost."""
    return sorted((result for result in (job.result() for job in pending) if result is not None),
                  key=lambda result: result.cost)


SHAPES = ("per_wire", "shared")  # each wire its own transformation shape, or one shape for both


FULL_NAMES = [name for name in SCALARS if name not in FIXED]  # the full vector's scalars (those fitted)


def _tie(wire_operators: int, output_operators: int, shapes: str, tension: bool = False) -> np.ndarray:
    """The 0/1 matrix that spreads the free parameters over the full vector (FULL_NAMES, then the weights):
    `shared` ties the wires' widths, hysteresis widths and weights; without `tension` the tension coupling has
    no column (it is 0)."""
    if shapes not in SHAPES:
        raise InputError(f"shapes must be one of {', '.join(SHAPES)}, got {shapes!r}")
    full = FULL_NAMES + [f"weights_a[{j}]" for j in range(wire_operators)] + [f"weights_b[{j}]" for j in
                                                                              range(wire_operators)]
    full += [f"output_weights[{k}]" for k in range(output_operators)]

    def group(name: str) -> str:
        if shapes == "shared" and (name.startswith(("width_", "hysteresis_", "weights_"))):
            return name.replace("_a", "_*").replace("_b", "_*")
        return name

    fitted = [name for name in full if tension or name != "tension_coupling"]
    groups = list(dict.fromkeys(group(name) for name in fitted))
    tie = np.zeros((len(full), len(groups)))
    for row, name in enumerate(full):
        if name in fitted:
            tie[row, groups.index(group(name))] = 1.0
    return tie


class _Problem:
    """The least-squares problem over the free parameters (the heating reference fixed at the record's largest
    current, the onset's shape at `compact`), residuals in units of the output's span."""

    def __init__(self, t: np.ndarray, u: np.ndarray, y: np.ndarray, wire_operators: int,
                 output_operators: int, shapes: str = "per_wire", tension: bool = False, compact: bool = False) -> None:
        self.t, self.u, self.y = t, u, y
        self.n, self.m = wire_operators, output_operators
        self.reference = float(np.max(np.abs(u)))
        self.span = float(np.ptp(y))
        self.tension = tension
        self.fixed = {"heating_reference_a": self.reference, "compact_onset": 1.0 if compact else 0.0}
        self.tie = _tie(wire_operators, output_operators, shapes, tension)
        fixed_at = [SCALARS.index(name) for name in FIXED]
        self._fitted = np.array([c for c in range(self.tie.shape[0] + len(FIXED)) if c not in fixed_at])
        first = self.tie.argmax(axis=0)  # each free parameter's first place in the full vector
        last = self.tie.shape[0] - 1 - self.tie[::-1].argmax(axis=0)  # and its last (the same unless tied)
        self._kernel_first, self._tied = self._fitted[first], np.flatnonzero(last != first)
        self._kernel_last = self._fitted[last[self._tied]]
        low, high = self._bounds()
        self.low, self.high = low[first], high[first]

    def _bounds(self) -> tuple[np.ndarray, np.ndarray]:
        reference, span, level = self.reference, self.span, float(np.max(np.abs(self.y)))
        coupling = 50.0 * reference / span
        scalars = {"tau_a_s": TAU_RANGE_S, "tau_b_s": TAU_RANGE_S, "coupling_a": (-coupling, coupling),
                   "coupling_b": (-coupling, coupling), "centre_a": (-reference, 2.0 * reference),
                   "centre_b": (-reference, 2.0 * reference), "width_a": (0.005 * reference, reference),
                   "width_b": (0.005 * reference, reference), "hysteresis_a": (0.0, reference),
                   "hysteresis_b": (0.0, reference), "stroke_a": (0.0, 3.0 * span), "stroke_b": (0.0, 3.0 * span),
                   "offset": (-level - span, level + span), "output_threshold": (0.0, span),
                   "resistance_drop": RESISTANCE_DROP_RANGE,
                   "tension_coupling": (0.0, TENSION_COUPLING_RANGE * reference)}
        weights = 2 * self.n + self.m
        low = np.r_[[scalars[name][0] for name in FULL_NAMES], np.zeros(weights)]
        high = np.r_[[scalars[name][1] for name in FULL_NAMES], np.full(weights, 3.0)]
        return low, high

    def random_start(self, rng: np.random.Generator) -> np.ndarray:
        """A start inside the bounds: both wires alike, transformation mid-range, no coupling to begin with."""
        reference, span = self.reference, self.span
        pair = lambda low, high: np.full(2, rng.uniform(low, high))  # noqa: E731 -- both wires alike
        start = np.r_[pair(2.0, 20.0), rng.uniform(-1.0, 1.0, 2) * reference / span, pair(0.3, 0.8) * reference,
                      pair(0.05, 0.2) * reference, pair(0.05, 0.3) * reference, np.full(2, span / 2.0),
                      float(np.mean(self.y)) - 0.0, rng.uniform(0.01, 0.2) * span,
                      rng.uniform(*RESISTANCE_DROP_START),
                      rng.uniform(*TENSION_COUPLING_START) * reference if self.tension else 0.0,
                      np.full(2 * self.n, 1.0 / self.n), np.full(self.m, 1.0 / self.m)]
        return self._inside(start)

    def coupled_start(self, source: _Problem, free: np.ndarray) -> np.ndarray:
        """A start for this problem from a solution `free` of `source` (the model without the tension coupling),
        the coupling at COUPLED_START times the heating reference."""
        full = source.tie @ free
        full[FULL_NAMES.index("tension_coupling")] = COUPLED_START * self.reference
        return self._inside(full)

    def _inside(self, full: np.ndarray) -> np.ndarray:
        """The free parameters of a full vector, moved just inside the bounds."""
        start = full[self.tie.argmax(axis=0)]
        return np.clip(start, self.low + 1e-9 * (self.high - self.low), self.high - 1e-9 * (self.high - self.low))

    def parameters(self, free: np.ndarray) -> TwoWireParameters:
        """The model's parameters for a vector of the free ones."""
        full = self.tie @ free
        for name in FIXED:  # in SCALARS order, so that each index is where it ends
            full = np.insert(full, SCALARS.index(name), self.fixed[name])
        return TwoWireParameters.from_array(full, self.n, self.m)

    def residuals(self, free: np.ndarray) -> np.ndarray:
        check_cancelled()
        return (TwoWireModel(self.parameters(free)).predict(self.t, self.u) - self.y) / self.span

    def jacobian(self, free: np.ndarray) -> np.ndarray:
        """d residuals / d free, from the model's sensitivities (run_with_sensitivities) from rest."""
        check_cancelled()
        p = self.parameters(free).as_array()
        state, dstate = rest_with_sensitivities(p, self.n, self.m)
        out, dout = np.empty(self.t.size), np.empty((self.t.size, p.size))
        run_with_sensitivities(self.t, self.u, p, self.n, self.m, state, dstate, out, dout)
        jacobian = dout.take(self._kernel_first, axis=1)  # C order: scipy's sums run as over `tie`'s product
        jacobian[:, self._tied] += dout.take(self._kernel_last, axis=1)  # a tied pair's second column (no more)
        jacobian /= self.span
        return jacobian

    def solve(self, start: np.ndarray, evaluations: int, tolerance: float = 1e-8) -> object:
        """scipy's least_squares from start, stopped after `evaluations`, when the cost and the step change by
        less than `tolerance` (relative), or when it stalls (STALL_ITERATIONS)."""
        costs = []

        def stop_when_stalled(intermediate_result: object) -> None:
            costs.append(intermediate_result.cost)
            if len(costs) > STALL_ITERATIONS and costs[-1] > costs[-1 - STALL_ITERATIONS] * (1.0 - STALL_FRACTION) ** 2:
                raise StopIteration

        return least_squares(self.residuals, start, jac=self.jacobian, bounds=(self.low, self.high), x_scale="jac",
                             max_nfev=evaluations, ftol=tolerance, xtol=tolerance, callback=stop_when_stalled)
