"""The model watch on the stage simulator, in process (no ROS): false alarms while nothing changes, and how soon
a change of the stage is flagged; the watch's cost per sample. Prints tables.

    .venv/bin/python bench/bench_watch.py [--hours 4] [--seeds 0,1,2] [--change-seeds 1] [--path-time-constants 2,8]
                                          [--families gpi,two_wire] [--watch-starts 8] [--loop-jitter 2]

The model is identified as bench/bench_tracking.py identifies it (the paper's signals, the package's pipeline);
then a fresh simulator tracks a setpoint with the compensator's PI loop at 0.1 s, and the watch
(sma_stage.identify.watch, the node's defaults) runs the model on the applied current and compares it with the
measured position, fed one second of samples at a time as the node feeds it. Setpoints: a sine over 60 % of the
stroke (period 300 s), two incommensurate cosines over the same range (the paper's validation signal's shape:
periods 200 s and 314 s) and random levels held 60 s each. Nothing changing: `--hours` of tracking per seed
(the sine) and per setpoint, every alarm counted (the tests restart after each). Changes, each from 3000 s on
(the model long in force, the watch calibrated): a load step of 2 N, an ambient drift of 0.002 K/s, a creep of
50 um (tau 200 s) switched on; the delay of the first flag after it and which test gave it, each change's record
watched `--watch-starts` times, the watch started 3.5 s later each time (where its windows fall against the
change, and what it calibrated on, move the delay by tens of seconds). Last, how far each
change moves the residual in its first minutes (the same seed with and without it), beside how far it moves
from one period of the sine to the next with nothing changed: what a test of the residual has to resolve.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path

import numpy as np
from record_results import recorded

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_tracking import CONTROL_STEP_S, MAX_CURRENT_A, identify  # noqa: E402

from sma_stage.control import Compensator  # noqa: E402
from sma_stage.control.compensator import imc_gains  # noqa: E402
from sma_stage.errors import InputError  # noqa: E402
from sma_stage.identify.watch import DriftTest, ModelWatch  # noqa: E402
from sma_stage.plant import StageSimulator  # noqa: E402
from sma_stage.plant.config import Effects  # noqa: E402

FRACTION = 0.6  # of the stroke the setpoints span
CHUNK_STEPS = 10  # samples per call of the watch: one second at 0.1 s
CHANGE_S = 3000.0  # every change starts here, the model in force and the watch long calibrated
AFTER_CHANGE_S = 1200.0
HOLD_S = 60.0  # the random levels' hold
SINE_PERIOD_S = 300.0
WINDOW_S = DriftTest().window_s  # the residual's moves are averaged over the watch's window [s]
WATCH_START_STEP_S = 3.5  # the watch's starts over a change's record are this far apart [s]
MOVED_AFTER_S = (60.0, 120.0, 240.0)  # after the change [s]
CHANGES = {"load step 2 N": Effects(load_change_n=2.0, load_change_time_s=CHANGE_S),
           "ambient drift 0.002 K/s": Effects(ambient_drift_k_per_s=0.002, ambient_drift_start_s=CHANGE_S),
           "creep 50 um (tau 200 s) switched on": Effects(creep_amplitude_m=50e-6, creep_start_s=CHANGE_S)}
Setpoint = Callable[[float], float]


def setpoints(stroke: tuple[float, float]) -> dict[str, Setpoint]:
    """The setpoint kinds [m] as functions of time [s]."""
    low, high = stroke
    middle, amplitude = 0.5 * (low + high), 0.5 * FRACTION * (high - low)
    levels = middle + amplitude * np.random.default_rng(5).uniform(-1.0, 1.0, 10_000)
    return {"sine": lambda t: middle + amplitude * np.sin(2 * np.pi * t / SINE_PERIOD_S),
            "two cosines": lambda t: middle + 0.5 * amplitude * (np.cos(0.01 * np.pi * t) + np.cos(0.02 * t)),
            "held random levels": lambda t: float(levels[int(t // HOLD_S)])}


def record(model, setpoint: Setpoint, effects: Effects, seconds: float, seed: int, jitter_steps: int = 0
           ) -> np.ndarray:
    """The PI loop tracking setpoint on a fresh simulator: rows of (time at the end of each step [s], applied current [A],
    measured position [m], setpoint [m]), one per CONTROL_STEP_S. jitter_steps: the loop is given the position a
    random 0 to jitter_steps steps late (as through the nodes, where it arrives a few ms late at a fast pace)."""
    core = Compensator(model, MAX_CURRENT_A, **imc_gains(model, CONTROL_STEP_S))
    stage = StageSimulator(effects=effects, seed=seed)
    lateness = np.random.default_rng(seed + 1000)
    steps = int(round(seconds / CONTROL_STEP_S))
    measured = deque([stage.state.measured_position_m] * (jitter_steps + 1), maxlen=jitter_steps + 1)
    rows = np.empty((steps, 4))
    for k in range(steps):
        t = k * CONTROL_STEP_S
        target = setpoint(t)
        current = core.command(target, measured[-1 - int(lateness.integers(0, jitter_steps + 1))],
                               CONTROL_STEP_S if k else 0.0)
        position = stage.step(current, CONTROL_STEP_S).measured_position_m
        measured.append(position)
        rows[k] = (t + CONTROL_STEP_S, current, position, target)
    return rows


def run(model, setpoint: Setpoint, effects: Effects, seconds: float, seed: int, test: DriftTest | None = None,
        jitter_steps: int = 0) -> tuple[list[tuple[float, str]], float, float, float, tuple[float, float]]:
    """((time [s], test) of each drift flag, restarting the tests after each; the tracking RMS [m]; the path test's
    mean coverage of the windows it looked at; the watch's mean cost per sample [us]; how far a window's mean
    innovation wandered while calibrating, bias_held_out_m [m], and the widening of the bias test's scale), the watch started with the record."""
    rows = record(model, setpoint, effects, seconds, seed, jitter_steps)
    alarms, coverage, cost_us, bias_scale = watched(model, rows, test)
    tracking_rms = float(np.sqrt(np.mean(np.square(rows[:, 2] - rows[:, 3]))))
    return alarms, tracking_rms, coverage, cost_us, bias_scale


def watched(model, rows: np.ndarray, test: DriftTest | None = None, start_s: float = 0.0
            ) -> tuple[list[tuple[float, str]], float, float, tuple[float, float]]:
    """The watch over a record's rows from start_s [s] on (started where the applied current before leaves the model,
    as the node starts it): ((time [s], test) of each drift flag, restarting the tests after each; the path test's
    mean coverage; the cost per sample [us]; (bias_held_out_m [m], the bias scale's widening)). Fed CHUNK_STEPS samples at a time, as it would be
    while the stage runs (it only looks back)."""
    first = int(round(start_s / CONTROL_STEP_S))
    watch = ModelWatch(model, test, (rows[:first, 0], rows[:first, 1]))
    rows = rows[first:]
    alarms, coverages, watch_s = [], [], 0.0
    for start in range(0, len(rows) - CHUNK_STEPS + 1, CHUNK_STEPS):
        chunk = rows[start:start + CHUNK_STEPS]
        windows = watch.cusum.windows
        started = time.perf_counter()
        watch.step(chunk[:, 0], chunk[:, 1], chunk[:, 2])
        watch_s += time.perf_counter() - started
        if watch.cusum.windows > windows and watch.coverage is not None:
            coverages.append(watch.coverage)
        if watch.state == "drift":
            alarms.append((float(chunk[-1, 0]), alarm_test(watch)))
            watch.restart_tests()  # the model runs on
    coverage = float(np.mean(coverages)) if coverages else float("nan")
    bias_scale = (watch.held_out_bias_m if watch.held_out_bias_m is not None else float("nan"),
                  watch.bias_scale_widening)
    return alarms, coverage, 1e6 * watch_s / max(len(rows), 1), bias_scale


def alarm_test(watch: ModelWatch) -> str:
    """Which test flagged: bias (the path test's mean), path (its size) or level."""
    if watch.bias_drift:
        return "bias"
    return "path" if watch.path_drift else "level"


def residual_moved(model, setpoint: Setpoint, seed: int, after_s: tuple[float, ...], jitter_steps: int = 0
                   ) -> dict[str, list[float]]:
    """How far each change moves the model's residual [m]: the mean over the WINDOW_S ending each of after_s [s]
    after the change of (residual with the change - residual without it), the same seed and setpoint; and, as
    "nothing (one period later)", how far it moves with nothing changed between one sine period and the next."""
    seconds = CHANGE_S + max(after_s)

    def residual(effects: Effects) -> np.ndarray:
        rows = record(model, setpoint, effects, seconds, seed, jitter_steps)
        return rows[:, 2] - model.run(rows[:, 0], rows[:, 1], None)[0]

    quiet = residual(Effects())
    per_window = int(round(WINDOW_S / CONTROL_STEP_S))

    def window_mean(values: np.ndarray, end_s: float) -> float:
        end = int(round((CHANGE_S + end_s) / CONTROL_STEP_S))
        return float(np.mean(values[end - per_window:end]))

    period = int(round(SINE_PERIOD_S / CONTROL_STEP_S))
    moved = {"nothing (one period later)": [window_mean(quiet[period:] - quiet[:-period], end_s - SINE_PERIOD_S)
                                            for end_s in after_s]}
    for name, effects in CHANGES.items():
        changed = residual(effects)
        moved[name] = [window_mean(changed - quiet, end_s) for end_s in after_s]
    return moved


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hours", type=float, default=4.0, help="hours of tracking per run with nothing changing")
    parser.add_argument("--seeds", default="0,1,2", help="simulator seeds of the sine runs with nothing changing")
    parser.add_argument("--change-seeds", default="1", help="simulator seeds of the runs with a change")
    parser.add_argument("--path-time-constants", default=None,
                        help="the path test's low-passes of the position [s], comma-separated (default: the watch's)")
    parser.add_argument("--families", default="gpi",
                        help="the model families the identification compares (gpi_tool diagnose --families); the "
                             "watch runs the one chosen")
    parser.add_argument("--watch-starts", type=int, default=8,
                        help=f"how many times each change is watched, started {WATCH_START_STEP_S:g} s apart")
    parser.add_argument("--loop-jitter", type=int, default=0,
                        help="the PI loop is given the position a random 0 to this many control steps late")
    args = parser.parse_args()
    if not 1 <= args.watch_starts <= 100:
        parser.error(f"--watch-starts must be from 1 to 100, got {args.watch_starts}")
    if args.loop_jitter < 0:
        parser.error(f"--loop-jitter must be 0 or more control steps, got {args.loop_jitter}")
    started = time.perf_counter()
    try:
        identified = identify(tuple(args.families.split(",")))
    except InputError as error:
        parser.error(f"--families: {error}")
    model = identified.models[1].model
    stroke = identified.stroke_m[1] - identified.stroke_m[0]
    kinds = setpoints(identified.stroke_m)
    try:
        test = DriftTest() if args.path_time_constants is None else DriftTest(
            path_time_constants_s=tuple(float(tau) for tau in args.path_time_constants.split(",")))
    except (ValueError, InputError) as error:
        parser.error(f"--path-time-constants: {error}")
    warm_up_s = (test.warmup_windows + test.calibration_windows + 5) * test.window_s
    run(model, kinds["sine"], Effects(), warm_up_s, 0, test)  # the watch's kernels compiled before anything is timed
    print(f"model: {identified.models[1].name}, held-out RMS {model.metadata.get('held_out_rms', float('nan')):.3g} m, "
          f"stroke {stroke:.4g} m; watch settings {test}; PI loop at {CONTROL_STEP_S:g} s\n")
    print("| setpoint | seed | simulated h | false alarms | tracking RMS % of stroke | path test coverage | "
          "watch cost per sample [us] | bias_held_out_m [um] | bias scale widening |")
    print("|---|---|---|---|---|---|---|---|---|")
    runs = [("sine", int(seed)) for seed in args.seeds.split(",")] + [("two cosines", 0), ("held random levels", 0)]
    alarms_total, hours_total = 0, 0.0
    for kind, seed in runs:
        alarms, rms, coverage, cost, bias_scale = run(model, kinds[kind], Effects(), 3600.0 * args.hours, seed, test,
                                                      args.loop_jitter)
        alarms_total, hours_total = alarms_total + len(alarms), hours_total + args.hours
        listed = f" ({', '.join(f'{when:.0f} s {test}' for when, test in alarms[:3])})" if alarms else ""
        print(f"| {kind} | {seed} | {args.hours:g} | {len(alarms)}{listed} | {100 * rms / stroke:.3f} | "
              f"{coverage:.2f} | {cost:.1f} | {1e6 * bias_scale[0]:.3f} | {bias_scale[1]:.2f} |")
    rate = f"{alarms_total / hours_total:.3g} per hour" if alarms_total else f"0 in {hours_total:g} h"
    print(f"\nfalse alarms: {rate}\n")
    starts_s = WATCH_START_STEP_S * np.arange(args.watch_starts)
    print(f"Each change watched {args.watch_starts} times, the watch started {', '.join(f'{s:g}' for s in starts_s)} s "
          "into the record (its windows' phase against the change and its calibration differ)\n")
    print("| setpoint | change from 3000 s | seed | first flag after it [s], each start | worst | tests | "
          "flags before it |")
    print("|---|---|---|---|---|---|---|")
    cases = [("sine", name, int(seed)) for name in CHANGES for seed in args.change_seeds.split(",")] + [
        ("two cosines", "load step 2 N", 1), ("held random levels", "load step 2 N", 1)]
    for kind, name, seed in cases:
        rows = record(model, kinds[kind], CHANGES[name], CHANGE_S + AFTER_CHANGE_S, seed, args.loop_jitter)
        delays, tests, early = [], set(), 0
        for start_s in starts_s:
            alarms = watched(model, rows, test, start_s)[0]
            flagged = [(when, by) for when, by in alarms if when >= CHANGE_S]
            early += len(alarms) - len(flagged)
            delays.append(flagged[0][0] - CHANGE_S if flagged else math.inf)
            tests.update(by for _, by in flagged[:1])
        listed = "/".join(f"{delay:.0f}" if delay < math.inf else "-" for delay in delays)
        worst = f"{max(delays):.0f}" if max(delays) < math.inf else f"none in {AFTER_CHANGE_S:g}"
        print(f"| {kind} | {name} | {seed} | {listed} | {worst} | {', '.join(sorted(tests)) or '-'} | {early} |")
    after = " | ".join(f"{end_s:.0f} s after" for end_s in MOVED_AFTER_S)
    print(f"\nHow far each change moves the residual (sine, seed 1; mean over the {WINDOW_S:g} s ending at each time, "
          f"with the change less without it) [um], against the model's held-out RMS "
          f"{1e6 * model.metadata.get('held_out_rms', float('nan')):.1f} um:\n")
    print(f"| change from 3000 s | {after} |")
    print("|---" * (1 + len(MOVED_AFTER_S)) + "|")
    for name, moves in residual_moved(model, kinds["sine"], 1, MOVED_AFTER_S, args.loop_jitter).items():
        print(f"| {name} | " + " | ".join(f"{1e6 * move:+.2f}" for move in moves) + " |")
    print(f"\nwall time {time.perf_counter() - started:.1f} s")
    return 0


if __name__ == "__main__":
    with recorded(__file__):
        raise SystemExit(main())
