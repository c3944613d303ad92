"""Benchmark of the residual diagnosis: how long `gpi_tool diagnose`'s pipeline takes on records of the stage
simulator (a physical model with no GPI inside) of a given size, every candidate effect included, every round
run, and every model family given fitted and compared.

Identification on the paper's decaying sine, validation on its two cosines, each N samples over 1000 s
from an idle stage (the simulator with nothing switched on). Prints a table: samples, candidates, workers,
what was named, the validation RMS before and after, each family's validation RMS and the wall-clock seconds.

Each size runs with every --workers count given (candidates fitted in that many processes; the result is
the same for any count, which the table shows).

Run: python bench/bench_diagnosis.py [--samples 5000,20000] [--workers 1,2] [--families gpi --families gpi,two_wire ...]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
from record_results import recorded

from sma_stage.identify.effects import EFFECT_NAMES
from sma_stage.identify.families import FAMILIES
from sma_stage.identify.pipeline import identify_recording
from sma_stage.io.series import Series, make_series
from sma_stage.plant import simulate
from sma_stage.signals import paper_identification_signal, paper_validation_signal

DURATION_S = 1000.0


def record(signal, samples: int, seed: int) -> Series:
    """The simulator's record (t [s], current [A], measured position [m]) from an idle stage, `samples` samples."""
    step = DURATION_S / samples
    t = np.arange(1, samples + 1) * step
    run = simulate(signal(t - step), step, seed=seed)
    return make_series(run.t_s, run.current_a, run.measured_position_m, f"simulator {samples}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", default="5000,20000", help="comma-separated record sizes")
    parser.add_argument("--workers", default=f"1,{os.cpu_count() or 1}", help="comma-separated worker counts")
    parser.add_argument("--families", action="append",
                        help="comma-separated model families compared; repeat it for several sets, each timed beside "
                             "the first (default: gpi, then every family)")
    parser.add_argument("--rounds", type=int, default=4, help="diagnosis rounds at most (gpi_tool's default 4)")
    args = parser.parse_args(argv)
    family_sets = [tuple(text.split(",")) for text in (args.families or ["gpi", ",".join(FAMILIES)])]
    print(f"{os.cpu_count()} CPUs\n")
    print("| samples (each record) | candidates | workers | named | validation RMS before -> after % | families: "
          "validation RMS % (chosen *) | seconds | seconds / first set's |")
    print("|---|---|---|---|---|---|---|---|")
    for samples in (int(text) for text in args.samples.split(",")):
        ident = record(paper_identification_signal, samples, seed=1)
        valid = record(paper_validation_signal, samples, seed=2)
        for workers in dict.fromkeys(int(text) for text in args.workers.split(",")):
            first = None
            for families in family_sets:
                started = time.perf_counter()
                found = identify_recording(ident, valid, diagnose_rounds=args.rounds, workers=workers,
                                           families=families)
                seconds = time.perf_counter() - started
                first = first or seconds
                diagnosis = found.diagnosis
                rows = found.report.get("families", [])
                scores = ", ".join(f"{row['family']} {row['validation']['rms_pct']:.2f}{' *' if row['chosen'] else ''}"
                                   if row["validation"] else f"{row['family']} -" for row in rows) or "gpi only"
                print(f"| {samples} | {len(EFFECT_NAMES)} | {workers} | {' + '.join(diagnosis.effects) or 'none'} "
                      f"| {diagnosis.before.rms_pct:.2f} -> {diagnosis.after.rms_pct:.4f} | {scores} | {seconds:.1f} "
                      f"| {seconds / first:.2f} |", flush=True)


if __name__ == "__main__":
    with recorded(__file__):
        main()
