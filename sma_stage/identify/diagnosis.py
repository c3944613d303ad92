"""Close the loop: fit the GPI, test its validation residual, fit the candidate effects, keep the one that
earns its parameters (or none), then look again at what the model with it still gets wrong, round after
round, and give the JSON report's "diagnosis" block.

Selection rule, in each round: a candidate is accepted when its BIC on the identification data is at
least BIC_MARGIN below the current model's AND its validation RMS error is below the current model's by
at least VALIDATION_MARGIN (relative) in the first round, LATER_VALIDATION_MARGIN in later ones; of the
accepted ones the lowest validation RMS wins (the lower BIC on a tie). A round with none accepted ends
the search. In a later round the candidate is fitted on the input and output the effects found so far
make (the GPI refitted with it), then every effect of the model is fitted again on top of the others
(backfitting, `refine`) before it is judged: a lag found first holds part of a later dead time or drift.
Each effect enters at most once, and none follows `rate` (it changes the GPI itself rather than its input
or output).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np

from sma_stage.errors import InputError
from sma_stage.identify.cancel import check_cancelled
from sma_stage.identify.effects import (
    EFFECT_NAMES,
    EFFECTS,
    FITTED_STARTS,
    EffectFit,
    NotFitted,
    attempt,
    check_record,
    fit_effect,
    lowest_cost,
    no_effect,
    recount_effect,
    refit_effect,
)
from sma_stage.identify.fit import (
    OPERATOR_CANDIDATES,
    SCREEN_SAMPLES,
    FitResult,
    fit_gpi,
    information_criterion,
    thinned,
)
from sma_stage.identify.metrics import ErrorMetrics, error_metrics
from sma_stage.identify.residual_tests import ResidualTests, residual_tests
from sma_stage.identify.start import StartFit, estimate_start, start_fit
from sma_stage.identify.workers import Pending, Progress, Workers, one_blas_thread
from sma_stage.model.forward import forward
from sma_stage.model.identified import IdentifiedModel, Start
from sma_stage.model.parameters import GPIParameters

BIC_MARGIN = 10.0  # "very strong" evidence on the Kass-Raftery scale
VALIDATION_MARGIN = 0.10  # the validation RMS must fall by at least 10 % in the first round
LATER_VALIDATION_MARGIN = 0.03  # and by at least 3 % in a later round
REFINE_SWEEPS = 1  # backfitting sweeps over the added effects after each later round
EXCLUSIVE = {"thermal_lag": ("wire_thermal",), "wire_thermal": ("thermal_lag",)}  # one thermal reading per model
COUNT_FIT_MARGIN = 0.10  # operator counts whose identification RMS is within 10 % of the best are admitted
COUNT_TIE = 0.01  # validation RMS within 1 % of the lowest: the smaller operator count is kept
RECOUNTED = 2  # accepted candidates (best validation first) whose operator count is chosen again
# Which residual test points at which effect (the strongest first; ties keep this order).
POINTERS: dict[str, tuple[str, ...]] = {
    "thermal_lag": ("lagged_input", "input_rate"),
    "delay": ("lagged_input", "input_rate"),
    "rate": ("input_rate",),
    "drift": ("time",),
    "wire_thermal": ("lagged_input", "input_rate"),
}

Record = tuple[np.ndarray, np.ndarray, np.ndarray]


@dataclass(frozen=True)
class CandidateResult:
    """One fitted candidate, judged: BIC difference to the model it was fitted on (negative favours the
    candidate), validation errors, why it was accepted or refused, and the model with it (in a later
    round, every effect fitted again on top of the others; parameters are then the whole model's)."""

    effect: str
    parameters: dict[str, float]
    identification: ErrorMetrics
    validation: ErrorMetrics
    delta_bic: float
    accepted: bool
    reason: str
    seconds: float
    fit: EffectFit = field(repr=False, compare=False)
    model: Chain | None = field(default=None, repr=False, compare=False)

    def to_dict(self) -> dict[str, object]:
        """Plain values for the JSON report."""
        return {
            "effect": self.effect,
            "fitted": True,
            "parameters": dict(self.parameters),
            "identification": _errors(self.identification),
            "validation": _errors(self.validation),
            "delta_bic": self.delta_bic,
            "accepted": self.accepted,
            "reason": self.reason,
            "fit_seconds": self.seconds,
        }


@dataclass(frozen=True)
class Diagnosis:
    """The outcome: the effect named first ("none" or one of EFFECT_NAMES) and every effect added, in
    order; the test evidence on the plain GPI's validation residual; the added effects' parameters;
    validation errors before and after; the first round's candidates (those that could not be fitted
    under `failures`, with the reason) and every round; the series behind them (for plots)."""

    effect: str
    effects: list[str]
    evidence: dict[str, str]
    parameters: dict[str, float]
    before: ErrorMetrics
    after: ErrorMetrics
    base: FitResult
    chain: Chain
    tests_before: ResidualTests
    tests_after: ResidualTests
    candidates: list[CandidateResult]
    rounds: list[Round]
    validation_predicted_before: np.ndarray = field(repr=False)
    validation_predicted_after: np.ndarray = field(repr=False)
    failures: dict[str, str] = field(default_factory=dict)
    seconds: float = 0.0
    starts: dict[str, StartFit] = field(default_factory=dict)
    operators: dict[str, object] = field(default_factory=dict)

    @property
    def chosen(self) -> EffectFit:
        """The last stage of the model (the plain GPI when nothing was added)."""
        return self.chain.last

    def to_dict(self) -> dict[str, object]:
        """The JSON report's "diagnosis" block, plus the effects added in order, the first round's
        candidates under "candidates" and every round under "rounds"."""
        return {
            "effect": self.effect,
            "evidence": dict(self.evidence),
            "parameters": dict(self.parameters),
            "before": {"validation": _errors(self.before)},
            "after": {"validation": _errors(self.after)},
            "effects": list(self.effects),
            "starts": {record: found.to_dict(self.chain.model) for record, found in self.starts.items()},
            "operators": dict(self.operators),
            "candidates": _candidate_list(self.candidates, self.failures),
            "rounds": [found.to_dict() for found in self.rounds],
        }


def _candidate_list(candidates: list[CandidateResult], failures: dict[str, str]) -> list[dict[str, object]]:
    """The report's candidate list: each fitted candidate, then each that could not be fitted (with why)."""
    return ([candidate.to_dict() for candidate in candidates]
            + [{"effect": name, "fitted": False, "accepted": False, "reason": f"not fitted: {reason}"}
               for name, reason in failures.items()])


def _errors(metrics: ErrorMetrics) -> dict[str, float]:
    return {"rms_pct": metrics.rms_pct, "max_pct": metrics.max_pct}


def as_record(data: object, name: str) -> Record:
    """(t, u, y) from a Series-like object (attributes t, input, output) or a (t, u, y) triple."""
    if all(hasattr(data, attribute) for attribute in ("t", "input", "output")):
        t, u, y = data.t, data.input, data.output
    else:
        try:
            t, u, y = data
        except (TypeError, ValueError):
            raise InputError(f"{name} data must be a Series or a (t, u, y) triple") from None
    try:
        return check_record(t, u, y)
    except InputError as error:
        raise InputError(f"{name} data: {error}") from None


def rank_candidates(tests: ResidualTests) -> list[str]:
    """Candidates ordered by how far the tests that point at them exceed their bands (strongest first)."""
    def strength(effect: str) -> float:
        return max(tests.checks[name].ratio for name in POINTERS[effect])

    return sorted(EFFECT_NAMES, key=lambda effect: -strength(effect))


@dataclass(frozen=True)
class Chain:
    """The model so far: the plain GPI fit, then each added effect in the order found. Each stage was
    fitted on the input and output the stages before it make (their input transforms applied in turn,
    their output offsets taken off); the last one predicts."""

    stages: tuple[EffectFit, ...]
    base: FitResult = field(repr=False, compare=False)

    @property
    def effects(self) -> list[str]:
        """Names of the added effects, in order."""
        return [stage.effect for stage in self.stages[1:]]

    @property
    def parameters(self) -> dict[str, float]:
        """Every added effect's parameters."""
        return {name: value for stage in self.stages[1:] for name, value in stage.parameters.items()}

    @property
    def last(self) -> EffectFit:
        return self.stages[-1]

    @property
    def composable(self) -> bool:
        """Whether a further effect can be fitted on top (see the module docstring)."""
        return self.last.composable

    @property
    def bic(self) -> float:
        """BIC on the identification data, counting the parameters of every stage."""
        earlier = sum(len(stage.parameters) for stage in self.stages[:-1])
        return information_criterion(self.last.cost, self.last.samples, self.last.parameter_count + earlier)

    @property
    def model(self) -> IdentifiedModel:
        """The whole model: the last stage's GPI with every added effect, in the order found."""
        last = self.last
        effects = tuple(stage.spec for stage in self.stages[1:])
        return IdentifiedModel(last.gpi_parameters, last.operators, effects)

    @property
    def start(self) -> str:
        """How the identification record starts for this model: the first added effect's start (rest or
        held; later effects are fitted from the same)."""
        return self.stages[1].start if len(self.stages) > 1 else "rest"

    def data(self, t: np.ndarray, u: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(input, output) as an effect added on top sees them: every stage's input transform applied in
        turn (from the chain's start), every output offset taken off."""
        v, offset = u, np.zeros_like(t)
        for stage in self.stages[1:]:
            spec = stage.spec
            if spec.role == "input":
                v = spec.transform(t, v, spec.start_state(t, v, self.start))[0]
            elif spec.role == "output":
                offset = offset + spec.offset(t)[0]
        return v, y - offset

    def predict(self, t: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Output [output unit] of the whole model for the identification record (t [s], u [A]) from its start."""
        return self.model.predict_from(t, u, Start(self.start))

    def then(self, stage: EffectFit) -> Chain:
        """This model with one more effect."""
        return Chain((*self.stages, stage), self.base)

    def without(self, index: int) -> Chain:
        """This model without stage `index` (an added effect; the last stage keeps its GPI)."""
        return Chain(self.stages[:index] + self.stages[index + 1:], self.base)

    @property
    def refittable(self) -> bool:
        """Whether every added effect can be fitted again on top of the others: they are input
        transforms that commute (linear, time-invariant: lag, delay) and output offsets, so their order
        does not matter."""
        return all(stage.composable for stage in self.stages)


@dataclass(frozen=True)
class Round:
    """One round of the search: the model it started from (its validation errors), every candidate
    fitted on top of it, and the one added (None when none earned its parameters)."""

    before: ErrorMetrics
    candidates: list[CandidateResult]
    failures: dict[str, str]
    winner: CandidateResult | None

    def to_dict(self) -> dict[str, object]:
        """Plain values for the JSON report."""
        return {
            "added": self.winner.effect if self.winner else "none",
            "before": {"validation": _errors(self.before)},
            "after": {"validation": _errors(self.winner.validation if self.winner else self.before)},
            "candidates": _candidate_list(self.candidates, self.failures),
        }


def judge(delta_bic: float, validation: ErrorMetrics, before: ErrorMetrics,
          margin: float = VALIDATION_MARGIN) -> tuple[bool, str]:
    """(accepted, reason) under the selection rule, margin being the relative fall the validation RMS needs."""
    target = (1.0 - margin) * before.rms_pct
    if delta_bic > -BIC_MARGIN:
        return False, f"BIC change {delta_bic:+.1f} does not reach -{BIC_MARGIN:g}"
    if validation.rms_pct > target:
        return False, f"validation RMS {validation.rms_pct:.3g} % is not below {target:.3g} % (-{margin:.0%})"
    return True, f"BIC change {delta_bic:+.1f}, validation RMS {before.rms_pct:.3g} % -> {validation.rms_pct:.3g} %"


@dataclass(frozen=True)
class Validation:
    """The validation record (t [s], u [A], y) and the sample its errors count from. A separate record
    (scored_from 0) starts as estimate_start finds for each model; a record that continues the
    identification record (its errors counted from scored_from) runs from the identification's start."""

    t: np.ndarray
    u: np.ndarray
    y: np.ndarray
    scored_from: int = 0

    def predict(self, model: IdentifiedModel, identification_start: str) -> StartFit:
        """The model's output over the record, and the start it runs from."""
        if self.scored_from > 0:
            return start_fit(model, self.t, self.u, self.y, Start(identification_start))
        return estimate_start(model, self.t, self.u, self.y)

    def errors(self, predicted: np.ndarray) -> ErrorMetrics:
        """RMS and max error of a prediction over the scored samples [% of their span]."""
        return error_metrics(self.y[self.scored_from:], predicted[self.scored_from:])

    def tests(self, predicted: np.ndarray) -> ResidualTests:
        """The residual tests of a prediction over the scored samples."""
        k = self.scored_from
        return residual_tests((self.y - predicted)[k:], self.u[k:], self.t[k:])


def _candidate(chain: Chain, fit: EffectFit, ident: Record, valid: Validation, before: ErrorMetrics, spent_s: float,
               margin: float, progress: Progress) -> CandidateResult:
    """Judge the chain with fit on top; in a later round its effects are first fitted again together.
    spent_s: the seconds its fits took so far (the judging time is added)."""
    started = time.perf_counter()
    extended = chain.then(fit)
    if len(chain.stages) > 1:
        extended = refine(extended, ident, progress=progress)
    validation = valid.errors(valid.predict(extended.model, extended.start).predicted)
    delta_bic = extended.bic - chain.bic
    accepted, reason = judge(delta_bic, validation, before, margin)
    if accepted:
        accepted, reason = _above_noise(extended, fit.effect, ident, reason)
    parameters = fit.parameters if len(chain.stages) == 1 else extended.parameters
    return CandidateResult(fit.effect, parameters, extended.last.identification, validation, delta_bic, accepted,
                           reason, spent_s + time.perf_counter() - started, fit, extended)


def _above_noise(chain: Chain, effect: str, ident: Record, reason: str) -> tuple[bool, str]:
    """(accepted, reason): refused when taking the effect out of the model (its GPI and the other effects
    kept) changes the identification output by less, RMS, than the model's own residual there: whatever
    it improved elsewhere (the GPI refitted with it, the other effects refined), its own part is below
    the noise and the data do not show it."""
    t_i, u_i, y_i = ident
    model = chain.model
    start = Start(chain.start)
    with_it = model.predict_from(t_i, u_i, start)
    without = replace(model, effects=tuple(e for e in model.effects if e.kind != effect), state=None)
    part = float(np.sqrt(np.mean((with_it - without.predict_from(t_i, u_i, start)) ** 2)))
    noise = float(np.sqrt(np.mean((y_i - with_it) ** 2)))
    if part < noise:
        return False, f"its own part of the output, {part:.3g} RMS, is below the residual's {noise:.3g}: not resolved"
    return True, reason


def _judged(name: str, chain: Chain, ident: Record, valid: Validation, before: ErrorMetrics, margin: float,
            v_i: np.ndarray, w_i: np.ndarray, base: FitResult, starts: tuple[str, ...],
            progress: Progress = None) -> CandidateResult | NotFitted:
    """Candidate `name` fitted on (t, v_i, w_i), what the chain leaves of the identification record, from
    base, and judged on top of the chain; NotFitted when it cannot be fitted."""

    def judged() -> CandidateResult:
        fit = fit_effect(name, ident[0], v_i, w_i, base, progress, starts)
        return _candidate(chain, fit, ident, valid, before, fit.seconds, margin, progress)

    return attempt(name, judged)


def _recounted(leader: CandidateResult, chain: Chain, ident: Record, valid: Validation, before: ErrorMetrics,
               margin: float, v_i: np.ndarray, w_i: np.ndarray, progress: Progress = None
               ) -> CandidateResult | NotFitted:
    """An accepted candidate with its operator count chosen again, judged again when the count changed."""

    def recounted() -> CandidateResult:
        fit = recount_effect(leader.fit, ident[0], v_i, w_i, progress)
        if fit is leader.fit:
            return leader
        return _candidate(chain, fit, ident, valid, before, leader.seconds + fit.seconds, margin, progress)

    return attempt(leader.effect, recounted)


def _job_name(job: tuple) -> str:
    first = job[0]
    if isinstance(first, int):
        return f"{first} operators"
    return first if isinstance(first, str) else first.effect


def _job_cost(job: tuple) -> float:
    """About how long a job takes, to hand out the costliest first: an effect's relative_cost, an
    operator count's count."""
    first = job[0]
    return float(first) if isinstance(first, int) else EFFECTS[_job_name(job)].relative_cost


def _search_round(chain: Chain, ident: Record, valid: Validation, before: ErrorMetrics, tests: ResidualTests,
                  recount: bool, progress: Progress, pool: Workers, then: Callable[[], object] | None = None) -> Round:
    """Fit every effect not yet in the chain on top of it and pick the winner (see the selection rule); `then` is
    called once the candidates are handed to the pool (Workers.run)."""
    first = len(chain.stages) == 1
    margin = VALIDATION_MARGIN if first else LATER_VALIDATION_MARGIN
    t_i, u_i, y_i = ident
    v_i, w_i = chain.data(t_i, u_i, y_i)
    last = chain.last
    taken = {name for effect in chain.effects for name in (effect, *EXCLUSIVE.get(effect, ()))}
    names = [effect for effect in rank_candidates(tests) if effect not in taken]
    base = chain.base if first else attempt("GPI", lambda: fit_gpi(
        v_i, w_i, operators=last.operators, initial=last.gpi_parameters, output_unit=last.gpi_parameters.output_unit))
    if isinstance(base, NotFitted):
        return Round(before, [], {name: f"on top of {' + '.join(chain.effects)}: {base}" for name in names}, None)
    starts = FITTED_STARTS if first else (chain.start,)
    jobs = [(name, chain, ident, valid, before, margin, v_i, w_i, base, starts) for name in names]
    candidates, failures = [], {}
    doing = "fitting candidate {}" + ("" if first else f" on top of {' + '.join(chain.effects)}")
    for name, outcome in zip(names, pool.run(_judged, jobs, progress, doing, then, _job_name, _job_cost), strict=True):
        if isinstance(outcome, NotFitted):
            failures[name] = str(outcome)
            _report(progress, f"{name}: not fitted: {outcome}")
            continue
        candidates.append(outcome)
        _report(progress, f"{name}: {outcome.reason}")
    if recount:
        leaders = sorted((c for c in candidates if c.accepted), key=lambda c: c.validation.rms_pct)[:RECOUNTED]
        jobs = [(leader, chain, ident, valid, before, margin, v_i, w_i) for leader in leaders]
        again = "choosing the operator count of {} again"
        for leader, outcome in zip(leaders, pool.run(_recounted, jobs, progress, again, name=_job_name, cost=_job_cost), strict=True):
            if isinstance(outcome, NotFitted):
                _report(progress, f"operator count kept: {outcome}")
                continue
            candidates[candidates.index(leader)] = outcome
    accepted = [c for c in candidates if c.accepted]
    winner = min(accepted, key=lambda c: (c.validation.rms_pct, c.delta_bic)) if accepted else None
    return Round(before, candidates, failures, winner)


def refine(chain: Chain, ident: Record, sweeps: int = REFINE_SWEEPS, progress: Progress = None) -> Chain:
    """Fit every added effect again, in turn, on top of all the others (backfitting): a greedy search
    leaves an early effect holding part of a later one (a lag fitted with a drift still in the data).
    A refit replaces the chain only when it lowers the identification SSR."""
    if len(chain.effects) < 2 or not chain.refittable:
        return chain
    t_i, u_i, y_i = ident
    for _ in range(sweeps):
        for name in list(chain.effects):
            index = chain.effects.index(name) + 1
            others = chain.without(index)
            v_i, w_i = others.data(t_i, u_i, y_i)
            last = others.last

            def refitted(v_i: np.ndarray = v_i, w_i: np.ndarray = w_i, last: EffectFit = last,
                         previous: EffectFit = chain.stages[index]) -> EffectFit:
                start = fit_gpi(v_i, w_i, operators=last.operators, initial=last.gpi_parameters,
                                output_unit=last.gpi_parameters.output_unit)
                return refit_effect(previous, t_i, v_i, w_i, start, progress)

            fit = attempt(name, refitted)
            if isinstance(fit, NotFitted):
                _report(progress, f"not refitted: {fit}")
                continue
            if fit.cost < chain.last.cost:
                chain = others.then(fit)
                _report(progress, f"{name} refitted on top of the others: {fit.parameters}")
    return chain


def recount_last(chain: Chain, ident: Record, progress: Progress = None) -> Chain:
    """The chain with its operator count chosen again on top of every added effect (fit_gpi's rule): the
    first round chose it with only the first effect in."""
    t_i, u_i, y_i = ident
    others = chain.without(len(chain.stages) - 1)
    v_i, w_i = others.data(t_i, u_i, y_i)
    fit = attempt(chain.last.effect, lambda: recount_effect(chain.last, t_i, v_i, w_i, progress))
    if isinstance(fit, NotFitted):
        _report(progress, f"operator count kept: {fit}")
        return chain
    return chain if fit is chain.last else others.then(fit)


def count_by_held_out(chain: Chain, ident: Record, valid: Validation, progress: Progress = None,
                      cold: bool = True, pool: Workers | None = None, begun: ColdFit | None = None
                      ) -> tuple[Chain, dict[str, object]]:
    """The operator count of the model chosen by the identification BIC and the held-out error together:
    the GPI refitted at every count of OPERATOR_CANDIDATES with the effects held (from the model's GPI and,
    when cold, from a cold fit of every count, the better kept; on a copy thinned to SCREEN_SAMPLES, the chosen count
    then refitted on all samples). Every count has the same parameters, so the BIC only ranks their fit
    to the identification data, where more operators fit a little closer; the held-out error says which
    of them generalises. The BIC admits the counts whose RMS error there is within COUNT_FIT_MARGIN of
    the best (a BIC within 2 N ln(1 + COUNT_FIT_MARGIN): a fit that failed is not chosen for luck on the
    validation record), and of those the lowest validation RMS wins, the smaller count on a near-tie
    (COUNT_TIE). The counts are fitted in the pool's processes when one is given; `begun`, a cold fit begun
    earlier (begin_cold_fit), is taken when it was begun on the same data. Returns the
    chain with that count and the report's "operators" block (the choice, the runner-up, every count's
    BIC and validation RMS)."""
    t_i, u_i, y_i = ident
    v_i, w_i = chain.data(t_i, u_i, y_i)
    last, unit = chain.last, chain.last.gpi_parameters.output_unit
    keep = thinned(v_i, SCREEN_SAMPLES)
    cold_fit = None
    if cold:
        ready = begun is not None and begun.fits(v_i, w_i)
        cold_fit = begun.pending.result() if ready else _cold_fit(v_i, w_i, unit)
    cold_fits = cold_fit.by_count if isinstance(cold_fit, FitResult) else {}
    jobs = [(count, chain, (v_i, w_i, y_i), valid, cold_fits.get(count)) for count in OPERATOR_CANDIDATES
            if count != last.operators]
    pool = pool or Workers()
    options: dict[int, Chain] = {last.operators: chain}
    rows = {last.operators: _count_row(chain, valid)}
    for (count, *_), outcome in zip(jobs, pool.run(_count_option, jobs, progress, "fitting {}", name=_job_name, cost=_job_cost), strict=True):
        if isinstance(outcome, str):
            _report(progress, f"{count} operators: {outcome}")
            continue
        options[count], rows[count] = outcome
    best_bic = min(row["bic"] for row in rows.values())
    margin = 2.0 * y_i.size * math.log1p(COUNT_FIT_MARGIN)
    admissible = sorted((count for count, row in rows.items() if row["bic"] <= best_bic + margin),
                        key=lambda count: (rows[count]["validation_rms_pct"], count))
    lowest = rows[admissible[0]]["validation_rms_pct"]
    chosen = min(count for count in admissible if rows[count]["validation_rms_pct"] <= (1.0 + COUNT_TIE) * lowest)
    runner_up = next((count for count in admissible if count != chosen), None)
    found_chain = options[chosen]
    if chosen != last.operators and keep.size < v_i.size:
        polished = attempt("GPI", lambda: fit_gpi(v_i, w_i, operators=chosen, initial=found_chain.last.gpi_parameters,
                                                  output_unit=unit))
        if not isinstance(polished, NotFitted):
            found_chain = _with_gpi(chain, polished.parameters, chosen, v_i, w_i, y_i)
    _report(progress, f"operators: {chosen} chosen (runner-up {runner_up}) by BIC and held-out error")
    return found_chain, {"chosen": chosen, "runner_up": runner_up,
                         "by_count": {str(count): rows[count] for count in sorted(rows)}}


@dataclass(frozen=True)
class ColdFit:
    """A cold fit of every operator count (count_by_held_out's) under way on what a chain leaves of the
    identification record (v, w)."""

    v: np.ndarray
    w: np.ndarray
    pending: Pending

    def fits(self, v: np.ndarray, w: np.ndarray) -> bool:
        """Whether it was begun on these data."""
        return np.array_equal(self.v, v) and np.array_equal(self.w, w)


def begin_cold_fit(v: np.ndarray, w: np.ndarray, unit: str, pool: Workers) -> ColdFit:
    """count_by_held_out's cold fit of (v, w) begun in the pool's processes (with workers 1: when asked for)."""
    return ColdFit(v, w, pool.submit(_cold_fit, v, w, unit))


def _cold_fit(v: np.ndarray, w: np.ndarray, unit: str) -> FitResult | NotFitted:
    """A fit of every operator count from cold starts on (v, w) thinned to SCREEN_SAMPLES."""
    keep = thinned(v, SCREEN_SAMPLES)
    return attempt("GPI", lambda: fit_gpi(v[keep], w[keep], output_unit=unit))


def _count_option(count: int, chain: Chain, data: tuple[np.ndarray, np.ndarray, np.ndarray], valid: Validation,
                  cold_start: GPIParameters | None, progress: Progress = None) -> tuple[Chain, dict[str, float]] | str:
    """The chain with its GPI refitted at `count` operators (effects held; from the chain's GPI carried to
    the count and from cold_start, the better kept, on the SCREEN_SAMPLES copy) and its report row (BIC,
    validation RMS); why not, when no fit was found. data: (v_i, w_i, y_i), what the chain's effects
    leave of the identification record (chain.data) and its output."""
    v_i, w_i, y_i = data
    last, unit = chain.last, chain.last.gpi_parameters.output_unit
    keep = thinned(v_i, SCREEN_SAMPLES)
    carried = last.gpi_parameters.replace(a9=last.gpi_parameters.a9 * max(last.operators - 1, 1) / max(count - 1, 1))
    tries = [attempt("GPI", lambda initial=initial: fit_gpi(v_i[keep], w_i[keep], operators=count, initial=initial,
                                                            output_unit=unit))
             for initial in (carried, cold_start) if initial is not None]
    found = lowest_cost(fit for fit in tries if not isinstance(fit, NotFitted))
    if found is None:
        return "; ".join(str(fit) for fit in tries)
    option = _with_gpi(chain, found.parameters, count, v_i, w_i, y_i)
    return option, _count_row(option, valid)


def _count_row(option: Chain, valid: Validation) -> dict[str, float]:
    return {"bic": option.bic, "validation_rms_pct": valid.errors(valid.predict(option.model, option.start).predicted).rms_pct}


def _with_gpi(chain: Chain, parameters: GPIParameters, operators: int, v_i: np.ndarray, w_i: np.ndarray,
              y_i: np.ndarray) -> Chain:
    """The chain with its last GPI replaced (the effects held), scored on the whole identification record."""
    predicted = forward(v_i, parameters, operators) + (y_i - w_i)
    residual = y_i - predicted
    stage = replace(chain.last, gpi_parameters=parameters, operators=operators, cost=float(residual @ residual),
                    identification=error_metrics(y_i, predicted))
    return chain.without(len(chain.stages) - 1).then(stage)


def diagnose(ident: object, valid: object, base: FitResult | None = None, operators: int | None = None,
             progress: Progress = None, output_unit: str = "m", max_rounds: int = len(EFFECT_NAMES),
             scored_from: int = 0, workers: int = 1, pool: Workers | None = None) -> Diagnosis:
    """Fit (unless base is given) on ident, test the validation residual, fit and judge every candidate
    effect, add the one that earns its parameters, and search again on top of it, up to max_rounds
    rounds; "none" when the first round adds nothing.

    In the first round candidates are fitted at the base fit's operator count; unless operators is
    given, the count is then chosen again for the RECOUNTED best accepted candidates (an effect the
    plain GPI lacks also skews the count chosen for it). Later rounds keep the count; after them every
    added effect is fitted again on top of the others (`refine`) and the count chosen once more.
    workers: processes that fit a round's candidates at once (Workers; the result is the same for any count).
    pool: a caller's Workers to use instead (its `workers` then; it stays open). BLAS runs on one thread
    meanwhile (one_blas_thread).
    """
    with one_blas_thread():
        if pool is not None:
            return _diagnose(ident, valid, base, operators, progress, output_unit, max_rounds, scored_from, pool)
        with Workers(workers) as own:
            return _diagnose(ident, valid, base, operators, progress, output_unit, max_rounds, scored_from, own)


def _diagnose(ident: object, valid: object, base: FitResult | None, operators: int | None, progress: Progress,
              output_unit: str, max_rounds: int, scored_from: int, pool: Workers) -> Diagnosis:
    started = time.perf_counter()
    ident_record = as_record(ident, "identification")
    valid_record = as_record(valid, "validation")
    if not 0 <= scored_from <= valid_record[0].size - 3:
        raise InputError(f"scored_from must leave at least 3 validation samples, got {scored_from}")
    pool.start()
    validation = Validation(*valid_record, scored_from)
    t_i, u_i, y_i = ident_record
    if base is None:
        _report(progress, "fitting the plain GPI on the identification data")
        base = fit_gpi(u_i, y_i, operators=operators, output_unit=output_unit, progress=progress)
    chain = Chain((no_effect(t_i, u_i, y_i, base),), base)
    start_before = validation.predict(chain.model, chain.start)
    predicted_before = start_before.predicted
    before = validation.errors(predicted_before)
    tests_before = validation.tests(predicted_before)
    failed = [name for name, check in tests_before.checks.items() if not check.passed]
    _report(progress, f"plain GPI: validation RMS {before.rms_pct:.3g} %, residual tests "
                      + (f"failed: {', '.join(failed)}" if failed else "all passed"))
    chain, rounds, begun = _search_rounds(chain, ident_record, validation, before, tests_before, operators is None,
                                          max_rounds, progress, pool)
    if operators is None and len(chain.effects) > 1:
        chain = recount_last(chain, ident_record, progress)
    counts: dict[str, object] = {}
    if operators is None and chain.last.composable:
        chain, counts = count_by_held_out(chain, ident_record, validation, progress, pool=pool, begun=begun)
    changed = bool(chain.effects) or chain.last.operators != base.operators
    start_after = validation.predict(chain.model, chain.start) if changed else start_before
    predicted_after = start_after.predicted
    after = validation.errors(predicted_after) if changed else before
    tests_after = validation.tests(predicted_after) if changed else tests_before
    found_order = [found.winner.effect for found in rounds if found.winner is not None]
    return Diagnosis(
        effect=found_order[0] if found_order else "none",
        effects=found_order,
        evidence=tests_before.evidence(),
        parameters=chain.parameters,
        before=before,
        after=after,
        base=base,
        chain=chain,
        tests_before=tests_before,
        tests_after=tests_after,
        candidates=rounds[0].candidates if rounds else [],
        rounds=rounds,
        validation_predicted_before=predicted_before,
        validation_predicted_after=predicted_after,
        failures=rounds[0].failures if rounds else {},
        seconds=time.perf_counter() - started,
        starts={"identification": estimate_start(chain.model, t_i, u_i, y_i), "validation": start_after},
        operators=counts,
    )


def _search_rounds(chain: Chain, ident: Record, validation: Validation, before: ErrorMetrics,
                   tests_before: ResidualTests, recount: bool, max_rounds: int, progress: Progress,
                   pool: Workers) -> tuple[Chain, list[Round], ColdFit | None]:
    """Round after round (_search_round), each on top of the model the one before left, until one adds
    nothing or max_rounds; with recount, the operator count is chosen again after each round that adds an
    effect (count_by_held_out). Returns the model found, every round, and (with recount) the final count's cold
    fit of the model the last round began from, begun in the pool behind that round's candidates (in the time
    the round's longest fit leaves the other processes): what the final count needs when the round adds
    nothing."""
    rounds: list[Round] = []
    current = before
    begun: ColdFit | None = None

    def begin(chain: Chain) -> None:
        nonlocal begun
        begun = begin_cold_fit(*chain.data(*ident), chain.last.gpi_parameters.output_unit, pool)

    while len(rounds) < max_rounds and chain.composable and len(chain.effects) < len(EFFECT_NAMES):
        tests = validation.tests(validation.predict(chain.model, chain.start).predicted) if rounds else tests_before
        then = partial(begin, chain) if recount and rounds else None
        found = _search_round(chain, ident, validation, current, tests, recount and not rounds, progress, pool, then)
        rounds.append(found)
        if found.winner is None:
            break
        chain, current = found.winner.model, found.winner.validation
        _report(progress, f"added {found.winner.effect}: validation RMS {current.rms_pct:.3g} %")
        if recount and chain.composable:
            chain, _ = count_by_held_out(chain, ident, validation, progress, cold=False, pool=pool)
            current = validation.errors(validation.predict(chain.model, chain.start).predicted)
    return chain, rounds, begun


def _report(progress: Progress, message: str) -> None:
    check_cancelled()
    if progress is not None:
        progress(message)
