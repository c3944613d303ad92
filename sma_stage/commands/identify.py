"""gpi_tool fit and gpi_tool diagnose: read data, fit or diagnose, write the model, report and figures."""

from __future__ import annotations

import argparse
import os
import resource
import sys
from pathlib import Path

from sma_stage.errors import InputError
from sma_stage.identify.families import FAMILIES
from sma_stage.identify.fit import predict
from sma_stage.identify.pipeline import GPI_MODEL_FILE, Identification, identify_recording
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
                       output_topic=args.output_topic, joint_name=args.joint,
                       default_input_topic=args.default_input_topic)


def progress_line(text: str) -> None:
    """Progress on standard error, so --json output stays clean."""
    print(f"gpi_tool: {text}", file=sys.stderr, flush=True)


FIT_BYTES_PER_ROW = 400  # peak memory of gpi_tool fit per row of its records, over the interpreter's own
BASE_BYTES = 200 << 20  # the interpreter with numpy, scipy, numba and the package (bench/bench_records.py)


def check_memory(paths: list[Path | None]) -> None:
    """InputError in one line when the CSV records given would need more memory than this machine has free
    (estimated from their size and FIT_BYTES_PER_ROW, docs/reliability.md), before anything is read."""
    rows = sum(estimated_rows(path) for path in paths if path is not None and path.is_file())
    needed = BASE_BYTES + rows * FIT_BYTES_PER_ROW
    available = available_memory_bytes()
    if available is not None and needed > available:
        raise InputError(f"the records hold about {rows:,} rows: the fit needs about {needed / 2**30:.1f} GiB and "
                         f"{available / 2**30:.1f} GiB are free (thin the record, e.g. keep every 10th row: "
                         "hysteresis is slow next to a 1 kHz logger)")


def estimated_rows(path: Path, sample_bytes: int = 1 << 16) -> int:
    """Rows of a CSV file estimated from its size and the length of its first lines."""
    size = path.stat().st_size
    with open(path, "rb") as file:
        head = file.read(sample_bytes)
    lines = head.count(b"\n")
    return int(size / (len(head) / lines)) if lines else 1


def available_memory_bytes() -> int | None:
    """The memory this process may still take: the least of the free memory (MemAvailable), its cgroup's room
    and its address-space limit; None when none of them can be read."""
    limits = []
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                limits.append(int(line.split()[1]) * 1024)
    except (OSError, ValueError, IndexError):
        pass
    try:
        maximum = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if maximum != "max":
            limits.append(int(maximum) - int(Path("/sys/fs/cgroup/memory.current").read_text()))
    except (OSError, ValueError):
        pass
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft != resource.RLIM_INFINITY:
        limits.append(soft - _resident_bytes())
    return min(limits) if limits else None


def _resident_bytes() -> int:
    try:
        return int(Path("/proc/self/statm").read_text().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError):
        return 0


def run_fit(args: argparse.Namespace) -> dict:
    """Fit the GPI; validate on --validate data when given; write model.yaml, report.json/.md, fit.png."""
    check_memory([args.data, *(args.validate or [])])
    with RunFolder(args.out) as run:
        data = read_data(args.data, args)
        valid, *more = [read_data(path, args) for path in args.validate] if args.validate else [None]
        found = identify_recording(data, valid, args.holdout, operators=args.operators, output_unit=args.unit,
                                   progress=progress_line, source=str(args.data), max_fit_samples=args.max_fit_samples,
                                   more_validation=more)
        write_outputs(run.staging, found, "GPI fit")
        ident = data.split(1.0 - args.holdout)[0] if args.holdout else data
        valid_predicted = predict(found.fit, found.validation.input) if found.validation else None
        write_fit_figures(run.staging / "fit.png", ident, found.fit, found.validation, valid_predicted)
    print_summary(args, found, "GPI fit")
    return found.report


def run_diagnose(args: argparse.Namespace) -> dict:
    """Fit, test the validation residual, add the effects the model lacks, compare the model families (all of
    them unless --families names some), report before and after; the model written is the chosen family's."""
    check_memory([args.data, *(args.validate or [])])
    with RunFolder(args.out) as run:
        data = read_data(args.data, args)
        valid, *more = [read_data(path, args) for path in args.validate] if args.validate else [None]
        found = identify_recording(data, valid, args.holdout, operators=args.operators,
                                   diagnose_rounds=args.rounds, output_unit=args.unit, progress=progress_line,
                                   source=str(args.data), workers=args.workers,
                                   families=args.families or FAMILIES,
                                   max_fit_samples=args.max_fit_samples, more_validation=more)
        if found.diagnosis is None:
            raise InputError(found.warnings[0] if found.warnings else "the diagnosis did not run")
        write_outputs(run.staging, found, "GPI fit and residual diagnosis")
        write_diagnosis_figures(run.staging, found.validation, found.diagnosis, found.fit.parameters.output_unit)
    print_summary(args, found, "GPI fit and residual diagnosis")
    return found.report


def write_outputs(folder: Path, found: Identification, title: str) -> None:
    """model.yaml (the identified model), report.json and report.md into folder."""
    found.model.save(folder / "model.yaml")
    if found.gpi_model is not None:
        found.gpi_model.save(folder / GPI_MODEL_FILE)
    write_json(folder / "report.json", found.report)
    atomic_write_text(folder / "report.md", markdown_summary(found.report, title))


def print_summary(args: argparse.Namespace, found: Identification, title: str) -> None:
    """The report's summary on standard output, unless --json (then the JSON alone goes there)."""
    if not args.json:
        print(markdown_summary(found.report, title))
