"""Close the loop: fit the GPI, test its validation residual, fit the candidate effects, keep the one that
earns its parameters (or none), and give the JSON report's "diagnosis" block.

Selection rule: a candidate is accepted when its BIC on the identification data is at least BIC_MARGIN
below the plain GPI's AND its validation RMS error is at least VALIDATION_MARGIN (relative) below the
plain GPI's; of the accepted ones the lowest validation RMS wins (the lower BIC on a tie); none accepted
means "none".
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from sma_stage.errors import InputError
from sma_stage.identify.effects import (
    EFFECT_NAMES,
    EffectFit,
    check_record,
    fit_effect,
    no_effect,
    recount_effect,
)
from sma_stage.identify.fit import FitResult, fit_gpi, predict
from sma_stage.identify.metrics import ErrorMetrics, error_metrics
from sma_stage.identify.residual_tests import ResidualTests, residual_tests

BIC_MARGIN = 10.0  # "very strong" evidence on the Kass-Raftery scale
VALIDATION_MARGIN = 0.10  # the validation RMS must fall by at least 10 %
RECOUNTED = 2  # accepted candidates (best validation first) whose operator count is chosen again
# Which residual test points at which effect (the strongest first; ties keep this order).
POINTERS: dict[str, tuple[str, ...]] = {
    "thermal_lag": ("lagged_input", "input_rate"),
    "delay": ("lagged_input", "input_rate"),
    "rate": ("input_rate",),
    "drift": ("time",),
}

Record = tuple[np.ndarray, np.ndarray, np.ndarray]
Progress = Callable[[str], None] | None


@dataclass(frozen=True)
class CandidateResult:
    """One fitted candidate, judged: BIC difference to the plain GPI (negative favours the candidate),
    validation errors, and why it was accepted or refused."""

    effect: str
    parameters: dict[str, float]
    identification: ErrorMetrics
    validation: ErrorMetrics
    delta_bic: float
    accepted: bool
    reason: str
    seconds: float
    fit: EffectFit = field(repr=False, compare=False)

    def to_dict(self) -> dict[str, object]:
        """Plain values for the JSON report."""
        return {
            "effect": self.effect,
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
    """The outcome: the effect named ("none" or one of EFFECT_NAMES), the test evidence on the plain
    GPI's validation residual, the effect's parameters, validation errors before and after, every
    candidate (those that could not be fitted under `failures`, with the reason), and the series
    behind them (for plots)."""

    effect: str
    evidence: dict[str, str]
    parameters: dict[str, float]
    before: ErrorMetrics
    after: ErrorMetrics
    base: FitResult
    chosen: EffectFit
    tests_before: ResidualTests
    tests_after: ResidualTests
    candidates: list[CandidateResult]
    validation_predicted_before: np.ndarray = field(repr=False)
    validation_predicted_after: np.ndarray = field(repr=False)
    failures: dict[str, str] = field(default_factory=dict)
    seconds: float = 0.0

    def to_dict(self) -> dict[str, object]:
        """The JSON report's "diagnosis" block (plus the per-candidate table under "candidates")."""
        return {
            "effect": self.effect,
            "evidence": dict(self.evidence),
            "parameters": dict(self.parameters),
            "before": {"validation": _errors(self.before)},
            "after": {"validation": _errors(self.after)},
            "candidates": [candidate.to_dict() for candidate in self.candidates],
            **({"not_fitted": dict(self.failures)} if self.failures else {}),
        }


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


def judge(fit: EffectFit, plain: EffectFit, validation: ErrorMetrics, before: ErrorMetrics) -> tuple[bool, str]:
    """(accepted, reason) under the selection rule."""
    delta_bic = fit.bic - plain.bic
    target = (1.0 - VALIDATION_MARGIN) * before.rms_pct
    if delta_bic > -BIC_MARGIN:
        return False, f"BIC change {delta_bic:+.1f} does not reach -{BIC_MARGIN:g}"
    if validation.rms_pct > target:
        return False, f"validation RMS {validation.rms_pct:.3g} % is not below {target:.3g} % (-{VALIDATION_MARGIN:.0%})"
    return True, f"BIC change {delta_bic:+.1f}, validation RMS {before.rms_pct:.3g} % -> {validation.rms_pct:.3g} %"


def _candidate(fit: EffectFit, plain: EffectFit, valid: Record, before: ErrorMetrics,
               seconds: float) -> CandidateResult:
    t_v, u_v, y_v = valid
    validation = error_metrics(y_v, fit.predict(t_v, u_v))
    accepted, reason = judge(fit, plain, validation, before)
    return CandidateResult(fit.effect, fit.parameters, fit.identification, validation, fit.bic - plain.bic,
                           accepted, reason, seconds, fit)


def diagnose(ident: object, valid: object, base: FitResult | None = None, operators: int | None = None,
             progress: Progress = None, output_unit: str = "m") -> Diagnosis:
    """Fit (unless base is given) on ident, test the validation residual, fit and judge every candidate
    effect, and name the one that earns its parameters ("none" if none does).

    Candidates are fitted at the base fit's operator count; unless operators is given, the count is
    then chosen again for the RECOUNTED best accepted candidates (an effect the plain GPI lacks also
    skews the count chosen for it).
    """
    started = time.perf_counter()
    t_i, u_i, y_i = as_record(ident, "identification")
    valid_record = as_record(valid, "validation")
    t_v, u_v, y_v = valid_record
    if base is None:
        _report(progress, "fitting the plain GPI on the identification data")
        base = fit_gpi(u_i, y_i, operators=operators, output_unit=output_unit, progress=progress)
    plain = no_effect(t_i, u_i, y_i, base)
    predicted_before = predict(base, u_v)
    before = error_metrics(y_v, predicted_before)
    tests_before = residual_tests(y_v - predicted_before, u_v, t_v)
    failed = [name for name, check in tests_before.checks.items() if not check.passed]
    _report(progress, f"plain GPI: validation RMS {before.rms_pct:.3g} %, residual tests "
                      + (f"failed: {', '.join(failed)}" if failed else "all passed"))
    candidates, failures = [], {}
    for name in rank_candidates(tests_before):
        _report(progress, f"fitting candidate {name}")
        try:
            fit = fit_effect(name, t_i, u_i, y_i, base, progress)
        except InputError as error:
            failures[name] = str(error)
            _report(progress, f"{name}: not fitted: {error}")
            continue
        candidates.append(_candidate(fit, plain, valid_record, before, fit.seconds))
        _report(progress, f"{name}: {candidates[-1].reason}")
    if operators is None:
        leaders = sorted((c for c in candidates if c.accepted), key=lambda c: c.validation.rms_pct)[:RECOUNTED]
        for leader in leaders:
            try:
                fit = recount_effect(leader.fit, t_i, u_i, y_i, progress)
            except InputError as error:
                _report(progress, f"{leader.effect}: operator count kept: {error}")
                continue
            if fit is not leader.fit:
                candidates[candidates.index(leader)] = _candidate(fit, plain, valid_record, before,
                                                                  leader.seconds + fit.seconds)
    accepted = [c for c in candidates if c.accepted]
    winner = min(accepted, key=lambda c: (c.validation.rms_pct, c.delta_bic)) if accepted else None
    chosen = winner.fit if winner else plain
    predicted_after = chosen.predict(t_v, u_v) if winner else predicted_before
    return Diagnosis(
        effect=winner.effect if winner else "none",
        evidence=tests_before.evidence(),
        parameters=dict(winner.parameters) if winner else {},
        before=before,
        after=winner.validation if winner else before,
        base=base,
        chosen=chosen,
        tests_before=tests_before,
        tests_after=residual_tests(y_v - predicted_after, u_v, t_v) if winner else tests_before,
        candidates=candidates,
        validation_predicted_before=predicted_before,
        validation_predicted_after=predicted_after,
        failures=failures,
        seconds=time.perf_counter() - started,
    )


def _report(progress: Progress, message: str) -> None:
    if progress is not None:
        progress(message)
