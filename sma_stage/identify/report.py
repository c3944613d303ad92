"""The identification report: the design's JSON document, a Markdown summary and PNG figures."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sma_stage.identify.diagnosis import Diagnosis
from sma_stage.identify.fit import FitResult
from sma_stage.identify.metrics import ErrorMetrics
from sma_stage.io.atomic import atomic_write_text
from sma_stage.io.plain import strict_json
from sma_stage.io.series import Series
from sma_stage.model.parameters import MODEL_KIND


def fit_report(fit: FitResult, validation: ErrorMetrics | None, validation_source: str) -> dict:
    """The JSON document's gpi_fit (the plain GPI fit, with its standard errors), identification, validation and
    fit_seconds keys; the pipeline adds `model`, the model chosen and written."""
    return {
        "gpi_fit": {
            "kind": MODEL_KIND,
            "operators": fit.operators,
            "output_unit": fit.parameters.output_unit,
            "parameters": fit.parameters.to_dict(),
            "standard_errors": dict(fit.standard_errors),
        },
        "identification": fit.identification.to_dict(),
        "validation": validation.to_dict() if validation else None,
        "validation_source": validation_source,
        "fit_seconds": fit.seconds,
    }


def write_json(path: Path, report: dict) -> None:
    """The report as indented strict JSON (non-finite numbers as null), atomically."""
    atomic_write_text(path, strict_json(report, indent=2) + "\n")


def markdown_summary(report: dict, title: str) -> str:
    """A person's one-page reading of the report."""
    model = report["gpi_fit"]
    chosen = next((row for row in report.get("families") or [] if row["chosen"]), None)
    written = [] if chosen is None or chosen["family"] == "gpi" else [
        f"Model written (model.yaml): **{chosen['model']}**, chosen among the families below; model_gpi.yaml holds "
        "the GPI family's model. The GPI fit:", ""]
    lines = [f"# {title}", "", *written, f"GPI model, {model['operators']} operators, output in "
             f"{model['output_unit']}.", "",
             "| parameter | value | standard error |", "|---|---|---|"]
    for name, value in model["parameters"].items():
        lines.append(f"| {name} | {value:.6g} | {model['standard_errors'].get(name, float('nan')):.3g} |")
    lines += ["", "| data | samples | RMS error [% of span] | max error [% of span] |", "|---|---|---|---|"]
    for key in ("identification", "validation"):
        if report.get(key):
            errors = report[key]
            lines.append(f"| {key} | {errors['samples']} | {errors['rms_pct']:.3f} | {errors['max_pct']:.3f} |")
    lines += ["", f"Validation data: {report['validation_source']}. Fit time: {report['fit_seconds']:.2f} s."]
    if report.get("validation_records"):
        lines += ["", "The model written, run from rest on every validation record:", "",
                  "| validation record | samples | RMS error [% of span] | max error [% of span] |", "|---|---|---|---|"]
        lines += [f"| {record['source']} | {record['samples']} | {record['rms_pct']:.3f} | {record['max_pct']:.3f} |"
                  for record in report["validation_records"]]
    if "diagnosis" in report:
        lines += diagnosis_markdown(report["diagnosis"], len(report.get("validation_records", ())) > 1)
    if report.get("families"):
        lines += families_markdown(report["families"])
    if report.get("compensation"):
        lines += ["", "## Compensation of the model written", ""]
        lines += [f"- {kind}: {how}" for kind, how in report["compensation"].items()]
    return "\n".join(lines) + "\n"


def families_markdown(families: list[dict]) -> list[str]:
    """The model families compared on the same record, the chosen one marked (its model is model.yaml)."""
    several = any("worst_validation" in row for row in families)
    worst_column = " worst validation record RMS / max % |" if several else ""
    lines = ["", "## Model families", "", "| family | model | parameters | identification RMS / max % | "
             f"validation RMS / max % |{worst_column} BIC | chosen |", "|---" * (7 + several) + "|"]
    for row in families:
        if row["not_fitted"]:
            lines.append(f"| {row['family']} | not fitted: {row['not_fitted']} |" + " |" * (5 + several))
            continue
        ident, valid, worst = (f"{errors['rms_pct']:.2f} / {errors['max_pct']:.1f}" if errors else "-"
                               for errors in (row["identification"], row["validation"], row.get("worst_validation")))
        lines.append(f"| {row['family']} | {row['model']} | {row['parameters']} | {ident} | {valid} | "
                     + (f"{worst} | " if several else "") + f"{row['bic']:.0f} | {'**yes**' if row['chosen'] else ''} |")
    return lines


def diagnosis_markdown(diagnosis: dict, several: bool = False) -> list[str]:
    """The diagnosis part of the summary: the effects added, the evidence, each round's candidates (several:
    judged on the validation record each predicts worst)."""
    before, after = diagnosis["before"]["validation"], diagnosis["after"]["validation"]
    added = " + ".join(diagnosis.get("effects") or [diagnosis["effect"]])
    parameters = ", ".join(f"{key} = {value:.4g}" for key, value in diagnosis["parameters"].items())
    lines = ["", "## Diagnosis", "", f"Effects the GPI lacks, in the order found: **{added}** {parameters}", "",
             f"Validation error before: RMS {before['rms_pct']:.3f} %, max {before['max_pct']:.3f} %; "
             f"after: RMS {after['rms_pct']:.3f} %, max {after['max_pct']:.3f} %.", "",
             "| residual test (plain GPI) | value and threshold |", "|---|---|"]
    lines += [f"| {name} | {text} |" for name, text in diagnosis["evidence"].items()]
    rounds = diagnosis.get("rounds") or [{"added": diagnosis["effect"], "candidates": diagnosis.get("candidates", [])}]
    for number, found in enumerate(rounds, start=1):
        lines += ["", f"Round {number}: added **{found['added']}**.", "",
                  f"| candidate | parameters | {'worst ' if several else ''}validation RMS % | delta BIC | kept | why |",
                  "|---|---|---|---|---|---|"]
        for candidate in found["candidates"]:
            if not candidate.get("fitted", True):
                lines.append(f"| {candidate['effect']} | | | | no | {candidate['reason']} |")
                continue
            values = ", ".join(f"{key} = {value:.4g}" for key, value in candidate["parameters"].items())
            lines.append(f"| {candidate['effect']} | {values} | {candidate['validation']['rms_pct']:.3f} | "
                         f"{candidate['delta_bic']:.1f} | {'yes' if candidate['accepted'] else 'no'} | "
                         f"{candidate['reason']} |")
    return lines


def write_fit_figures(path: Path, ident: Series, fit: FitResult, valid: Series | None,
                      valid_predicted: np.ndarray | None) -> None:
    """Measured and model loops and the residual against time, for identification (and validation)."""
    from sma_stage.plots import Panel, save_panels

    unit = fit.parameters.output_unit
    panels = [
        Panel("identification: loop", ident.input, [("measured", ident.output), ("model", fit.predicted)],
              "input [A]", f"output [{unit}]"),
        Panel("identification: residual", ident.t, [("measured - model", fit.residual)], "time [s]", unit),
    ]
    if valid is not None and valid_predicted is not None:
        panels += [
            Panel("validation: loop", valid.input, [("measured", valid.output), ("model", valid_predicted)],
                  "input [A]", f"output [{unit}]"),
            Panel("validation: residual", valid.t, [("measured - model", valid.output - valid_predicted)],
                  "time [s]", unit),
        ]
    save_panels(path, panels, columns=2)


def write_diagnosis_figures(out_dir: Path, valid: Series, diagnosis: Diagnosis, unit: str) -> list[Path]:
    """Loops and residuals before and after the added effect, and the residual tests with their bands."""
    from sma_stage.plots import Panel, save_panels

    before, after = diagnosis.validation_predicted_before, diagnosis.validation_predicted_after
    label = "GPI + " + " + ".join(diagnosis.effects) if diagnosis.effects else "GPI (nothing added)"
    loops = [
        Panel("validation loop: plain GPI", valid.input, [("measured", valid.output), ("GPI", before)],
              "input [A]", f"output [{unit}]"),
        Panel(f"validation loop: {label}", valid.input, [("measured", valid.output), (label, after)],
              "input [A]", f"output [{unit}]"),
        Panel("validation residual against time", valid.t,
              [("plain GPI", valid.output - before), (label, valid.output - after)], "time [s]", unit),
    ]
    tests = diagnosis.tests_before
    correlations = [
        Panel("residual autocorrelation (plain GPI)", tests.autocorrelation_lags_s,
              [("autocorrelation", tests.autocorrelation)], "lag [s]", "correlation", band=tests.band),
        Panel("residual-input cross-correlation (plain GPI); band: the lagged-input test's",
              tests.cross_correlation_lags_s, [("cross-correlation", tests.cross_correlation)], "lag [s]",
              "correlation", band=tests.checks["lagged_input"].threshold),
    ]
    paths = [out_dir / "diagnosis_loops.png", out_dir / "diagnosis_correlations.png"]
    save_panels(paths[0], loops, columns=3)
    save_panels(paths[1], correlations, columns=2, kind="line")
    return paths
