"""What a sine's tracking can reach on each plant of bench/bench_positioning.py when the law knows the plant exactly
and plans the relay's hand-overs: an oracle to tell the misses of the package's law that the stage imposes from
those a better law could remove.

Each plant is identified from the paper's record as bench_positioning.py does (the default law needs the model),
then driven through a sine over 70 % of the stroke twice from its state after the record: by the default law (the PI
loop with the preview, the identified model), and by a receding-horizon plan over the plant itself. The plan: every
0.2 s, the current path over the next --horizon seconds (constant on KNOT_STEPS' segments) whose run of an exact copy
of the plant (no noise, the true position) comes nearest the setpoints due over it, found by a coordinate search from
the last plan and from constant paths; its first step is commanded. Nothing limits its rate nor holds its relay, so
its RMS is an upper bound on the best the stage allows with that much of the setpoint known ahead (the search may
stop short of the best; not a law to ship). Both are scored over --seconds after LEAD_IN_S at the sine's first value,
as bench_positioning.py scores: the default law on the measured position it was given (its sensor's noise in it: 0.2
% of the span on the physical plants, less on the simulator), the plan on the true one.

With --learnt N it asks instead whether a plan over the horizon keeps to a path known to track: the default law
with the learning told the sine's period (bench/bench_learning.py's runs) is run for N periods; from the plant's
state where the last begins, one period of that period's currents replayed, of the plan with its segments offsets
from those currents (starting from none), and of the plan alone. A plan that leaves the learnt path for a worse one
was drawn off it by what it saw within its horizon.

Prints the table and writes it to bench/results/reachable.md (reachable_learnt.md with --learnt; --out); the plan
runs the plant some 40 times over 5 s per command (about 5 minutes a plant for a 100 s window).

    .venv/bin/python bench/bench_reachable.py [--plants nominal,...] [--periods 50] [--seconds 100] [--horizon 5]
        [--learnt 0] [--seed 0] [--workers 2] [--out FILE]
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))
sys.path.insert(0, str(REPO / "test"))

import bench_exact_model as exact  # noqa: E402
import bench_positioning as positioning  # noqa: E402

from sma_stage.control import Compensator  # noqa: E402

KNOT_STEPS = (0, 2, 5, 10, 17, 25, 35, 50, 70, 100)  # the plan's segments, in 0.2 s commands, cut at the horizon
CONSTANT_STARTS_A = (-5.0, -1.5, 0.0, 1.5, 5.0)
SEARCH_STEPS_A = (1.5, 0.5, 0.15)
SWITCH_WINDOW_S = (2.0, 10.0)  # bench_positioning.py --where: where the default law's error sits


class Planner:
    """The receding-horizon plan over an exact copy of the plant: `command(stage, wanted)` with the plant's state
    now and the setpoints [m] due after each of the horizon's commands gives the current [A]."""

    def __init__(self, max_current_a: float, horizon_s: float) -> None:
        self.max_current_a = max_current_a
        steps = round(horizon_s / positioning.PERIOD_S)
        self.bounds = (*(bound for bound in KNOT_STEPS if bound < steps), steps)
        self.knots = np.zeros(len(self.bounds) - 1)

    def _run(self, stage: object, knots: np.ndarray, wanted: np.ndarray, segments: range,
             base: np.ndarray) -> tuple[float, object]:
        """The squared error [m^2] of the path (`base` plus the knots, clipped) over `segments`, from the stage's
        state given at the first one, and a copy of the stage's state at the end."""
        stage, cost = copy.deepcopy(stage), 0.0
        for segment in segments:
            for step in range(self.bounds[segment], self.bounds[segment + 1]):
                current = float(np.clip(base[step] + knots[segment], -self.max_current_a, self.max_current_a))
                cost += (exact._advance(stage, current, positioning.PERIOD_S) - wanted[step]) ** 2
        return cost, stage

    def command(self, stage: object, wanted: np.ndarray, base: np.ndarray | None = None) -> float:
        """The current [A] to command now; with `base` (a current path [A] over the horizon) the knots are offsets
        from it, searched from none and from the last plan's."""
        limit = self.max_current_a
        held = bool(np.all(wanted == wanted[0]))  # a held setpoint (the lead-in): the last plan refined only
        if base is None:
            base = np.zeros(self.bounds[-1])
            starts = [self.knots, *(np.full(self.knots.size, value) for value in CONSTANT_STARTS_A
                                    if abs(value) <= limit and not held)]
        else:
            starts = [np.zeros(self.knots.size), self.knots]
        best, best_cost = starts[0], np.inf
        for knots in starts:
            cost, _ = self._run(stage, knots, wanted, range(knots.size), base)
            if cost < best_cost:
                best, best_cost = knots, cost
        for step_a in SEARCH_STEPS_A[1:] if held else SEARCH_STEPS_A:
            for segment in range(best.size):
                before, there = self._run(stage, best, wanted, range(segment), base)
                for sign in (1.0, -1.0):
                    trial = best.copy()
                    trial[segment] = np.clip(trial[segment] + sign * step_a, -limit, limit)
                    if trial[segment] == best[segment]:
                        continue
                    cost = before + self._run(there, trial, wanted, range(segment, best.size), base)[0]
                    if cost < best_cost:
                        best, best_cost = trial, cost
                        break
        self.knots = best
        return float(np.clip(base[0] + best[0], -limit, limit))

def planned_drive(identified: positioning.Identified, form: Callable[[np.ndarray], np.ndarray],
                  seconds: float, horizon_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The plant (a copy after its record) driven for LEAD_IN_S at the shape's first value, then `seconds` through
    it, by the Planner: (true positions [m] after each command, currents [A], setpoints [m], as positioning.drive)."""
    plant = copy.deepcopy(identified.plant)
    stage = exact.true_stage(plant)
    low, high = identified.stroke_m
    centre, half = 0.5 * (low + high), 0.5 * positioning.STROKE_FRACTION * (high - low)
    lead_in = int(positioning.LEAD_IN_S / positioning.PERIOD_S)
    planner = Planner(positioning.MAX_CURRENT_A, horizon_s)
    steps, ahead = lead_in + int(seconds / positioning.PERIOD_S), planner.bounds[-1]
    since_s = np.maximum(positioning.PERIOD_S * (np.arange(steps + 1 + ahead) - lead_in), 0.0)
    wanted = centre + half * form(since_s)
    positions, currents = np.empty(steps), np.empty(steps)
    for k in range(steps):
        currents[k] = planner.command(stage, wanted[k + 1:k + 1 + ahead])
        positions[k] = exact._advance(stage, currents[k], positioning.PERIOD_S)
    return positions, currents, wanted[:steps + 1]


def learnt_period(identified: positioning.Identified, form: Callable[[np.ndarray], np.ndarray], period_s: float,
                  periods: int) -> tuple[object, np.ndarray, np.ndarray, float]:
    """The default law with the learning told the sine's period, run for `periods` periods as bench_learning.py
    runs it: (a copy of the plant's state where its last period begins, that period's currents [A], the setpoints
    [m] due after each of its commands, its RMS error [% of the stroke] as measured)."""
    positions, currents, wanted = positioning.drive(identified, form, positioning.LOOP_PREVIEW, period_s * periods,
                                                    period_s)
    steps = round(period_s / positioning.PERIOD_S)
    start = int(positioning.LEAD_IN_S / positioning.PERIOD_S) + (periods - 1) * steps
    stage = exact.true_stage(copy.deepcopy(identified.plant))
    initial = Compensator(identified.model, positioning.MAX_CURRENT_A).drive.initial_current()
    replay(stage, np.concatenate([[initial], currents[:start]]))
    low, high = identified.stroke_m
    error = positions[start:] - wanted[start + 1:]
    return stage, currents[start:], wanted[start + 1:], 100.0 * float(np.sqrt(np.mean(error**2))) / (high - low)


def replay(stage: object, currents: np.ndarray) -> np.ndarray:
    """Step the stage's state through the currents [A], one command each: the true positions [m] after each."""
    return np.array([exact._advance(stage, float(current), positioning.PERIOD_S) for current in currents])


def planned_period(stage: object, learnt: np.ndarray, wanted: np.ndarray, horizon_s: float,
                   warm: bool) -> tuple[np.ndarray, np.ndarray]:
    """One period of the Planner from the stage's state (a copy), the setpoints `wanted` [m] repeating beyond it, its
    knots offsets from the learnt currents [A] (warm) or not: (true positions [m], currents [A])."""
    stage = copy.deepcopy(stage)
    steps = learnt.size
    planner = Planner(positioning.MAX_CURRENT_A, horizon_s)
    positions, currents = np.empty(steps), np.empty(steps)
    for k in range(steps):
        due = (k + np.arange(planner.bounds[-1])) % steps
        currents[k] = planner.command(stage, wanted[due], learnt[due] if warm else None)
        positions[k] = exact._advance(stage, float(currents[k]), positioning.PERIOD_S)
    return positions, currents


def learnt_rows(name: str, periods_s: list[float], learnt_periods: int, horizon_s: float, seed: int) -> list[str]:
    """One row per sine period of one plant: the learning's last period, its currents replayed on the plant, the
    plan from that state warm from the learnt path and cold."""
    identified = positioning.identify(name, seed)
    low, high = identified.stroke_m
    rows = []
    for period in periods_s:
        stage, learnt, wanted, measured_pct = learnt_period(identified, positioning.sine(period), period,
                                                            learnt_periods)
        cells = [f"{measured_pct:.2f}"]
        runs = [(replay(copy.deepcopy(stage), learnt), learnt),
                *(planned_period(stage, learnt, wanted, horizon_s, warm) for warm in (True, False))]
        for positions, currents in runs:
            error = 100.0 * (positions - wanted) / (high - low)
            change = 100.0 * np.abs(np.diff(currents)) / positioning.MAX_CURRENT_A
            cells.append(f"{np.sqrt(np.mean(error**2)):.2f} ({np.percentile(change, 99):.1f})")
        rows.append(f"| {name} | sine {period:g} s | " + " | ".join(cells) + " |")
        print(rows[-1], flush=True)
    return rows


def scored_cells(identified: positioning.Identified, positions: np.ndarray, currents: np.ndarray,
                 wanted: np.ndarray) -> str:
    """RMS / max error [% of the stroke] (p99 current change, % of the limit; the share of the squared error 2-10 s
    after a relay switch, %)."""
    error, change = positioning.scored(identified, positions, currents, wanted)
    since = positioning.since_switch_s(currents)[int(positioning.LEAD_IN_S / positioning.PERIOD_S):]
    window = (since >= SWITCH_WINDOW_S[0]) & (since < SWITCH_WINDOW_S[1])
    share = 100.0 * np.sum(error[window] ** 2) / max(float(np.sum(error**2)), 1e-30)
    return (f"{np.sqrt(np.mean(error**2)):.2f} / {np.max(np.abs(error)):.1f} ({np.percentile(change, 99):.1f}; "
            f"{share:.0f})")


def plant_rows(name: str, periods_s: list[float], seconds: float, horizon_s: float, seed: int) -> list[str]:
    """One row per sine period of one plant: the default law, then the plan over the plant."""
    identified = positioning.identify(name, seed)
    rows = []
    for period in periods_s:
        default = positioning.drive(identified, positioning.sine(period), positioning.LOOP_PREVIEW, seconds)
        planned = planned_drive(identified, positioning.sine(period), seconds, horizon_s)
        rows.append(f"| {name} | sine {period:g} s | {scored_cells(identified, *default)} | "
                    f"{scored_cells(identified, *planned)} |")
        print(rows[-1], flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--plants", default=",".join(positioning.PLANTS))
    parser.add_argument("--periods", default="50", help="comma-separated sine periods [s]")
    parser.add_argument("--seconds", type=float, default=100.0, help="the scored window after the lead-in [s]")
    parser.add_argument("--horizon", type=float, default=5.0, help="the plan's horizon [s]")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--learnt", type=int, default=0,
                        help="plan from the learning's last period after this many periods (0: from the lead-in)")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    names = positioning.plant_names(parser, args.plants)
    try:
        periods = [float(value) for value in args.periods.split(",")]
    except ValueError:
        parser.error(f"--periods must be comma-separated numbers, got {args.periods!r}")
    if not all(5.0 <= period <= 1000.0 for period in periods):
        parser.error(f"--periods must each be from 5 to 1000 s, got {args.periods}")
    if not 10.0 <= args.seconds <= 1000.0:
        parser.error(f"--seconds must be from 10 to 1000, got {args.seconds:g}")
    if not 1.0 <= args.horizon <= 20.0:
        parser.error(f"--horizon must be from 1 to 20 s, got {args.horizon:g}")
    if args.seed < 0:
        parser.error(f"--seed must be 0 or more, got {args.seed}")
    if not 1 <= args.workers <= 16:
        parser.error(f"--workers must be from 1 to 16, got {args.workers}")
    if not 0 <= args.learnt <= 50:
        parser.error(f"--learnt must be from 0 to 50 periods, got {args.learnt}")
    started = time.perf_counter()
    if args.learnt:
        header = ("| plant | setpoint | the learning's last period, measured | its currents replayed | the plan from "
                  "the learnt path | the plan alone |\n|---|---|---|---|---|---|")
        make_rows, arguments = learnt_rows, [args.learnt] * len(names)
        title = "What a plan over the plant does from a learnt period"
        explained = (f"From the plant's state where the last of {args.learnt} periods of the default law with the "
                     "learning begins: that period's RMS error [% of the stroke] as measured, then one period of each "
                     "drive, RMS on the true position (the current's p99 change, % of the limit).")
    else:
        header = ("| plant | setpoint | PI loop, preview (the default law) | a plan over the plant itself |\n"
                  "|---|---|---|---|")
        make_rows, arguments = plant_rows, [args.seconds] * len(names)
        title = "What a sine's tracking can reach with the plant known exactly"
        explained = ("Each cell: RMS / max error [% of the stroke] over the scored window (the current's p99 change, % "
                     "of the limit; the share of the squared error 2-10 s after a relay switch, %).")
    print(header, flush=True)
    with ProcessPoolExecutor(args.workers) as pool:
        found = list(pool.map(make_rows, names, [periods] * len(names), arguments, [args.horizon] * len(names),
                              [args.seed] * len(names)))
    lines = [row for rows in found for row in rows]
    note = positioning.run_note(f"--plants {args.plants} --periods {args.periods} --seconds {args.seconds:g} "
                                f"--horizon {args.horizon:g} --seed {args.seed} --learnt {args.learnt}", started,
                                "bench_reachable.py")
    out = args.out or REPO / "bench" / "results" / ("reachable_learnt.md" if args.learnt else "reachable.md")
    positioning.write_table(out, title, explained, header, lines, note)
    print(note)


if __name__ == "__main__":
    main()
