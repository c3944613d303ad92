"""gpi_tool excitation: write an identification current signal (t, input) as CSV, to play on a stage."""

from __future__ import annotations

import argparse
import math

import numpy as np

from sma_stage.commands.simulate import MAX_SAMPLES
from sma_stage.errors import InputError
from sma_stage.io.atomic import atomic_write_text
from sma_stage.signals import designed_identification_signal, paper_identification_signal

KINDS = ("paper", "designed")


def excitation(kind: str, duration_s: float, step_s: float, max_current_a: float = 5.0,
               seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(t [s], current [A]) of the named excitation: `paper`, the decaying sine scaled to max_current_a at its
    start (5 A falling to 3.6 A at 5 A); `designed`, sma_stage.signals.designed_identification_signal."""
    if kind not in KINDS:
        raise InputError(f"excitation must be one of {', '.join(KINDS)}, got {kind!r}")
    for name, value in (("--duration", duration_s), ("--step", step_s), ("--max-current", max_current_a)):
        if not 0.0 < value < math.inf:
            raise InputError(f"{name} must be positive and finite, got {value:g}")
    if duration_s / step_s > MAX_SAMPLES:
        raise InputError(f"--duration {duration_s:g} s at --step {step_s:g} s is more than {MAX_SAMPLES:,} samples")
    t = np.arange(0.0, duration_s, step_s)
    if kind == "paper":
        scale = max_current_a / 5.0
        return t, paper_identification_signal(t, 5.0 * scale, 3.6 * scale, duration_s=duration_s)
    return t, designed_identification_signal(t, max_current_a, duration_s, seed)


def run_excitation(args: argparse.Namespace) -> dict:
    """Write the excitation's CSV (columns t,input) atomically; what was written."""
    t, current = excitation(args.kind, args.duration, args.step, args.max_current, args.seed)
    lines = ["t,input"] + [f"{time_s:.6f},{value:.9g}" for time_s, value in zip(t, current, strict=True)]
    atomic_write_text(args.out, "\n".join(lines) + "\n")
    return {"file": str(args.out), "kind": args.kind, "samples": int(t.size), "step_s": args.step,
            "max_current_a": float(np.max(np.abs(current)))}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The excitation subcommand's options."""
    parser.add_argument("kind", choices=KINDS, help="paper: the paper's decaying sine; designed: excursions of each "
                                                    "wire to many peaks and reversal levels, with holds")
    parser.add_argument("--duration", type=float, default=1000.0, help="seconds of signal (default 1000)")
    parser.add_argument("--step", type=float, default=0.2, help="sample period [s] (default 0.2)")
    parser.add_argument("--max-current", type=float, default=5.0, help="the stage's current limit [A] (default 5)")
    parser.add_argument("--seed", type=int, default=0, help="the designed signal's draw (default 0)")
    parser.add_argument("--out", type=str, required=True, help="CSV file to write")
    parser.add_argument("--json", action="store_true", help="print what was written as JSON")
