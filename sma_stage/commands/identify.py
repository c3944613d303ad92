"""gpi_tool fit and gpi_tool diagnose: read data, fit or diagnose, write the model, report and figures."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sma_stage.errors import InputError
from sma_stage.identify.fit import predict
from sma_stage.identify.pipeline import Identification, identify_recording
from sma_stage.identify.report import (
    markdown_summary,
    write_diagnosis_figures,
    write_fit_figures,
    write_json,
)
from sma_stage.io.atomic import atomic_write_text
from sma_stage.io.load import load_series
from sma_stage.io.run_folder import RunFolder
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
    with RunFolder(args.out) as run:
        data = read_data(args.data, args)
        valid = read_data(args.validate, args) if args.validate else None
        found = identify_recording(data, valid, args.holdout, operators=args.operators, output_unit=args.unit,
                                   progress=progress_line, source=str(args.data))
        write_outputs(run.staging, found, "GPI fit")
        ident = data.split(1.0 - args.holdout)[0] if args.holdout else data
        valid_predicted = predict(found.fit, found.validation.input) if found.validation else None
        write_fit_figures(run.staging / "fit.png", ident, found.fit, found.validation, valid_predicted)
    print_summary(args, found, "GPI fit")
    return found.report


def run_diagnose(args: argparse.Namespace) -> dict:
    """Fit, test the validation residual, add the effects the model lacks, report before and after; the
    model written is the GPI with those effects."""
    with RunFolder(args.out) as run:
        data = read_data(args.data, args)
        valid = read_data(args.validate, args) if args.validate else None
        found = identify_recording(data, valid, args.holdout, operators=args.operators,
                                   diagnose_rounds=args.rounds, output_unit=args.unit, progress=progress_line,
                                   source=str(args.data), workers=args.workers)
        if found.diagnosis is None:
            raise InputError(found.warnings[0] if found.warnings else "the diagnosis did not run")
        write_outputs(run.staging, found, "GPI fit and residual diagnosis")
        write_diagnosis_figures(run.staging, found.validation, found.diagnosis, found.fit.parameters.output_unit)
    print_summary(args, found, "GPI fit and residual diagnosis")
    return found.report


def write_outputs(folder: Path, found: Identification, title: str) -> None:
    """model.yaml (the identified model), report.json and report.md into folder."""
    found.model.save(folder / "model.yaml")
    write_json(folder / "report.json", found.report)
    atomic_write_text(folder / "report.md", markdown_summary(found.report, title))


def print_summary(args: argparse.Namespace, found: Identification, title: str) -> None:
    """The report's summary on standard output, unless --json (then the JSON alone goes there)."""
    if not args.json:
        print(markdown_summary(found.report, title))
