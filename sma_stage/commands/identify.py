"""gpi_tool fit and gpi_tool diagnose: read data, fit or diagnose, write the model, report and figures."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sma_stage.errors import InputError
from sma_stage.identify.diagnosis import diagnose
from sma_stage.identify.fit import FitResult, fit_gpi, predict
from sma_stage.identify.metrics import error_metrics
from sma_stage.identify.report import (
    diagnosis_report,
    fit_report,
    markdown_summary,
    write_diagnosis_figures,
    write_fit_figures,
    write_json,
)
from sma_stage.io.atomic import atomic_write_text
from sma_stage.io.load import load_series
from sma_stage.io.series import Series


def parse_columns(text: str | None) -> dict[str, str | None] | None:
    """--columns "t=time,input=current,output=pos" (t= empty: the sample index is the time)."""
    if not text:
        return None
    mapping: dict[str, str | None] = {}
    for item in text.split(","):
        key, separator, value = item.partition("=")
        key = key.strip()
        if not separator or key not in ("t", "input", "output"):
            raise InputError(f"--columns takes t=NAME,input=NAME,output=NAME, got {item!r}")
        mapping[key] = value.strip() or None
    return mapping


def read_data(path: Path, args: argparse.Namespace) -> Series:
    """One data set from a CSV file or a rosbag2 directory, as the command line names it."""
    return load_series(path, columns=parse_columns(args.columns), input_topic=args.input_topic,
                       output_topic=args.output_topic, joint_name=args.joint)


def progress_line(text: str) -> None:
    """Progress on standard error, so --json output stays clean."""
    print(f"gpi_tool: {text}", file=sys.stderr, flush=True)


def run_fit(args: argparse.Namespace) -> dict:
    """Fit the GPI; validate on --validate data when given; write model.yaml, report.json/.md, fit.png."""
    ident = read_data(args.data, args)
    valid = read_data(args.validate, args) if args.validate else None
    fit = fit_gpi(ident.input, ident.output, operators=args.operators, output_unit=args.unit,
                  progress=progress_line)
    valid_predicted = predict(fit, valid.input) if valid else None
    validation = error_metrics(valid.output, valid_predicted) if valid else None
    report = fit_report(fit, validation, valid.source if valid else "none (no --validate data)")
    write_outputs(args, report, "GPI fit", fit)
    write_fit_figures(args.out / "fit.png", ident, fit, valid, valid_predicted)
    return report


def run_diagnose(args: argparse.Namespace) -> dict:
    """Fit, test the validation residual, add the effect the model lacks, report before and after."""
    ident = read_data(args.data, args)
    valid = read_data(args.validate, args)
    diagnosis = diagnose((ident.t, ident.input, ident.output), (valid.t, valid.input, valid.output),
                         operators=args.operators, progress=progress_line, output_unit=args.unit)
    report = diagnosis_report(diagnosis, valid.source)
    write_outputs(args, report, "GPI fit and residual diagnosis", diagnosis.base)
    write_diagnosis_figures(args.out, valid, diagnosis, diagnosis.base.parameters.output_unit)
    return report


def write_outputs(args: argparse.Namespace, report: dict, title: str, fit: FitResult) -> None:
    """model.yaml, report.json and report.md under --out; the summary also to stderr unless --json."""
    args.out.mkdir(parents=True, exist_ok=True)
    metadata = {"source": str(args.data), "identification_rms_pct": fit.identification.rms_pct}
    fit.parameters.to_yaml(args.out / "model.yaml", fit.operators, metadata=metadata)
    write_json(args.out / "report.json", report)
    summary = markdown_summary(report, title)
    atomic_write_text(args.out / "report.md", summary)
    if not args.json:
        print(summary)
