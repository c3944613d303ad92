"""gpi_tool simulate: drive the stage simulator offline with a named or recorded input signal."""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np

from sma_stage.errors import InputError
from sma_stage.io.csv_io import write_csv
from sma_stage.io.series import make_series
from sma_stage.plant import Effects, StageConfig, simulate
from sma_stage.plant.simulator import PROGRESS_SAMPLES
from sma_stage.signals import (
    IDENTIFICATION_DURATION_S,
    designed_identification_signal,
    paper_identification_signal,
    paper_validation_signal,
)

SIGNALS = {"identification": paper_identification_signal, "validation": paper_validation_signal,
           "designed": designed_identification_signal}
MAX_SAMPLES = 10_000_000  # about 0.5 GB of CSV and a few minutes of simulation


def parse_settings(items: list[str] | None, what: str) -> dict[str, float]:
    """NAME=VALUE pairs from the command line as floats."""
    settings = {}
    for item in items or []:
        name, separator, value = item.partition("=")
        try:
            settings[name.strip()] = float(value)
        except ValueError:
            separator = ""
        if not separator:
            raise InputError(f"--{what} takes NAME=NUMBER, got {item!r}")
    return settings


def input_signal(args: argparse.Namespace) -> tuple[np.ndarray, float]:
    """The current sequence [A] and its sample period [s] from --input (a signal name or a CSV file)."""
    if args.input in SIGNALS:
        if not (0.0 < args.rate_hz < math.inf and 0.0 < args.duration < math.inf):
            raise InputError("--rate-hz and --duration must be positive and finite")
        samples = args.duration * args.rate_hz
        if samples > MAX_SAMPLES:
            raise InputError(f"--duration {args.duration:g} s at --rate-hz {args.rate_hz:g} is {samples:.3g} samples; "
                             f"simulate writes at most {MAX_SAMPLES:,} (shorten the run or lower the rate)")
        dt = 1.0 / args.rate_hz
        t = np.arange(0.0, args.duration, dt)
        return SIGNALS[args.input](t), dt
    from sma_stage.io.csv_io import read_csv

    recorded = read_csv(args.input, columns={"t": "t", "input": "input", "output": "input"})
    periods = np.diff(recorded.t)
    if recorded.time_is_index or np.ptp(periods) > 1e-6 * periods.mean():
        raise InputError(f"{args.input}: simulate needs evenly sampled time in seconds in column t")
    return np.asarray(recorded.input), float(periods.mean())


def report_progress(done: int, total: int) -> None:
    """Progress of a long simulation on standard error (--json output stays clean)."""
    if total > PROGRESS_SAMPLES:
        print(f"gpi_tool: simulated {done:,} of {total:,} samples", file=sys.stderr, flush=True)


def run_simulate(args: argparse.Namespace) -> dict:
    """Simulate and write t, input, output (the measured position [m]) as CSV."""
    current, dt = input_signal(args)
    config = StageConfig.from_mapping(parse_settings(args.set, "set"))
    effects = Effects.from_mapping(parse_settings(args.effect, "effect"))
    result = simulate(current, dt, config=config, effects=effects, seed=args.seed, progress=report_progress)
    series = make_series(result.t_s, result.current_a, result.measured_position_m,
                         source=f"simulator: {args.input}")
    write_csv(args.out, series)
    return {"file": str(args.out), "samples": int(result.t_s.size), "sample_period_s": dt,
            "position_range_m": [float(result.position_m.min()), float(result.position_m.max())],
            "effects": effects.as_dict()}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The simulate subcommand's options."""
    parser.add_argument("--input", required=True, metavar="SIGNAL",
                        help="identification | validation (the paper's signals) | designed (gpi_tool excitation designed) | "
                             "a CSV file with t,input")
    parser.add_argument("--duration", type=float, default=IDENTIFICATION_DURATION_S, help="seconds (named signals)")
    parser.add_argument("--rate-hz", type=float, default=10.0, help="sample rate (named signals)")
    parser.add_argument("--effect", action="append", metavar="NAME=VALUE",
                        help="switch an effect on, e.g. sensor_delay_s=2 (repeatable)")
    parser.add_argument("--set", action="append", metavar="NAME=VALUE",
                        help="change a stage parameter, e.g. flexure_stiffness_n_m=6e5 (repeatable)")
    parser.add_argument("--seed", type=int, default=0, help="sensor-noise seed")
    parser.add_argument("--out", required=True, help="CSV file to write (t, input, output)")
    parser.add_argument("--json", action="store_true", help="print a JSON summary")
