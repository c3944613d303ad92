"""gpi_tool excitation: write an identification current signal (t, input) as CSV, to play on a stage."""

from __future__ import annotations

import argparse
import math

import numpy as np

from sma_stage.commands.simulate import MAX_SAMPLES
from sma_stage.errors import InputError
from sma_stage.experiment.design import designed_signal
from sma_stage.experiment.probe import ProbeResult, analyse_probe, probe_duration_s, probe_signal
from sma_stage.io.atomic import atomic_write_text
from sma_stage.io.load import load_series
from sma_stage.signals import (
    IDENTIFICATION_DURATION_S,
    LEVELS_HOLD_S,
    designed_identification_signal,
    held_levels_signal,
    paper_identification_signal,
    paper_validation_signal,
)

KINDS = ("paper", "designed", "probe", "validation", "levels")
PROBE_S = probe_duration_s(IDENTIFICATION_DURATION_S)
DEFAULT_DURATION_S = {"paper": IDENTIFICATION_DURATION_S, "designed": IDENTIFICATION_DURATION_S, "probe": PROBE_S,
                      "validation": IDENTIFICATION_DURATION_S, "levels": IDENTIFICATION_DURATION_S}
DESIGNED_AFTER_PROBE_S = IDENTIFICATION_DURATION_S - PROBE_S  # designed --probe: with the probe, 1000 s


def excitation(kind: str, duration_s: float, step_s: float, max_current_a: float = 5.0, seed: int = 0,
               probe: ProbeResult | None = None, hold_s: float = LEVELS_HOLD_S) -> tuple[np.ndarray, np.ndarray]:
    """(t [s], current [A]) of the named excitation: `paper`, the decaying sine scaled to max_current_a at its
    start (5 A falling to 3.6 A at 5 A); `probe`, sma_stage.experiment.probe's held currents up to
    max_current_a; `designed`, built on what a probe found (sma_stage.experiment.design) when one is given,
    else sma_stage.signals.designed_identification_signal (fixed fractions of max_current_a); the validation
    shapes `validation`, the paper's two cosines scaled as `paper` is, and `levels`, held random levels within
    +-max_current_a, hold_s [s] each, drawn by seed."""
    if kind not in KINDS:
        raise InputError(f"excitation must be one of {', '.join(KINDS)}, got {kind!r}")
    for name, value in (("--duration", duration_s), ("--step", step_s), ("--max-current", max_current_a),
                        ("--hold", hold_s)):
        if not 0.0 < value < math.inf:
            raise InputError(f"{name} must be positive and finite, got {value:g}")
    if duration_s / step_s > MAX_SAMPLES:
        raise InputError(f"--duration {duration_s:g} s at --step {step_s:g} s is more than {MAX_SAMPLES:,} samples")
    t = np.arange(0.0, duration_s, step_s)
    if kind == "paper":
        scale = max_current_a / 5.0
        return t, paper_identification_signal(t, 5.0 * scale, 3.6 * scale, duration_s=duration_s)
    if kind == "probe":
        return t, probe_signal(t, max_current_a, duration_s)
    if kind == "validation":
        return t, paper_validation_signal(t, max_current_a / 5.0)
    if kind == "levels":
        return t, held_levels_signal(t, max_current_a, hold_s, seed)
    if probe is not None:
        return t, designed_signal(t, probe, duration_s, seed)
    return t, designed_identification_signal(t, max_current_a, duration_s, seed)


def read_probe(path: str) -> ProbeResult:
    """What the probe recorded in a file (t, input, output: a CSV or a rosbag2) found."""
    record = load_series(path)
    return analyse_probe(record.t, record.input, record.output)


def run_excitation(args: argparse.Namespace) -> dict:
    """Write the excitation's CSV (columns t,input) atomically; what was written (and what the probe found)."""
    if args.probe is not None and args.kind != "designed":
        raise InputError(f"--probe is for the designed excitation, not {args.kind!r}")
    if args.hold is not None and args.kind != "levels":
        raise InputError(f"--hold is for the levels excitation, not {args.kind!r}")
    probe = read_probe(args.probe) if args.probe is not None else None
    duration = args.duration
    if duration is None:
        duration = DESIGNED_AFTER_PROBE_S if probe is not None else DEFAULT_DURATION_S[args.kind]
    t, current = excitation(args.kind, duration, args.step, args.max_current, args.seed, probe,
                            LEVELS_HOLD_S if args.hold is None else args.hold)
    lines = ["t,input"] + [f"{time_s:.6f},{value:.9g}" for time_s, value in zip(t, current, strict=True)]
    atomic_write_text(args.out, "\n".join(lines) + "\n")
    report = {"file": str(args.out), "kind": args.kind, "samples": int(t.size), "step_s": args.step,
              "max_current_a": float(np.max(np.abs(current)))}
    if probe is not None:
        report["probe"] = probe.as_dict()
        report["probe_summary"] = probe.summary()
    return report


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The excitation subcommand's options."""
    parser.add_argument("kind", choices=KINDS, help="paper: the paper's decaying sine; probe: held currents on each "
                                                    "wire that find its band and the lag; designed: reversal curves "
                                                    "of each wire (over the band a recorded probe found, --probe); "
                                                    "validation: the paper's two cosines; levels: held random "
                                                    "levels (validation shapes)")
    parser.add_argument("--duration", type=float, default=None,
                        help="seconds of signal (default 1000; probe 100; designed --probe 900)")
    parser.add_argument("--step", type=float, default=0.2, help="sample period [s] (default 0.2)")
    parser.add_argument("--max-current", type=float, default=5.0,
                        help="the stage's current limit [A] (default 5; designed --probe: the probe's)")
    parser.add_argument("--seed", type=int, default=0, help="the designed or levels signal's draw (default 0)")
    parser.add_argument("--hold", type=float, default=None,
                        help=f"levels: seconds each level is held (default {LEVELS_HOLD_S:g})")
    parser.add_argument("--probe", type=str, default=None,
                        help="designed: a recorded probe (t,input,output CSV or rosbag2) to design from")
    parser.add_argument("--out", type=str, required=True, help="CSV file to write")
    parser.add_argument("--json", action="store_true", help="print what was written as JSON")
