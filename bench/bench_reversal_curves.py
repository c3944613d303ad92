"""Quasi-static first-order reversal curves of the second physical stage (test/antagonistic_plant.py, which the
model code did not make, and the positioning bench's three variants of it), placed where the probe finds each wire
moves the stage: first `gpi_tool excitation probe` (100 s) on the stage, then each wire ramped at 0.02 A/s from rest
to a peak and back, twelve peaks per wire spread evenly over the range the designed excitation draws its peaks from
(`sma_stage.experiment.design.peak_range`: from a fifth into the wire's band to a fifth of its width beyond it), the
wires taking turns. The curves of every other peak are the fit's record, the others held out, and then the other way
round; each record runs from the stage at rest, sampled every 1 s. `identify_recording` as `gpi_tool diagnose
--rounds 2` runs it (every family, the operator count chosen from the data) is scored on both, and the table gives
the held-out RMS over the fit's RMS: a model that learnt the curves it saw and not the stage's shows a ratio well
over 1. The chosen model is also scored on curves placed without the probe (peaks at 0.50, 0.60, ... 1.00 of the
5 A limit, both wires), whose shallowest peaks lie below the band's. A second table gives the chosen model's RMS
on each curve of both records (from rest, as scored), and the ratio without each record's first peak. Prints both
and writes them to bench/results/reversal_curves.md.

    .venv/bin/python bench/bench_reversal_curves.py [--variants nominal,...] [--families gpi,...]

With --families naming two_wire_compact the tables go to bench/results/reversal_curves_compact.md.
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
from bench_experiment import probed  # noqa: E402
from bench_positioning import NEW_VARIANTS  # noqa: E402
from record_results import recorded  # noqa: E402

from sma_stage.cli import family_list  # noqa: E402
from sma_stage.experiment.design import peak_range  # noqa: E402
from sma_stage.identify.families import FAMILIES  # noqa: E402
from sma_stage.identify.metrics import error_metrics  # noqa: E402
from sma_stage.identify.pipeline import identify_recording  # noqa: E402
from sma_stage.io import make_series  # noqa: E402
from sma_stage.model.kinds import AnyModel  # noqa: E402

LIMIT_A = 5.0
RATE_A_S = 0.02
PEAKS_PER_WIRE = 12
FIXED_PEAKS = np.linspace(0.5, 1.0, 6) * LIMIT_A  # the check without the probe [A]
SAMPLE_S = 1.0
STAGES = {**physical.VARIANTS, **NEW_VARIANTS}
HALVES = {"even": slice(0, None, 2), "odd": slice(1, None, 2)}  # which peaks the fit's record has


def curves(peaks_a: np.ndarray, peaks_b: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """Each curve's label (peak [A], wire) and current [A] every SAMPLE_S: a ramp at RATE_A_S from 0 to the peak and
    back, then 30 s at 0 A; wire a to its first peak, wire b to its first, then each wire's second, and so on."""
    parts = []
    for peak_a, peak_b in zip(peaks_a, peaks_b, strict=True):
        for wire, sign, peak in (("a", 1.0, peak_a), ("b", -1.0, peak_b)):
            up = np.arange(0.0, peak, RATE_A_S * SAMPLE_S)
            parts.append((f"{peak:.2f}{wire}", sign * np.r_[up, up[::-1], np.zeros(int(30.0 / SAMPLE_S))]))
    return parts


def record(stage: physical.Stage, parts: list[tuple[str, np.ndarray]],
           seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, current, position) sampled every SAMPLE_S of the curves one after the other: the plant run from rest at
    its own 0.2 s period, the current held."""
    current = np.concatenate([part for _, part in parts])
    steps = int(round(SAMPLE_S / physical.SAMPLE_PERIOD_S))
    y = physical.simulate(np.repeat(current, steps), stage, seed)[::steps]
    return SAMPLE_S * np.arange(current.size), current, y


def per_curve_rms(model: AnyModel, recorded: tuple[np.ndarray, np.ndarray, np.ndarray],
                  parts: list[tuple[str, np.ndarray]]) -> tuple[list[str], float]:
    """The model's RMS error [% of the record's span] on each curve of a record, run from rest over the whole
    record, as "label rms"; and its RMS without the first peak's two curves."""
    t, u, y = recorded
    error = 100.0 * (model.without_state().predict(t, u) - y) / float(np.ptp(y))
    bounds = np.cumsum([0] + [current.size for _, current in parts])
    found = [f"{label} {np.sqrt(np.mean(error[start:end] ** 2)):.2f}"
             for (label, _), start, end in zip(parts, bounds[:-1], bounds[1:], strict=True)]
    return found, float(np.sqrt(np.mean(error[bounds[2]:] ** 2)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", default=",".join(STAGES))
    parser.add_argument("--families", type=family_list, default=FAMILIES,
                        help="the model families compared (default: gpi_tool diagnose's)")
    args = parser.parse_args()
    print("| variant | fit's peaks | family | model | fit RMS / max % | held-out curves RMS / max % | "
          "held-out / fit RMS | chosen: on the curves without the probe RMS / max % | seconds |")
    print("|---|---|---|---|---|---|---|---|---|")
    by_curve, bands = [], []
    for variant in args.variants.split(","):
        stage = STAGES[variant]
        _, found_probe = probed(stage, 2)
        ranges = [peak_range(band, LIMIT_A) for band in found_probe.wires]
        peaks = [np.linspace(low, high, PEAKS_PER_WIRE) for low, high in ranges]
        bands.append(f"| {variant} | {found_probe.summary()} | "
                     + "; ".join(f"{low:.2f}-{high:.2f}" for low, high in ranges) + " |")
        fixed = record(stage, curves(FIXED_PEAKS, FIXED_PEAKS), 3)
        for half, held_half in (("even", "odd"), ("odd", "even")):
            fit_parts = curves(peaks[0][HALVES[half]], peaks[1][HALVES[half]])
            held_parts = curves(peaks[0][HALVES[held_half]], peaks[1][HALVES[held_half]])
            fitted, held_out = record(stage, fit_parts, 0), record(stage, held_parts, 1)
            started = time.perf_counter()
            found = identify_recording(make_series(*fitted, "fit curves"), make_series(*held_out, "held-out curves"),
                                       families=args.families, diagnose_rounds=2, workers=2)
            seconds = time.perf_counter() - started
            on_fixed = error_metrics(fixed[2], found.model.without_state().predict(fixed[0], fixed[1]))
            for row in found.report["families"]:
                if row["not_fitted"]:
                    print(f"| {variant} | {half} | {row['family']} | not fitted: {row['not_fitted']} | | | | | |")
                    continue
                fit, valid = row["identification"], row["validation"]
                fixed_cell = f"{on_fixed.rms_pct:.2f} / {on_fixed.max_pct:.1f}" if row["chosen"] else ""
                print(f"| {variant} | {half} | {row['family']} | {row['model']} | {fit['rms_pct']:.2f} / "
                      f"{fit['max_pct']:.1f} | {valid['rms_pct']:.2f} / {valid['max_pct']:.1f} | "
                      f"{valid['rms_pct'] / fit['rms_pct']:.2f} | {fixed_cell} | {seconds:.0f} |", flush=True)
            on_fit, fit_rest = per_curve_rms(found.model, fitted, fit_parts)
            on_held, held_rest = per_curve_rms(found.model, held_out, held_parts)
            by_curve.append(f"| {variant} | {half} | {', '.join(on_fit)} | {', '.join(on_held)} | {fit_rest:.2f} / "
                            f"{held_rest:.2f} = {held_rest / fit_rest:.2f} |")
    print("\nWhat the probe found on each variant, and the range of each wire's peaks [A]:\n")
    print("| variant | probe | peaks, wire a; wire b [A] |")
    print("|---|---|---|")
    print("\n".join(bands))
    print("\nThe chosen model's RMS error [% of the record's span] on each curve (peak [A], wire), from rest over the "
          "whole record:\n")
    print("| variant | fit's peaks | fit curves | held-out curves | without each record's first peak: fit / held-out "
          "RMS |")
    print("|---|---|---|---|---|")
    print("\n".join(by_curve))


if __name__ == "__main__":
    with recorded(__file__, "reversal_curves_compact" if "two_wire_compact" in " ".join(sys.argv[1:]) else None):
        main()
