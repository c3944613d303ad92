"""The model watch on the stage simulator, in process (no ROS): false alarms while nothing changes, and how soon
a change of the stage is flagged; the watch's cost per sample. Prints tables.

    .venv/bin/python bench/bench_watch.py [--hours 4] [--seeds 0,1,2]

The model is identified as bench/bench_tracking.py identifies it (the paper's signals, the package's pipeline);
then a fresh simulator tracks a slow sine (60 % of the stroke, period 300 s) with the compensator's PI loop at
0.1 s, and the watch (sma_stage.identify.watch, the node's defaults) runs the model on the applied current and
compares it with the measured position, fed one second of samples at a time as the node feeds it. Nothing
changing: `--hours` of tracking per seed, every alarm counted (the test restarts after each). Changes: a load
step of 2 N at 3000 s (the flag's delay after it), an ambient drift of 0.002 K/s and a creep of 50 um
(tau 200 s), both on from the start (the time of the flag).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_tracking import CONTROL_STEP_S, MAX_CURRENT_A, identify  # noqa: E402

from sma_stage.control import Compensator  # noqa: E402
from sma_stage.control.compensator import imc_gains  # noqa: E402
from sma_stage.identify.watch import DriftTest, ModelWatch  # noqa: E402
from sma_stage.plant import StageSimulator  # noqa: E402
from sma_stage.plant.config import Effects  # noqa: E402

SINE_PERIOD_S = 300.0
SINE_FRACTION = 0.6
CHUNK_STEPS = 10  # samples per call of the watch: one second at 0.1 s
LOAD_STEP_S = 3000.0
CHANGES = {"load step 2 N at 3000 s": (Effects(load_change_n=2.0, load_change_time_s=LOAD_STEP_S), LOAD_STEP_S,
                                       LOAD_STEP_S + 1200.0),
           "ambient drift 0.002 K/s from 0 s": (Effects(ambient_drift_k_per_s=0.002), 0.0, 3600.0),
           "creep 50 um (tau 200 s) from 0 s": (Effects(creep_amplitude_m=50e-6), 0.0, 3600.0)}


def run(model, stroke: tuple[float, float], effects: Effects, seconds: float, seed: int
        ) -> tuple[list[float], float, float]:
    """(times [s] the watch flagged drift, restarting after each; the tracking RMS [% of the stroke]; the watch's
    mean cost per sample [us])."""
    gains = imc_gains(model, CONTROL_STEP_S)
    core = Compensator(model, MAX_CURRENT_A, **gains)
    stage = StageSimulator(effects=effects, seed=seed)
    watch = ModelWatch(model)
    low, high = stroke
    middle, amplitude = 0.5 * (low + high), 0.5 * SINE_FRACTION * (high - low)
    steps = int(round(seconds / CONTROL_STEP_S))
    position = stage.state.measured_position_m
    chunk_t, chunk_u, chunk_y, alarms, errors, watch_s = [], [], [], [], [], 0.0
    for k in range(steps):
        t = k * CONTROL_STEP_S
        setpoint = middle + amplitude * np.sin(2 * np.pi * t / SINE_PERIOD_S)
        current = core.command(setpoint, position, CONTROL_STEP_S if k else 0.0)
        position = stage.step(current, CONTROL_STEP_S).measured_position_m
        errors.append(position - setpoint)
        chunk_t.append(t + CONTROL_STEP_S)
        chunk_u.append(current)
        chunk_y.append(position)
        if len(chunk_t) == CHUNK_STEPS:
            started = time.perf_counter()
            watch.step(np.array(chunk_t), np.array(chunk_u), np.array(chunk_y))
            watch_s += time.perf_counter() - started
            chunk_t, chunk_u, chunk_y = [], [], []
            if watch.state == "drift":
                alarms.append(t + CONTROL_STEP_S)
                watch.cusum.statistic = 0.0  # the test restarts; the model runs on
    rms = 100.0 * float(np.sqrt(np.mean(np.square(errors)))) / (high - low)
    return alarms, rms, 1e6 * watch_s / steps


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hours", type=float, default=4.0, help="hours of tracking per seed with nothing changing")
    parser.add_argument("--seeds", default="0,1,2", help="simulator seeds of the runs with nothing changing")
    args = parser.parse_args()
    started = time.perf_counter()
    identified = identify()
    model = identified.models[1].model
    test = DriftTest()
    print(f"model: {identified.models[1].name}, held-out RMS {model.metadata.get('held_out_rms', float('nan')):.3g} m; "
          f"watch: window {test.window_s:g} s, allowance {test.allowance:g}, threshold {test.threshold:g}, "
          f"{test.calibration_windows} calibration windows; tracking a sine over {100 * SINE_FRACTION:g} % of the "
          f"stroke, period {SINE_PERIOD_S:g} s, PI loop at {CONTROL_STEP_S:g} s\n")
    print("| run | simulated h | false alarms | tracking RMS % of stroke | watch cost per sample [us] |")
    print("|---|---|---|---|---|")
    alarms_total, hours_total = 0, 0.0
    for seed in (int(s) for s in args.seeds.split(",")):
        alarms, rms, cost = run(model, identified.stroke_m, Effects(), 3600.0 * args.hours, seed)
        alarms_total, hours_total = alarms_total + len(alarms), hours_total + args.hours
        print(f"| nothing changing, seed {seed} | {args.hours:g} | {len(alarms)} | {rms:.3f} | {cost:.1f} |")
    rate = f"{alarms_total / hours_total:.3g} per hour" if alarms_total else f"0 in {hours_total:g} h"
    print(f"\nfalse alarms: {rate}\n")
    print("| change | flagged at [s] | after the change [s] | tracking RMS % of stroke |")
    print("|---|---|---|---|")
    for name, (effects, onset_s, seconds) in CHANGES.items():
        alarms, rms, _ = run(model, identified.stroke_m, effects, seconds, 1)
        flagged = [a for a in alarms if a >= onset_s]
        early = [a for a in alarms if a < onset_s]
        when = f"{flagged[0]:.0f}" if flagged else "never"
        delay = f"{flagged[0] - onset_s:.0f}" if flagged else "-"
        extra = f" ({len(early)} before it)" if early else ""
        print(f"| {name} | {when}{extra} | {delay} | {rms:.3f} |")
    print(f"\nwall time {time.perf_counter() - started:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
