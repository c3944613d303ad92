"""How much the two-wire model's prediction depends on the step it is run at: its couplings (the position's pull on
each wire, the tension coupling) act with one step's lag, from the position and the wires' transformed shares at
the step's start. On physical plants of test/antagonistic_plant.py, the model `gpi_tool diagnose` chooses from a
designed record (bench/bench_experiment.py's, 0.2 s samples) is run on the validation shapes at its record's step
and with each sample's current held over finer steps; then, along the held random levels, a hold of 1-3 s as the
compensator's inverse takes it (one call: 1 s sub-steps) against the same hold in steps of the record's 0.2 s.
Prints a table and writes it to bench/results/sample_period.md.

    .venv/bin/python bench/bench_sample_period.py [--variants nominal,thin_wires] [--seed 0]
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "test"))
sys.path.insert(0, str(REPO / "bench"))

import antagonistic_plant as physical  # noqa: E402
from bench_experiment import PERIOD_S, designed_record, identified_model, validation_records  # noqa: E402
from record_results import recorded  # noqa: E402

from sma_stage.identify.families import FAMILIES  # noqa: E402
from sma_stage.identify.metrics import error_metrics  # noqa: E402

SUBDIVISIONS = (1, 4, 10)  # each sample's current held over this many equal steps
HOLDS_S = (1.0, 2.0, 3.0)
EVERY = 5  # a hold compared from every this many samples of the held random levels


def finer(t: np.ndarray, u: np.ndarray, pieces: int) -> tuple[np.ndarray, np.ndarray]:
    """The record's times [s] and currents [A] with each sample's current held over `pieces` equal steps."""
    step = np.diff(t, append=t[-1] + (t[-1] - t[-2])) / pieces
    times = (t[:, None] + step[:, None] * np.arange(pieces)).ravel()
    return times, np.repeat(u, pieces)


def shape_row(model: object, shapes: dict, pieces: int) -> str:
    """RMS / max % of each shape's span, the model run with each sample split into `pieces` steps."""
    cells = []
    for t, u, y in shapes.values():
        times, currents = finer(t, u, pieces)
        metrics = error_metrics(y, model.predict(times, currents)[::pieces])
        cells.append(f"{metrics.rms_pct:.2f} / {metrics.max_pct:.1f}")
    return " | ".join(cells)


def hold_gaps(model: object, t: np.ndarray, u: np.ndarray, span: float, hold_s: float) -> np.ndarray:
    """|a hold of hold_s in one call - the same hold in steps of the record's period| [% of span], from every
    EVERY-th sample of the record (the model following the record between them)."""
    stream, gaps = model.stream(), []
    steps = int(round(hold_s / PERIOD_S))
    for k in range(1, t.size):
        if k % EVERY == 0:
            whole, stepped = copy.deepcopy(stream), copy.deepcopy(stream)
            at_once = whole.step(u[k - 1], hold_s)
            for _ in range(steps):
                by_steps = stepped.step(u[k - 1], PERIOD_S)
            gaps.append(abs(at_once - by_steps) / span * 100.0)
        stream.step(u[k - 1], t[k] - t[k - 1])
    return np.array(gaps)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", default="nominal,thin_wires,hot_alloy")
    parser.add_argument("--seed", type=int, default=0, help="the design's seed")
    args = parser.parse_args()
    variants = args.variants.split(",")
    unknown = [name for name in variants if name not in physical.VARIANTS]
    if unknown:
        parser.exit(2, f"bench_sample_period.py: unknown variant {unknown[0]!r} (known: "
                       f"{', '.join(physical.VARIANTS)})\n")
    if args.seed < 0:
        parser.exit(2, f"bench_sample_period.py: --seed must be 0 or more, got {args.seed}\n")
    names = list(physical.VALIDATION_SHAPES)
    print("| variant | model | step [s] | " + " | ".join(f"{name} RMS / max %" for name in names) + " |")
    print("|---" * (3 + len(names)) + "|")
    gaps = {}
    for variant in variants:
        stage = physical.VARIANTS[variant]
        shapes = validation_records(stage, 0)
        *record, _ = designed_record(stage, 0, args.seed)
        described, model = identified_model(tuple(record), shapes["paper"], FAMILIES, 4)
        for pieces in SUBDIVISIONS:
            print(f"| {variant} | {described if pieces == 1 else ''} | {PERIOD_S / pieces:.3g} | "
                  f"{shape_row(model, shapes, pieces)} |", flush=True)
        t, u, y = shapes["random_levels"]
        gaps[variant] = {hold: hold_gaps(model, t, u, float(np.ptp(y)), hold) for hold in HOLDS_S}
    print(f"\n| variant | hold [s] | one call against {PERIOD_S:g} s steps, % of span: mean | p99 | max |")
    print("|---|---|---|---|---|")
    for variant, by_hold in gaps.items():
        for hold, gap in by_hold.items():
            print(f"| {variant} | {hold:g} | {gap.mean():.3f} | {np.percentile(gap, 99):.2f} | {gap.max():.2f} |")


if __name__ == "__main__":
    with recorded(__file__):
        main()
