"""The one identification pipeline: fit the GPI, diagnose the residual, choose the model to deploy (the
GPI with every effect the diagnosis added), and report. `gpi_tool fit/diagnose`, the identification
node's `~/refit`, the demo and the benchmarks all call `identify_recording`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from sma_stage.control.compensator import compensation_notes
from sma_stage.errors import InputError
from sma_stage.identify.cancel import Progress
from sma_stage.identify.checks import MIN_SAMPLES
from sma_stage.identify.diagnosis import Diagnosis, diagnose
from sma_stage.identify.families import (
    HELD_CURRENT_FAMILIES,
    FamilyRow,
    check_families,
    choose,
    fit_free_weights_row,
    held_current_row,
    start_held_current_fit,
)
from sma_stage.identify.fit import FitResult, fit_gpi, information_criterion, predict
from sma_stage.identify.metrics import ErrorMetrics, error_metrics
from sma_stage.identify.report import fit_report
from sma_stage.identify.two_wire import HeldOut
from sma_stage.identify.workers import WORKER_NICENESS, Pending, Workers, one_blas_thread
from sma_stage.io.series import Series
from sma_stage.model.identified import IdentifiedModel, Start
from sma_stage.model.kinds import AnyModel

MIN_HELD_OUT = 10
FIT_SAMPLES = 20_000  # a longer record is fitted on a copy thinned to about this many samples (max_fit_samples)
THINNING_COST_WARNING = 1.25  # a warning when the full-rate held-out RMS exceeds the thinned one by this factor
GPI_MODEL_FILE = "model_gpi.yaml"  # gpi_tool writes the GPI family's model here when another family is chosen



@dataclass(frozen=True)
class Identification:
    """What the pipeline gives: the model to deploy (its state where the record ended), the plain GPI fit,
    the diagnosis (None when not asked for, or when it failed: see `warnings`), the JSON report and the
    validation record with the sample its errors count from."""

    model: AnyModel
    fit: FitResult
    diagnosis: Diagnosis | None
    report: dict
    warnings: list[str]
    validation: Series | None
    scored_from: int
    gpi_model: IdentifiedModel | None = None  # the GPI family's model, when another family's is `model`


def identify_recording(record: Series, validation: Series | None = None, holdout_fraction: float | None = None,
                       operators: int | None = None, diagnose_rounds: int = 0, output_unit: str = "m",
                       progress: Progress = None, source: str = "", workers: int = 1,
                       families: Sequence[str] = ("gpi",), max_fit_samples: int | None = None,
                       niceness: int = WORKER_NICENESS, more_validation: Sequence[Series] = ()) -> Identification:
    """Identify the model of a record (t [s], input [A], output [output_unit]).

    Validation: a separate record (`validation`, run from an idle stage), or the held-out tail of this one
    (`holdout_fraction`: the head is fitted, every model runs over the whole record and the errors count
    on the tail), or none. With diagnose_rounds > 0 (and validation data) the residual is diagnosed and
    the model deployed is the GPI with every effect it added; should the diagnosis fail, the plain fit is
    deployed and `warnings` says why in one line. The model's state is where it leaves the record, run from
    the start the diagnosis found for it (from rest without a diagnosis). workers: processes that fit the
    diagnosis's candidates and, meanwhile, the held-current families (the result is the same for any count);
    they run `niceness` levels below this process (0: at its priority).

    families (sma_stage.identify.families.FAMILIES): with validation data and more than the GPI named, each
    family is fitted on the same record and the one chosen by held-out error and BIC is deployed; the report's
    "families" table says what each gave. The compensator runs the model of either family.

    more_validation: further validation records (each run from an idle stage; beside `validation` or the held-out
    tail): every family is scored on each of them too, from rest, and chosen on the record it predicts worst, so
    that a choice cannot suit one shape of signal alone; the report's "validation_records" gives the deployed
    model's errors on every record, the first validation first. The diagnosis traces the residual of the first and
    judges each candidate effect on the record it predicts worst.

    max_fit_samples (None: FIT_SAMPLES; 0: never): a longer record is fitted, diagnosed and compared on a copy
    thinned by whole blocks to at most that many samples (Series.thinned; a validation record with the same
    block); hysteresis and the wires' lag are slow next to the rates that make records that long. The model's
    state and the report's "thinned" entry (with the deployed model's errors on the full-rate held-out samples)
    come from the full record.
    """
    if validation is not None and holdout_fraction is not None:
        raise InputError("give validation data or a holdout fraction, not both")
    if more_validation and validation is None and holdout_fraction is None:
        raise InputError("further validation records need a first one (validation data or a holdout fraction)")
    families = check_families(families)
    with Workers(workers, niceness) as pool:
        if diagnose_rounds > 0 or families != ("gpi",):
            pool.start()  # the processes load their kernels while this one fits the GPI
        return _identify(record, validation, holdout_fraction, operators, diagnose_rounds, output_unit, progress,
                         source, families, max_fit_samples, pool, tuple(more_validation))


def _identify(record: Series, validation: Series | None, holdout_fraction: float | None, operators: int | None,
              diagnose_rounds: int, output_unit: str, progress: Progress, source: str, families: tuple[str, ...],
              max_fit_samples: int | None, pool: Workers, more: tuple[Series, ...]) -> Identification:
    full_record, full_validation = record, validation
    block = _thinning_block(len(record), FIT_SAMPLES if max_fit_samples is None else max_fit_samples)
    record, validation = record.thinned(block), validation.thinned(block) if validation is not None else None
    more = tuple(series.thinned(block) for series in more)
    ident, valid, scored_from, validation_source = _split(record, validation, holdout_fraction)
    compared = families != ("gpi",) and valid is not None and float(np.ptp(valid.output[scored_from:])) > 0.0
    others = tuple((series.t, series.input, series.output) for series in more)
    held_out = HeldOut(valid.t, valid.input, valid.output, scored_from, others) if compared else None
    held = {family: start_held_current_fit(family, ident, output_unit, pool, held_out)
            for family in HELD_CURRENT_FAMILIES if compared and family in families}  # beside the GPI's fit
    with one_blas_thread():
        fit = fit_gpi(ident.input, ident.output, operators=operators, output_unit=output_unit, progress=progress)
    errors = _validation_errors(fit, valid, scored_from)
    report = fit_report(fit, errors, validation_source)
    report["samples"] = {"identification": len(ident), "validation": (len(valid) - scored_from) if valid else 0}
    found, warnings = None, []
    if diagnose_rounds > 0 and errors is not None:
        try:
            found = diagnose(ident, valid, base=fit, operators=operators, max_rounds=diagnose_rounds,
                             scored_from=scored_from, output_unit=fit.parameters.output_unit, progress=progress,
                             pool=pool, others=others)
        except Exception as error:  # noqa: BLE001 -- the fit stands whatever the diagnosis meets
            warnings.append(f"diagnosis failed, the plain GPI fit is kept: {type(error).__name__}: "
                            f"{' '.join(str(error).split())}")
    model = found.chain.model if found is not None else IdentifiedModel(fit.parameters, fit.operators)
    continued = full_record if holdout_fraction is not None else _head(full_record, block, len(ident))
    start = found.starts["identification"].start if found is not None else Start("rest")
    _, end_state = model.run(continued.t, continued.input, model.start_state(continued.t, continued.input, start))
    metadata = {"source": source or record.source, "samples": len(continued)}
    gpi_model = replace(model, state=end_state, metadata=metadata)
    model = gpi_model
    chosen = None
    if errors is not None and compared:
        chosen = _compare_families(families, fit, found, errors, ident, valid, scored_from, held, report, progress,
                                   pool, more)
        if chosen is not None:
            carried = chosen.start_state(continued.t, continued.input, start) if isinstance(chosen, IdentifiedModel) \
                else None
            model = replace(chosen, state=chosen.run(continued.t, continued.input, carried)[1], metadata=metadata)
    if found is not None:
        report["diagnosis"] = found.to_dict()
    held_out = deployed_held_out(report)
    if held_out is not None and valid is not None:
        model = replace(model, metadata={**model.metadata, **_held_out_metadata(
            held_out["rms_pct"], valid.output[scored_from:], record.output)})
    if block > 1:
        starts = found.starts if found is not None else {}
        start = starts.get("identification" if full_validation is None else "validation")
        report["thinned"] = _thinned_entry(model, start.start if start is not None else Start("rest"), full_record,
                                           full_validation, holdout_fraction, block, len(record), scored_from)
        warnings.extend(_thinning_cost(report["thinned"], held_out))
    if more and held_out is not None:
        report["validation_records"] = [{"source": validation_source, **held_out}] + [
            {"source": series.source, **errors_from_rest(model, series).to_dict()} for series in more]
    report["model"] = model.without_state().to_dict()
    report["compensation"] = compensation_notes(model)
    report["warnings"] = list(warnings)
    return Identification(model, fit, found, report, warnings, valid, scored_from,
                          gpi_model if chosen is not None else None)


def _held_out_metadata(rms_pct: float, held_out_output: np.ndarray, output: np.ndarray) -> dict[str, float]:
    """The model file's held_out_rms (rms_pct [%] of the held-out output's span, in the output's unit) and
    output_span (the identification output's span) that the model watch scales by."""
    return {"held_out_rms": rms_pct / 100.0 * float(np.ptp(held_out_output)), "output_span": float(np.ptp(output))}


def dynamics_held_refusal(model: AnyModel) -> str | None:
    """Why refit_hysteresis cannot refit this model (None: it can): it refits a GPI whose effects all transform
    its input (thermal_lag, wire_thermal, delay), with the density the paper gives."""
    if not isinstance(model, IdentifiedModel):
        return f"the model in force is a {getattr(model, 'kind', type(model).__name__)} model, not a GPI"
    if model.parameters.weights is not None:
        return "the model in force has free operator weights"
    others = [effect.kind for effect in model.effects if effect.role != "input"]
    return f"the model in force has the {', '.join(others)} effect" if others else None


# A tracking record seldom reaches the envelopes' knees: with their slopes free, the refit of a record that starts
# after a load step put the envelope's saturation at the record's lowest position in every seed tried (the model's
# reach at -5 A narrowed from about -500 to -281 um), and the compensator then drove the full current wherever
# a target lay a little beyond it (docs/watch.md, "On drift"; bench/bench_refit_reach.py).
REFIT_HELD = ("a2", "a6")


def refit_hysteresis(record: Series, model: IdentifiedModel, holdout_fraction: float, source: str = "",
                     held: Sequence[str] = REFIT_HELD) -> Identification:
    """Refit the GPI parameters of `model` on a record (t [s], input [A], output [m]) with its input effects (the
    wires' thermal dynamics, a delay) and the GPI parameters named in `held` (default the envelopes' slopes) kept
    as they are, warm-started from its parameters: for a record where the hysteresis moved (a load, the ambient
    temperature, creep) but the dynamics and the saturation are known better than the record shows them
    (closed-loop tracking, which rarely drives the stage to its ends). The model runs from rest over the whole
    record; the errors count on the held-out tail (holdout_fraction). InputError for a model
    dynamics_held_refusal refuses, or a record that cannot be fitted."""
    refusal = dynamics_held_refusal(model)
    if refusal is not None:
        raise InputError(f"the hysteresis alone cannot be refitted: {refusal}")
    ident, valid, scored_from, validation_source = _split(record, None, holdout_fraction)
    seen = model.without_state().gpi_input(record.t, record.input)
    with one_blas_thread():
        fit = fit_gpi(seen[:scored_from], ident.output, operators=model.operators, initial=model.parameters,
                      output_unit=model.output_unit, hold=held)
    refitted = replace(model, parameters=fit.parameters, state=None)
    predicted, end_state = refitted.run(record.t, record.input)
    errors = error_metrics(record.output[scored_from:], predicted[scored_from:])
    report = fit_report(fit, errors, validation_source)
    report["samples"] = {"identification": len(ident), "validation": len(record) - scored_from}
    report["refit"] = ("the hysteresis (GPI parameters) refitted from the model in force, its effects "
                       f"({', '.join(model.effect_names) or 'none'}) and {', '.join(held) or 'no GPI parameter'} held")
    metadata = {"source": source or record.source, "samples": len(record),
                **_held_out_metadata(errors.rms_pct, record.output[scored_from:], record.output)}
    refitted = replace(refitted, state=end_state, metadata=metadata)
    report["model"] = refitted.without_state().to_dict()
    report["compensation"] = compensation_notes(refitted)
    report["warnings"] = []
    return Identification(refitted, fit, None, report, [], valid, scored_from)


def _thinning_block(samples: int, limit: int) -> int:
    """Samples per block that bring a record of `samples` to at most `limit` (1: not thinned; limit 0: never)."""
    if limit <= 0 or samples <= limit:
        return 1
    return -(-samples // limit)


def _head(full: Series, block: int, thinned_samples: int) -> Series:
    """The full-rate samples a thinned head of thinned_samples covers."""
    return full.slice(None, len(full) % block + block * thinned_samples) if block > 1 else full.slice(None, thinned_samples)


def _thinned_entry(model: AnyModel, start: Start, full_record: Series,
                   full_validation: Series | None, holdout_fraction: float | None, block: int, fitted: int,
                   scored_from: int) -> dict:
    """The report's "thinned": how the record was thinned and the deployed model's errors on the full-rate
    validation samples (the held-out tail's, or the validation record's), run from the start the diagnosis found
    for that record (rest for a two-wire model)."""
    entry: dict[str, object] = {"samples": len(full_record), "fitted_samples": fitted, "block": block}
    if full_validation is None and holdout_fraction is None:
        return entry
    valid = full_validation if full_validation is not None else full_record
    first = 0 if full_validation is not None else len(full_record) % block + block * scored_from
    plain = model.without_state()
    predicted = (plain.predict_from(valid.t, valid.input, start) if isinstance(plain, IdentifiedModel)
                 else plain.predict(valid.t, valid.input))
    entry["validation_full_rate"] = error_metrics(valid.output[first:], predicted[first:]).to_dict()
    return entry


def _thinning_cost(entry: dict, held_out: dict | None) -> list[str]:
    """A warning when the model misses the full-rate held-out samples by much more than the thinned ones."""
    full_rate = entry.get("validation_full_rate")
    if held_out is None or full_rate is None or full_rate["rms_pct"] <= THINNING_COST_WARNING * held_out["rms_pct"]:
        return []
    return [f"fitted on a copy thinned {entry['block']}-fold ({entry['samples']} samples to {entry['fitted_samples']}): "
            f"on every held-out sample the model misses by {full_rate['rms_pct']:.3g} % RMS against "
            f"{held_out['rms_pct']:.3g} % on the thinned ones; the record's dynamics are fast for the blocks: fit "
            "every sample (max_fit_samples 0, gpi_tool --max-fit-samples 0)"]


def deployed_held_out(report: dict) -> dict | None:
    """The held-out errors (rms_pct, max_pct [% of the held-out span]) of the model a report deploys: the chosen
    family's, else the diagnosed model's, else the plain fit's; None without validation data."""
    chosen = [row for row in report.get("families", ()) if row["chosen"]]
    if chosen:
        return chosen[0]["validation"]
    diagnosis = report.get("diagnosis")
    return diagnosis["after"]["validation"] if diagnosis is not None else report.get("validation")


def errors_from_rest(model: AnyModel, series: Series) -> ErrorMetrics:
    """The model's errors on a record (t [s], input [A], output) it runs from rest over."""
    return error_metrics(series.output, model.without_state().predict(series.t, series.input))


def _compare_families(families: tuple[str, ...], fit: FitResult, found: Diagnosis | None, errors: ErrorMetrics,
                      ident: Series, valid: Series, scored_from: int, held: dict[str, Pending], report: dict,
                      progress: Progress, pool: Workers, more: tuple[Series, ...] = ()) -> AnyModel | None:
    """Fit the free-weight GPI (in the pool's processes, while the held-current families' fits, begun with `held`,
    are finished), score every family on the further validation records (`more`) and fill report["families"];
    the chosen family's model (without state) when it is not the GPI, else None."""
    gpi = _gpi_row(fit, found, errors, ident)
    rows, models = [], []
    if "gpi" in families:
        rows.append(gpi)
        models.append(None)
    for fitting in held.values():
        fitting.begin()  # the two-wire polish, longer than the free-weight fit, queued first
    free_weights = None
    if "gpi_free" in families:
        starts = found.starts if found is not None else {}
        ident_start = starts["identification"].start if "identification" in starts else Start("rest")
        valid_start = starts["validation"].start if "validation" in starts else Start("rest")
        gpi_model = found.chain.model if found is not None else IdentifiedModel(fit.parameters, fit.operators)
        free_weights = pool.submit(fit_free_weights_row, gpi_model, gpi.parameters, ident, ident_start, valid,
                                   scored_from, valid_start)
    held_rows = []
    for family, fitting in held.items():
        if progress is not None:
            progress(f"the {family.replace('_', '-')} model's fit")
        row, found_family = held_current_row(family, fitting, valid, scored_from)
        held_rows.append((row, found_family.model.without_state() if found_family is not None else None))
    if free_weights is not None:
        row, free = free_weights.result()
        rows.append(row)
        models.append(free)
    for row, model in held_rows:
        rows.append(row)
        models.append(model)
    if more:
        gpi_model = found.chain.model if found is not None else IdentifiedModel(fit.parameters, fit.operators)
        rows = [replace(row, more_validation=tuple(
            None if row.validation is None or (model is None and row.family != "gpi")
            else errors_from_rest(model if model is not None else gpi_model, series) for series in more))
            for row, model in zip(rows, models, strict=True)]
    chosen = choose(rows)
    if chosen is not None:
        rows[chosen] = replace(rows[chosen], chosen=True)
    report["families"] = [row.to_dict() for row in rows]
    return models[chosen] if chosen is not None else None


def _gpi_row(fit: FitResult, found: Diagnosis | None, errors: ErrorMetrics, ident: Series) -> FamilyRow:
    """The GPI family's row: the plain fit, or the GPI with the effects the diagnosis added."""
    if found is None:
        return FamilyRow("gpi", f"GPI, {fit.operators} operators", fit.parameter_count, fit.identification, errors,
                         information_criterion(fit.cost, fit.samples, fit.parameter_count))
    chain = found.chain
    count = chain.last.parameter_count + sum(len(stage.parameters) for stage in chain.stages[:-1])
    added = " + ".join(chain.effects) or "no effect"
    predicted = chain.predict(ident.t, ident.input)
    bic = information_criterion(float(np.sum((ident.output - predicted) ** 2)), len(ident), count)
    return FamilyRow("gpi", f"GPI, {chain.last.operators} operators, {added}", count,
                     error_metrics(ident.output, predicted), found.after, bic)


def _split(record: Series, validation: Series | None, holdout_fraction: float | None
           ) -> tuple[Series, Series | None, int, str]:
    """(identification data, validation data, first scored validation sample, where validation comes from)."""
    if holdout_fraction is not None:
        if not 0.0 < holdout_fraction < 1.0:
            raise InputError(f"holdout fraction must be between 0 and 1, got {holdout_fraction:g}")
        held_out = len(record) - round((1.0 - holdout_fraction) * len(record))
        if held_out < MIN_HELD_OUT or len(record) - held_out < MIN_SAMPLES:
            raise InputError(f"holdout fraction {holdout_fraction:g} leaves {held_out} of {len(record)} samples for "
                             f"validation and {len(record) - held_out} for the fit (at least {MIN_HELD_OUT} and "
                             f"{MIN_SAMPLES} are needed)")
        ident, tail = record.split(1.0 - holdout_fraction)
        source = (f"held-out tail of the recording: last {100 * holdout_fraction:g} % ({len(tail)} samples, "
                  f"t = {tail.t[0]:.3f} to {tail.t[-1]:.3f} s), model run over the whole recording")
        return ident, record, len(ident), source
    if validation is not None:
        return record, validation, 0, validation.source
    return record, None, 0, "none (no validation data)"


def _validation_errors(fit: FitResult, valid: Series | None, scored_from: int) -> ErrorMetrics | None:
    """The plain fit's errors on the scored validation samples (None without validation or excitation)."""
    if valid is None or np.ptp(valid.output[scored_from:]) <= 0.0:
        return None
    return error_metrics(valid.output[scored_from:], predict(fit, valid.input)[scored_from:])
