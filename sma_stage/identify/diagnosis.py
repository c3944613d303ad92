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

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np

from sma_stage.errors import InputError
from sma_stage.identify.cancel import Progress, report
from sma_stage.identify.chain import Chain, Record, Validation, as_record
from sma_stage.identify.counts import ColdFit, begin_cold_fit, count_by_held_out
from sma_stage.identify.effects import (
    EFFECT_NAMES,
    EFFECTS,
    FITTED_STARTS,
    EffectFit,
    NotFitted,
    attempt,
    fit_effect,
    no_effect,
    recount_effect,
    refit_effect,
)
from sma_stage.identify.fit import FitResult, fit_gpi
from sma_stage.identify.metrics import ErrorMetrics
from sma_stage.identify.residual_tests import ResidualTests
from sma_stage.identify.start import StartFit, estimate_start
from sma_stage.identify.workers import Workers, one_blas_thread
from sma_stage.model.identified import Start

BIC_MARGIN = 10.0  # "very strong" evidence on the Kass-Raftery scale
VALIDATION_MARGIN = 0.10  # the validation RMS must fall by at least 10 % in the first round
LATER_VALIDATION_MARGIN = 0.03  # and by at least 3 % in a later round
REFINE_SWEEPS = 1  # backfitting sweeps over the added effects after each later round
EXCLUSIVE = {"thermal_lag": ("wire_thermal",), "wire_thermal": ("thermal_lag",)}  # one thermal reading per model
RECOUNTED = 2  # accepted candidates (best validation first) whose operator count is chosen again
# Which residual test points at which effect (the strongest first; ties keep this order).
POINTERS: dict[str, tuple[str, ...]] = {
    "thermal_lag": ("lagged_input", "input_rate"),
    "delay": ("lagged_input", "input_rate"),
    "rate": ("input_rate",),
    "drift": ("time",),
    "wire_thermal": ("lagged_input", "input_rate"),
}


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


def rank_candidates(tests: ResidualTests) -> list[str]:
    """Candidates ordered by how far the tests that point at them exceed their bands (strongest first)."""
    def strength(effect: str) -> float:
        return max(tests.checks[name].ratio for name in POINTERS[effect])

    return sorted(EFFECT_NAMES, key=lambda effect: -strength(effect))


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


def _candidate(chain: Chain, fit: EffectFit, ident: Record, valid: Validation, before: ErrorMetrics, spent_s: float,
               margin: float, progress: Progress) -> CandidateResult:
    """Judge the chain with fit on top; in a later round its effects are first fitted again together.
    spent_s: the seconds its fits took so far (the judging time is added)."""
    started = time.perf_counter()
    extended = chain.then(fit)
    if len(chain.stages) > 1:
        extended = refine(extended, ident, progress=progress)
    validation = valid.worst_errors(extended.model, extended.start)
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
    return first if isinstance(first, str) else first.effect


def _job_cost(job: tuple) -> float:
    """About how long a job takes, to hand out the costliest first: its effect's relative_cost."""
    return EFFECTS[_job_name(job)].relative_cost


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
            report(progress, f"{name}: not fitted: {outcome}")
            continue
        candidates.append(outcome)
        report(progress, f"{name}: {outcome.reason}")
    if recount:
        leaders = sorted((c for c in candidates if c.accepted), key=lambda c: c.validation.rms_pct)[:RECOUNTED]
        jobs = [(leader, chain, ident, valid, before, margin, v_i, w_i) for leader in leaders]
        again = "choosing the operator count of {} again"
        for leader, outcome in zip(leaders, pool.run(_recounted, jobs, progress, again, name=_job_name, cost=_job_cost), strict=True):
            if isinstance(outcome, NotFitted):
                report(progress, f"operator count kept: {outcome}")
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
                report(progress, f"not refitted: {fit}")
                continue
            if fit.cost < chain.last.cost:
                chain = others.then(fit)
                report(progress, f"{name} refitted on top of the others: {fit.parameters}")
    return chain


def recount_last(chain: Chain, ident: Record, progress: Progress = None) -> Chain:
    """The chain with its operator count chosen again on top of every added effect (fit_gpi's rule): the
    first round chose it with only the first effect in."""
    t_i, u_i, y_i = ident
    others = chain.without(len(chain.stages) - 1)
    v_i, w_i = others.data(t_i, u_i, y_i)
    fit = attempt(chain.last.effect, lambda: recount_effect(chain.last, t_i, v_i, w_i, progress))
    if isinstance(fit, NotFitted):
        report(progress, f"operator count kept: {fit}")
        return chain
    return chain if fit is chain.last else others.then(fit)


def diagnose(ident: object, valid: object, base: FitResult | None = None, operators: int | None = None,
             progress: Progress = None, output_unit: str = "m", max_rounds: int = len(EFFECT_NAMES),
             scored_from: int = 0, workers: int = 1, pool: Workers | None = None,
             others: Sequence[object] = ()) -> Diagnosis:
    """Fit (unless base is given) on ident, test the validation residual, fit and judge every candidate
    effect, add the one that earns its parameters, and search again on top of it, up to max_rounds
    rounds; "none" when the first round adds nothing.

    In the first round candidates are fitted at the base fit's operator count; unless operators is
    given, the count is then chosen again for the RECOUNTED best accepted candidates (an effect the
    plain GPI lacks also skews the count chosen for it). Later rounds keep the count; after them every
    added effect is fitted again on top of the others (`refine`) and the count chosen once more.
    others: further validation records (t, u, y; each run from rest): a candidate is then judged by its errors on
    the record it predicts worst, the held-out one or one of these, so that an effect is not chosen for one shape.
    workers: processes that fit a round's candidates at once (Workers; the result is the same for any count).
    pool: a caller's Workers to use instead (its `workers` then; it stays open). BLAS runs on one thread
    meanwhile (one_blas_thread).
    """
    with one_blas_thread():
        if pool is not None:
            return _diagnose(ident, valid, base, operators, progress, output_unit, max_rounds, scored_from, pool,
                             others)
        with Workers(workers) as own:
            return _diagnose(ident, valid, base, operators, progress, output_unit, max_rounds, scored_from, own,
                             others)


def _diagnose(ident: object, valid: object, base: FitResult | None, operators: int | None, progress: Progress,
              output_unit: str, max_rounds: int, scored_from: int, pool: Workers, others: Sequence[object] = ()
              ) -> Diagnosis:
    started = time.perf_counter()
    ident_record = as_record(ident, "identification")
    valid_record = as_record(valid, "validation")
    if not 0 <= scored_from <= valid_record[0].size - 3:
        raise InputError(f"scored_from must leave at least 3 validation samples, got {scored_from}")
    pool.start()
    validation = Validation(*valid_record, scored_from,
                            tuple(as_record(record, "validation") for record in others))
    t_i, u_i, y_i = ident_record
    if base is None:
        report(progress, "fitting the plain GPI on the identification data")
        base = fit_gpi(u_i, y_i, operators=operators, output_unit=output_unit, progress=progress)
    chain = Chain((no_effect(t_i, u_i, y_i, base),), base)
    start_before = validation.predict(chain.model, chain.start)
    predicted_before = start_before.predicted
    before = validation.errors(predicted_before)
    tests_before = validation.tests(predicted_before)
    failed = [name for name, check in tests_before.checks.items() if not check.passed]
    report(progress, f"plain GPI: validation RMS {before.rms_pct:.3g} %, residual tests "
                      + (f"failed: {', '.join(failed)}" if failed else "all passed"))
    judged_before = validation.worst_errors(chain.model, chain.start) if validation.others else before
    chain, rounds, begun = _search_rounds(chain, ident_record, validation, judged_before, tests_before,
                                          operators is None, max_rounds, progress, pool)
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
        report(progress, f"added {found.winner.effect}: validation RMS {current.rms_pct:.3g} %")
        if recount and chain.composable:
            chain, _ = count_by_held_out(chain, ident, validation, progress, cold=False, pool=pool)
            current = validation.worst_errors(chain.model, chain.start)
    return chain, rounds, begun


