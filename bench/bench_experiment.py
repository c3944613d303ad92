"""The designed experiment against the paper's signal, on every variant of test/antagonistic_plant.py (a physical
stage the model code did not make). Per variant: the paper's decaying sine (1000 s), and for each seed the probe
(100 s: gpi_tool excitation probe) followed on the same stage by the excitation designed from what the probe found
(900 s: gpi_tool excitation designed --probe); each record identified as `gpi_tool diagnose` does (every family,
validated on the paper's validation record), then the chosen model run from rest on three validation shapes, each
on its own settled stage: the paper's validation signal, held random levels (60 s each) and a sine sweep (period
200 s down to 20 s). First, what the probe finds on each variant beside the plant's own figures: one wire's
m c / (h A), and the currents where 60 s holds from rest move the stage 5 % and 95 % of the way (wire a).
Prints the tables and writes them to bench/results/experiment.md. With --choose-on-levels each record is also
validated on held random levels of another draw than the scored one, and the family and the effects chosen on the
record each predicts worst (`diagnose --validate A --validate B`); written to bench/results/experiment_levels.md.

    .venv/bin/python bench/bench_experiment.py [--variants nominal,...] [--seeds 0,1,2,3,4] [--families ...]
        [--choose-on-levels]
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

from sma_stage.cli import family_list  # noqa: E402
from sma_stage.experiment.design import designed_signal  # noqa: E402
from sma_stage.experiment.probe import ProbeResult, analyse_probe, probe_duration_s, probe_signal  # noqa: E402
from sma_stage.identify.checks import moving_parts  # noqa: E402
from sma_stage.identify.families import FAMILIES  # noqa: E402
from sma_stage.identify.metrics import error_metrics  # noqa: E402
from sma_stage.identify.pipeline import identify_recording  # noqa: E402
from sma_stage.io import make_series  # noqa: E402

PERIOD_S = physical.SAMPLE_PERIOD_S
RECORD_S = 1000.0
PROBE_S = probe_duration_s(RECORD_S)  # the package's default share of the record (100 s)
LIMIT_A = 5.0
CHOICE_LEVELS_DRAW = 5


def validation_records(stage: physical.Stage, seed: int) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(t, current, position) of each validation shape, each from its own settled stage."""
    t = np.arange(0.0, RECORD_S, PERIOD_S)
    found = {}
    for number, (name, shape) in enumerate(physical.VALIDATION_SHAPES.items()):
        current = shape(t, seed) if name == "random_levels" else shape(t)
        found[name] = (t, current, physical.simulate(current, stage, seed + 20 + number))
    return found


def choice_levels(stage: physical.Stage, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Held random levels of another draw than the scored shape's (CHOICE_LEVELS_DRAW), from their own settled
    stage: a second record to choose on (--choose-on-levels)."""
    t = np.arange(0.0, RECORD_S, PERIOD_S)
    current = physical.random_levels(t, CHOICE_LEVELS_DRAW)
    return t, current, physical.simulate(current, stage, seed + 10 * CHOICE_LEVELS_DRAW + 5)


def probed(stage: physical.Stage, noise_seed: int) -> tuple[np.ndarray, ProbeResult]:
    """What `gpi_tool excitation probe` runs on a stage from rest (PROBE_S at LIMIT_A, the plant's period): its
    current [A] and what the probe found in the position recorded."""
    t = np.arange(0.0, PROBE_S, PERIOD_S)
    current = probe_signal(t, LIMIT_A, PROBE_S)
    return current, analyse_probe(t, current, physical.simulate(current, stage, noise_seed))


def designed_record(stage: physical.Stage, seed: int, design_seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                                 str]:
    """The probe and then the design from it, on one stage: (t, current, position, what the probe found)."""
    probe_current, found = probed(stage, seed + 5)
    t_design = np.arange(0.0, RECORD_S - PROBE_S, PERIOD_S)
    current = np.r_[probe_current, designed_signal(t_design, found, RECORD_S - PROBE_S, design_seed)]
    y = physical.simulate(current, stage, seed + 5)  # the same stage and noise: its first samples are the probe's
    t = np.arange(0.0, RECORD_S, PERIOD_S)
    return t, current, y, f"tau {found.time_constant_s:.1f} s, bands " + ", ".join(
        f"{band.start_a:.1f}-{band.end_a:.1f} A" if band.moves else "none" for band in found.wires)


def identified_model(record: tuple, validation: tuple, families: tuple[str, ...], rounds: int,
                     more: tuple[tuple, ...] = ()) -> tuple[str, object]:
    """The model `gpi_tool diagnose` chooses for record (t, current, position), validated on validation (and on
    each of `more`, chosen on the worst, as `--validate A --validate B` does): its description and the model,
    without the record's state (run from rest)."""
    found = identify_recording(make_series(*record, "identification"), make_series(*validation, "validation"),
                               diagnose_rounds=rounds, workers=2, families=families,
                               more_validation=[make_series(*extra, "more") for extra in more])
    rows = [row for row in found.report.get("families") or [] if row["chosen"]]
    return (rows[0]["model"] if rows else "GPI"), found.model.without_state()


def shape_errors(model: object, shapes: dict) -> dict[str, tuple[float, float]]:
    """The model's (RMS %, max %) on every validation shape (t, current, position)."""
    errors = {}
    for name, (t, u, y) in shapes.items():
        metrics = error_metrics(y, model.predict(t, u))
        errors[name] = (metrics.rms_pct, metrics.max_pct)
    return errors


def identified_errors(record: tuple, validation: tuple, shapes: dict, families: tuple[str, ...],
                      rounds: int, more: tuple[tuple, ...] = ()) -> tuple[str, dict[str, tuple[float, float]]]:
    """The chosen model's description and its (RMS %, max %) on every validation shape."""
    described, model = identified_model(record, validation, families, rounds, more)
    return described, shape_errors(model, shapes)


def held_band(stage: physical.Stage, edge: float = 0.05) -> tuple[float, float]:
    """Where 60 s holds of wire a's current (from rest, 0.25 A apart, each followed by 60 s at 0 A) move the stage
    edge and 1 - edge of the way to where 5 A held moves it [A]."""
    levels = np.arange(0.25, LIMIT_A + 1e-9, 0.25)
    hold = int(60.0 / PERIOD_S)
    current = np.concatenate([np.r_[np.full(hold, level), np.zeros(hold)] for level in levels])
    y = physical.simulate(current, stage, 0)
    moved = np.array([y[2 * hold * k + hold - 1] - y[2 * hold * k] for k in range(levels.size)])
    travelled = np.maximum.accumulate(moved / moved[-1])
    return (float(np.interp(edge, travelled, levels)), float(np.interp(1.0 - edge, travelled, levels)))


def probe_rows(variants: list[str], noise_seed: int) -> None:
    """What the probe finds beside the plant's own lag and band."""
    print("| variant | m c / (h A) [s] | probe's time constant [s] | wire a: 60 s holds move it 5 %-95 % [A] | "
          "probe's band, wire a; wire b [A] |")
    print("|---|---|---|---|---|")
    for variant in variants:
        stage = physical.VARIANTS[variant]
        _, found = probed(stage, noise_seed + 5)
        lag = stage.density_kg_m3 * stage.specific_heat_j_kg_k * stage.wire_diameter_m / 4 / stage.convection_w_m2_k
        low, high = held_band(stage)
        bands = "; ".join(f"{band.start_a:.2f}-{band.end_a:.2f}" for band in found.wires)
        print(f"| {variant} | {lag:.1f} | {found.time_constant_s:.1f} | {low:.2f}-{high:.2f} | {bands} |", flush=True)
    print()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", default=",".join(physical.VARIANTS))
    parser.add_argument("--seeds", default="0,1,2,3,4", help="the design's seeds")
    parser.add_argument("--families", type=family_list, default=FAMILIES,
                        help="the model families compared (default: gpi_tool diagnose's; naming two_wire_compact "
                             "writes ..._compact.md)")
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--noise-seed", type=int, default=0)
    parser.add_argument("--choose-on-levels", action="store_true",
                        help="validate on held random levels of another draw too, the choice on the worst")
    args = parser.parse_args()
    families = args.families
    seeds = [int(seed) for seed in args.seeds.split(",")]
    shape_names = list(physical.VALIDATION_SHAPES)
    probe_rows(args.variants.split(","), args.noise_seed)
    print("| variant | identified on | seed | moving % | model | " + " | ".join(f"{name} RMS / max %" for name in
                                                                            shape_names) + " | worst RMS % | probe |")
    print("|---" * (7 + len(shape_names)) + "|")
    summary = []
    for variant in args.variants.split(","):
        stage = physical.VARIANTS[variant]
        shapes = validation_records(stage, args.noise_seed)
        t = np.arange(0.0, RECORD_S, PERIOD_S)
        paper_current = physical.paper_identification(t)
        runs = [("paper", "-", (t, paper_current, physical.simulate(paper_current, stage, args.noise_seed)), "")]
        for seed in seeds:
            *record, probed = designed_record(stage, args.noise_seed, seed)
            runs.append(("designed", str(seed), tuple(record), probed))
        more = (choice_levels(stage, args.noise_seed),) if args.choose_on_levels else ()
        for kind, seed, record, probed in runs:
            started = time.perf_counter()
            described, errors = identified_errors(record, shapes["paper"], shapes, families, args.rounds, more)
            moving, parts = moving_parts(record[2])
            worst = max(rms for rms, _ in errors.values())
            summary.append((variant, kind, worst, max(top for _, top in errors.values())))
            cells = " | ".join(f"{rms:.2f} / {top:.1f}" for rms, top in errors.values())
            print(f"| {variant} | {kind} | {seed} | {100 * moving / parts:.0f} | {described} | {cells} | {worst:.2f} | "
                  f"{probed} ({time.perf_counter() - started:.0f} s) |", flush=True)
    print("\n| variant | identified on | records | worst-shape RMS %: mean, largest | worst-shape max %: largest |")
    print("|---|---|---|---|---|")
    for variant in dict.fromkeys(row[0] for row in summary):
        for kind in ("paper", "designed"):
            rows = [row for row in summary if row[0] == variant and row[1] == kind]
            worst = np.array([row[2] for row in rows])
            print(f"| {variant} | {kind} | {len(rows)} | {worst.mean():.2f}, {worst.max():.2f} | "
                  f"{max(row[3] for row in rows):.1f} |")


if __name__ == "__main__":
    named = ("_levels" if "--choose-on-levels" in sys.argv[1:] else "") + (
        "_compact" if "two_wire_compact" in " ".join(sys.argv[1:]) else "")
    with recorded(__file__, f"experiment{named}" if named else None):
        main()
