"""The hysteresis refit on drift (sma_stage.identify.pipeline.refit_hysteresis) on a tracking record after a load
step, in process, as test/test_watch_nodes.py drives it through the nodes: does the refitted model keep the stage's
reach, and how does the loop track with it? Prints a table.

    .venv/bin/python bench/bench_refit_reach.py [--seeds 0,1,2,3] [--starts=-1,40] [--held "a2,a6;a2,a3,a6,a7;"]

A 5-operator GPI is identified (the package's pipeline, the `gpi` family) on the paper's decaying sine, 500 s at
0.5 s steps, as the identification node's ~/excite and ~/refit make it in the node test. A fresh simulator then
tracks a 100 s sine over 30 % of the excitation's output range with the compensator's PI loop at 0.5 s; its load
steps by 8 N at 4200 s (the node test's step until it took 12 N). The record from `start` s after the step, 600 s long, is refitted with each set of GPI
parameters of `--held` kept (by default the envelopes' slopes, refit_hysteresis's default, and none); each model's reach is its output after -5 A and
+5 A held 300 s from the state the record leaves it in, beside the stage's own (the simulator copied at the
record's end). Then each model is swapped in (started from the applied current, the PI gains derived again) and
the loop tracks 300 s more: the same sine, and one over 45 % of the range (beyond what the record showed), its
RMS error against the 300 s before the step; `kept` is the model in force left in place.
"""

from __future__ import annotations

import argparse
import copy
import math

import numpy as np
from record_results import recorded

from sma_stage.control import Compensator
from sma_stage.control.compensator import imc_gains
from sma_stage.identify.history import started_from
from sma_stage.identify.pipeline import REFIT_HELD, identify_recording, refit_hysteresis
from sma_stage.identify.projection import HOLDABLE
from sma_stage.io.series import make_series
from sma_stage.plant import StageSimulator, simulate
from sma_stage.plant.config import Effects
from sma_stage.signals import paper_identification_signal

STEP_S = 0.5
EXCITE_S = 500.0
MAX_CURRENT_A = 5.0
LOAD_STEP_S = 4200.0
LOAD_STEP_N = 8.0
RECORD_S = 600.0
COMPARED_S = 300.0
PERIOD_S = 100.0
FRACTIONS = (0.3, 0.45)  # of the excitation's output range: the tracked sine's amplitude before and after the swap
HOLD_S = 300.0


def identified(seed: int):
    """(the GPI identified on the excitation, (lowest, highest) position it reached [m])."""
    t = np.arange(0.0, EXCITE_S, STEP_S)
    run = simulate(paper_identification_signal(t, duration_s=EXCITE_S), STEP_S, seed=seed)
    position = run.measured_position_m
    found = identify_recording(make_series(run.t_s, run.current_a, position, "the excitation"), holdout_fraction=0.25,
                               operators=5, diagnose_rounds=1, families=("gpi",))
    return found.model.without_state(), (float(position.min()), float(position.max()))


def sine(stroke: tuple[float, float], fraction: float):
    """The setpoint [m] at t [s]: a PERIOD_S sine about the middle of stroke, its amplitude fraction of it."""
    low, high = stroke
    return lambda t: 0.5 * (low + high) + fraction * (high - low) * math.sin(2 * math.pi * t / PERIOD_S)


def track(core: Compensator, stage: StageSimulator, setpoint, start_s: float, seconds: float, rows: list) -> None:
    """Run the loop from start_s for seconds, appending (time [s], current [A], position [m], setpoint [m])."""
    position = stage.state.measured_position_m
    for k in range(int(round(seconds / STEP_S))):
        t = start_s + k * STEP_S
        target = setpoint(t)
        current = core.command(target, position, STEP_S)
        position = stage.step(current, STEP_S).measured_position_m
        rows.append((t + STEP_S, current, position, target))


def rms_error(rows: list, from_s: float, to_s: float) -> float:
    table = np.array(rows)
    kept = (table[:, 0] > from_s) & (table[:, 0] <= to_s)
    return float(np.sqrt(np.mean(np.square(table[kept, 2] - table[kept, 3]))))


def reach_m(model, t_s: np.ndarray, current_a: np.ndarray) -> tuple[float, float]:
    """The model's output [m] after -5 A and +5 A held HOLD_S from the state the record leaves it in."""
    plain = model.without_state()
    _, state = plain.run(t_s, current_a)
    held_t = t_s[-1] + STEP_S * np.arange(1, int(HOLD_S / STEP_S) + 1)
    return tuple(float(plain.run(held_t, np.full(held_t.size, value), state)[0][-1])
                 for value in (-MAX_CURRENT_A, MAX_CURRENT_A))


def stage_reach_m(stage: StageSimulator) -> tuple[float, float]:
    ends = []
    for value in (-MAX_CURRENT_A, MAX_CURRENT_A):
        held = copy.deepcopy(stage)
        for _ in range(int(HOLD_S / STEP_S)):
            position = held.step(value, STEP_S).measured_position_m
        ends.append(position)
    return ends[0], ends[1]


def case(model, stroke, seed: int, start_after_s: float, held_sets: list[tuple[str, ...]]) -> list[dict]:
    """One seed and record start: a row per refit (and the model kept)."""
    core = Compensator(model, MAX_CURRENT_A, **imc_gains(model, STEP_S))
    stage = StageSimulator(effects=Effects(load_change_n=LOAD_STEP_N, load_change_time_s=LOAD_STEP_S), seed=seed)
    rows: list = []
    swap_s = LOAD_STEP_S + start_after_s + RECORD_S
    track(core, stage, sine(stroke, FRACTIONS[0]), 0.0, swap_s, rows)
    before = rms_error(rows, LOAD_STEP_S - COMPARED_S, LOAD_STEP_S)
    table = np.array(rows)
    recent = table[:, 0] > LOAD_STEP_S + start_after_s
    record = make_series(table[recent, 0], table[recent, 1], table[recent, 2], "after the step")
    stage_reach = stage_reach_m(stage)
    candidates = {"kept": (model, None)}
    for held in held_sets:
        found = refit_hysteresis(record, model, 0.25, held=held)
        candidates[f"{' '.join(held) or 'none'} held"] = (found.model, found.report["validation"]["rms_pct"])
    results = []
    for name, (candidate, held_out_pct) in candidates.items():
        ratios = []
        for fraction in FRACTIONS:
            follow = copy.deepcopy(core) if name == "kept" else Compensator(
                started_from(candidate, table[:, 0], table[:, 1]), MAX_CURRENT_A, **imc_gains(candidate, STEP_S))
            after: list = []
            track(follow, copy.deepcopy(stage), sine(stroke, fraction), swap_s, COMPARED_S, after)
            ratios.append(rms_error(after, swap_s, swap_s + COMPARED_S) / before)
        results.append({"seed": seed, "start": start_after_s, "refit": name, "held_out": held_out_pct,
                        "reach": reach_m(candidate, record.t, record.input), "stage": stage_reach,
                        "lowest": float(record.output.min()), "ratios": ratios})
    return results


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", default="0,1,2,3", help="simulator seeds, comma-separated")
    parser.add_argument("--starts", default="-1,40", help="record starts after the load step [s], comma-separated")
    parser.add_argument("--held", default=f"{','.join(REFIT_HELD)};",
                        help="sets of GPI parameters the refit keeps, ';'-separated, each comma-separated (empty: none)")
    args = parser.parse_args()
    try:
        seeds = [int(value) for value in args.seeds.split(",")]
        starts = [float(value) for value in args.starts.split(",")]
    except ValueError as error:
        parser.error(f"--seeds and --starts take comma-separated numbers ({error})")
    held_sets = [tuple(name for name in group.split(",") if name) for group in args.held.split(";")]
    unknown = sorted({name for held in held_sets for name in held} - set(HOLDABLE))
    if unknown:
        parser.error(f"--held may name {', '.join(HOLDABLE)}; got {', '.join(unknown)}")
    print("| seed | record from [s after the step] | refit | held-out RMS % | reach at -5 / +5 A [um] "
          "| stage's [um] | record's lowest [um] | tracking after / before: 30 %, 45 % sine |")
    print("|---|---|---|---|---|---|---|---|")
    for seed in seeds:
        model, stroke = identified(seed)
        for start in starts:
            for row in case(model, stroke, seed, start, held_sets):
                held_out = "" if row["held_out"] is None else f"{row['held_out']:.2f}"
                print(f"| {row['seed']} | {row['start']:g} | {row['refit']} | {held_out} | "
                      f"{row['reach'][0] * 1e6:.0f} / {row['reach'][1] * 1e6:.0f} | "
                      f"{row['stage'][0] * 1e6:.0f} / {row['stage'][1] * 1e6:.0f} | {row['lowest'] * 1e6:.0f} | "
                      f"{row['ratios'][0]:.2f}, {row['ratios'][1]:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    with recorded(__file__):
        raise SystemExit(main())
