"""The package's control law with an exact model: how much of each tracking miss of bench/bench_positioning.py is the
identified model's, and how much is the law's (its lead, preview, rate limit and relay hold) on that plant.

Each plant is identified from the paper's record as bench_positioning.py does, then driven through each setpoint by
the PI loop with the preview (the law the compensator node runs) twice: with the identified model, and with the
inverse's model replaced by a copy of the plant itself (`PlantStream`: the current that, held over the inverse's
horizon, brings the copy of the plant to the target, found by bisection; the copy stepped with every command, as
the inverse's model is). Everything else of the law is the package's: its lag, reach and gains still come from the
identified model. The loop is closed on the measured position (with its noise) as before.

Prints the table and writes it to bench/results/exact_model.md (--out); about 35 minutes for the nine plants and
two sines with two worker processes (the plant's bisection runs the plant some 20 times per command).

    .venv/bin/python bench/bench_exact_model.py [--plants nominal,...] [--shapes "sine 50 s,sine 100 s"]
        [--seed 0] [--workers 2] [--where] [--out FILE]

With --where, each run's error by the time since the relay last switched wire instead of its max and p99 change
(bench_positioning.py --where's bins): whether what the law misses after a hand-over is the model's.
"""

from __future__ import annotations

import argparse
import copy
import math
import sys
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))
sys.path.insert(0, str(REPO / "test"))

import antagonistic_plant as physical  # noqa: E402
import bench_positioning as positioning  # noqa: E402

from sma_stage.control import Compensator  # noqa: E402

BISECTIONS = 16  # the current found to 10 A / 2^16, 0.15 mA
SUBSTEP_S = positioning.PERIOD_S / physical.SUBSTEPS  # the physical plant's own sub-step [s]
DEFAULT_SHAPES = ("sine 50 s", "sine 100 s")
WHERE_CELLS = ("Each cell (--where): the RMS error [% of the stroke], then per bin of the time since the relay last "
               "switched wire (0-2; 2-5; 5-10; from 10 s, and before the first switch): the share of the time % / of "
               "the squared error % / the RMS error % / the identified model's RMS miss on the currents given %.")


def _position(stage: object) -> float:
    """A plant's state's true position [m] (the physical stage or the simulator, before its sensor)."""
    if isinstance(stage, physical.AntagonisticStage):
        return float(stage.position_m)
    return stage.state.position_m


def _advance(stage: object, current_a: float, dt_s: float) -> float:
    """Step a plant's state by dt_s [s] at current_a [A]: its true position [m] at the end."""
    if not isinstance(stage, physical.AntagonisticStage):
        return stage.step(current_a, dt_s).position_m
    steps = max(1, math.ceil(dt_s / SUBSTEP_S - 1e-9))
    for _ in range(steps):
        stage.step(current_a, dt_s / steps)
    return _position(stage)


def true_stage(plant: positioning.SimulatorPlant | positioning.PhysicalPlant) -> object:
    """The state a plant wrapper steps (the physical stage or the simulator), before its sensor."""
    return plant.plant if isinstance(plant, positioning.PhysicalPlant) else plant.stage


class PlantStream:
    """A copy of the plant in the place of the two-wire model's stream (the interface StreamDrive uses): `step`,
    `output`, `current_for` (the exact inverse over a hold, by bisection on the plant) and `last_clipped`."""

    def __init__(self, stage: object, max_current_a: float) -> None:
        self.stage, self.max_current_a, self.output, self.last_clipped = stage, max_current_a, _position(stage), 0

    def step(self, current_a: float, dt_s: float) -> float:
        self.output = _advance(self.stage, current_a, dt_s)
        return self.output

    def _held(self, current_a: float, hold_s: float) -> float:
        return _advance(copy.deepcopy(self.stage), current_a, hold_s)

    def current_for(self, target_m: float, hold_s: float) -> float:
        low, high = -self.max_current_a, self.max_current_a
        self.last_clipped = int(self._held(high, hold_s) < target_m) - int(self._held(low, hold_s) > target_m)
        if self.last_clipped:
            return high if self.last_clipped > 0 else low
        for _ in range(BISECTIONS):
            middle = 0.5 * (low + high)
            if self._held(middle, hold_s) < target_m:
                low = middle
            else:
                high = middle
        return 0.5 * (low + high)


def exact_law(stage: object) -> type[Compensator]:
    """The package's Compensator with its inverse's model replaced by a copy of `stage` (a plant's state)."""

    class ExactModel(Compensator):
        def reset(self) -> None:
            super().reset()
            self.drive.stream = PlantStream(copy.deepcopy(stage), self.max_current_a)

    return ExactModel


def where_cell(identified: positioning.Identified, shape: str, form: Callable[[np.ndarray], np.ndarray],
               mode: positioning.Mode) -> str:
    """The RMS error [%] of one drive, then its error by the time since the relay's last switch (bench_positioning's
    `placed`; the miss there is the identified model's on the currents given)."""
    error, _, _, cells = positioning.placed(identified, shape, form, mode)
    return f"{np.sqrt(np.mean(error**2)):.2f}: {cells}"


def plant_rows(name: str, shapes: list[str], seed: int, where: bool = False) -> list[str]:
    """One row per setpoint of one plant: the law with the identified model, then with the exact one (with where,
    each run's where_cell)."""
    identified = positioning.identify(name, seed)
    stage = true_stage(identified.plant)
    exact = positioning.Mode("PI loop, preview, exact model", True, True, core=exact_law(stage))
    forms = positioning.shapes(seed)
    rows = []
    for shape in shapes:
        modes = (positioning.LOOP_PREVIEW, exact)
        if where:
            cells = [where_cell(identified, shape, forms[shape], mode) for mode in modes]
        else:
            runs = [positioning.track(identified, shape, forms[shape], mode) for mode in modes]
            cells = [f"{run.rms_pct:.2f} / {run.max_pct:.1f} ({run.change_p99_pct:.1f})" for run in runs]
        rows.append(f"| {name} | {shape} | " + " | ".join(cells) + " |")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--plants", default=",".join(positioning.PLANTS))
    parser.add_argument("--shapes", default=",".join(DEFAULT_SHAPES), help="comma-separated setpoint shapes")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--where", action="store_true",
                        help="each run's error by the time since the relay's last switch (bench_positioning.py "
                             "--where's bins) instead of its max and p99 change")
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "exact_model.md")
    args = parser.parse_args()
    names = positioning.plant_names(parser, args.plants)
    if args.seed < 0:
        parser.error(f"--seed must be 0 or more, got {args.seed}")
    if not 1 <= args.workers <= 16:
        parser.error(f"--workers must be from 1 to 16, got {args.workers}")
    shapes = args.shapes.split(",")
    known = positioning.shapes(args.seed)
    unknown = [shape for shape in shapes if shape not in known]
    if unknown:
        parser.error(f"unknown shape {unknown[0]!r} (known: {', '.join(known)})")
    started = time.perf_counter()
    shown = "RMS %: the error by the time since the relay's last switch" if args.where else "RMS / max % (p99 change %)"
    header = (f"| plant | setpoint | PI loop, preview: {shown} | the same, the plant as its model |\n"
              "|---|---|---|---|")
    print(header, flush=True)
    with ProcessPoolExecutor(args.workers) as pool:
        found = list(pool.map(plant_rows, names, [shapes] * len(names), [args.seed] * len(names),
                              [args.where] * len(names)))
    lines = [row for rows in found for row in rows]
    print("\n".join(lines))
    where = " --where" if args.where else ""
    note = positioning.run_note(f'--plants {args.plants} --shapes "{args.shapes}" --seed {args.seed}{where}', started,
                                "bench_exact_model.py")
    explained = (WHERE_CELLS if args.where else
                 "Each cell: RMS / max error [% of the stroke] (the current's p99 change, % of the limit).")
    positioning.write_table(args.out, "The package's control law with an exact model", explained, header, lines, note)
    print(note)


if __name__ == "__main__":
    main()
