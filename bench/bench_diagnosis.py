"""Benchmark of the residual diagnosis: how long `diagnose` takes on records of the stage simulator (a
physical model with no GPI inside) of a given size, every candidate effect included, every round run.

Identification on the paper's decaying sine, validation on its two cosines, each N samples over 1000 s
from an idle stage (the simulator with nothing switched on). Prints a table: samples, candidates,
rounds, what was named, the validation RMS before and after, and the wall-clock seconds.

Each size runs with every --workers count given (candidates fitted in that many processes; the result is
the same for any count, which the table shows).

Run: python bench/bench_diagnosis.py [--samples 5000,20000] [--workers 1,2]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from sma_stage.identify.diagnosis import diagnose
from sma_stage.identify.effects import EFFECT_NAMES
from sma_stage.plant import simulate
from sma_stage.signals import paper_identification_signal, paper_validation_signal

DURATION_S = 1000.0


def record(signal, samples: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t [s], current [A], measured position [m]) of the simulator from an idle stage, `samples` samples."""
    step = DURATION_S / samples
    t = np.arange(1, samples + 1) * step
    run = simulate(signal(t - step), step, seed=seed)
    return run.t_s, run.current_a, run.measured_position_m


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", default="5000,20000", help="comma-separated record sizes")
    parser.add_argument("--workers", default=f"1,{os.cpu_count() or 1}", help="comma-separated worker counts")
    args = parser.parse_args(argv)
    print(f"{os.cpu_count()} CPUs\n")
    print("| samples (each record) | candidates | workers | rounds | named | validation RMS before -> after % "
          "| seconds |")
    print("|---|---|---|---|---|---|---|")
    for samples in (int(text) for text in args.samples.split(",")):
        ident = record(paper_identification_signal, samples, seed=1)
        valid = record(paper_validation_signal, samples, seed=2)
        for workers in dict.fromkeys(int(text) for text in args.workers.split(",")):
            started = time.perf_counter()
            result = diagnose(ident, valid, workers=workers)
            seconds = time.perf_counter() - started
            print(f"| {samples} | {len(EFFECT_NAMES)} | {workers} | {len(result.rounds)} "
                  f"| {' + '.join(result.effects) or 'none'} | {result.before.rms_pct:.2f} -> {result.after.rms_pct:.4f} "
                  f"| {seconds:.1f} |", flush=True)


if __name__ == "__main__":
    main()
