"""Quasi-static first-order reversal curves of the second physical stage (test/antagonistic_plant.py, which the
model code did not make): each wire ramped at 0.02 A/s from rest to a peak and back, twelve peaks from 0.45 to
1.0 of the 5 A limit, the wires taking turns. The curves of every other peak are the fit's record, the others
held out; each record runs from the stage at rest, sampled every 1 s. `identify_recording` as `gpi_tool diagnose
--rounds 2` runs it (every family, the operator count chosen from the data) is scored on both, and the table
gives the held-out RMS over the fit's RMS: a model that learnt the curves it saw and not the stage's shows a
ratio well over 1. A second table gives the chosen model's RMS on each curve of both records (from rest, as scored),
and the ratio without each record's first peak: where a ratio over 1 comes from. Prints both and writes them to
bench/results/reversal_curves.md.

    .venv/bin/python bench/bench_reversal_curves.py [--variants nominal,...]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "test"))
sys.path.insert(0, str(REPO / "bench"))

import antagonistic_plant as physical  # noqa: E402
from record_results import recorded  # noqa: E402

from sma_stage.identify.families import FAMILIES  # noqa: E402
from sma_stage.identify.pipeline import identify_recording  # noqa: E402
from sma_stage.io import make_series  # noqa: E402
from sma_stage.model.kinds import AnyModel  # noqa: E402

LIMIT_A = 5.0
RATE_A_S = 0.02
PEAKS = np.linspace(0.45, 1.0, 12)
SAMPLE_S = 1.0


def curves(peaks: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """Each curve's label (peak, wire) and current [A] every SAMPLE_S: a ramp at RATE_A_S from 0 to the peak (a
    fraction of the limit) and back, then 30 s at 0 A; wire a then wire b for each peak."""
    parts = []
    for peak in peaks:
        for wire, sign in (("a", 1.0), ("b", -1.0)):
            up = np.arange(0.0, peak * LIMIT_A, RATE_A_S * SAMPLE_S)
            parts.append((f"{peak:.2f}{wire}", sign * np.r_[up, up[::-1], np.zeros(int(30.0 / SAMPLE_S))]))
    return parts


def reversal_curves(peaks: np.ndarray) -> np.ndarray:
    """The current [A] of every curve of `peaks` (curves), one after the other."""
    return np.concatenate([current for _, current in curves(peaks)])


def per_curve_rms(model: AnyModel, recorded: tuple[np.ndarray, np.ndarray, np.ndarray],
                  peaks: np.ndarray) -> tuple[list[str], float]:
    """The model's RMS error [% of the record's span] on each curve of a record of `peaks`, run from rest over the
    whole record, as "label rms"; and its RMS without the first peak's two curves."""
    t, u, y = recorded
    error = 100.0 * (model.without_state().predict(t, u) - y) / float(np.ptp(y))
    parts = curves(peaks)
    bounds = np.cumsum([0] + [current.size for _, current in parts])
    labels = [label for label, _ in parts]
    found = [f"{label} {np.sqrt(np.mean(error[start:end] ** 2)):.2f}"
             for label, start, end in zip(labels, bounds[:-1], bounds[1:], strict=True)]
    return found, float(np.sqrt(np.mean(error[bounds[2]:] ** 2)))


def record(stage: physical.Stage, current: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, current, position) sampled every SAMPLE_S: the plant run at its own 0.2 s period, the current held."""
    steps = int(round(SAMPLE_S / physical.SAMPLE_PERIOD_S))
    y = physical.simulate(np.repeat(current, steps), stage, seed)[::steps]
    return SAMPLE_S * np.arange(current.size), current, y


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", default="nominal,thin_wires,hot_alloy,stiff_flexure")
    args = parser.parse_args()
    print("| variant | family | model | fit RMS / max % | held-out curves RMS / max % | held-out / fit RMS | "
          "chosen | seconds |")
    print("|---|---|---|---|---|---|---|---|")
    by_curve = []
    for variant in args.variants.split(","):
        stage = physical.VARIANTS[variant]
        fitted = record(stage, reversal_curves(PEAKS[::2]), 0)
        held_out = record(stage, reversal_curves(PEAKS[1::2]), 1)
        started = time.perf_counter()
        found = identify_recording(make_series(*fitted, "fit curves"), make_series(*held_out, "held-out curves"),
                                   families=FAMILIES, diagnose_rounds=2, workers=2)
        seconds = time.perf_counter() - started
        for row in found.report["families"]:
            if row["not_fitted"]:
                print(f"| {variant} | {row['family']} | not fitted: {row['not_fitted']} | | | | | |")
                continue
            fit, valid = row["identification"], row["validation"]
            print(f"| {variant} | {row['family']} | {row['model']} | {fit['rms_pct']:.2f} / {fit['max_pct']:.1f} | "
                  f"{valid['rms_pct']:.2f} / {valid['max_pct']:.1f} | {valid['rms_pct'] / fit['rms_pct']:.2f} | "
                  f"{'yes' if row['chosen'] else ''} | {seconds:.0f} |", flush=True)
        on_fit, fit_rest = per_curve_rms(found.model, fitted, PEAKS[::2])
        on_held, held_rest = per_curve_rms(found.model, held_out, PEAKS[1::2])
        by_curve.append(f"| {variant} | {', '.join(on_fit)} | {', '.join(on_held)} | {fit_rest:.2f} / {held_rest:.2f} = "
                        f"{held_rest / fit_rest:.2f} |")
    print("\nThe chosen model's RMS error [% of the record's span] on each curve (peak, wire), from rest over the whole "
          "record:\n")
    print("| variant | fit curves | held-out curves | without each record's first peak: fit / held-out RMS |")
    print("|---|---|---|---|")
    print("\n".join(by_curve))


if __name__ == "__main__":
    with recorded(__file__):
        main()
