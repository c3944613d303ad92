"""Learning a repeated setpoint (sma_stage.control.learning.PeriodicLearning) on the positioning bench's plants:
each plant identified as bench/bench_positioning.py does (the paper's identification record, every family), then
driven by the PI loop with the preview through a setpoint that repeats (sines of 20, 50, 100 and 250 s period over
70 % of the stroke, and the paper's validation shape forwards and back, over and over), without and with the
learning. The table gives the RMS error [% of the stroke] of the first and the last period, the best period's, the
last period's max, how many periods were within 1 %, and the current's p99 change from one command to the next over
the whole run (% of the 5 A limit: a learning that chatters cannot win); then, per shape, the ranges over the
plants. Writes bench/results/learning.md (--out).

    .venv/bin/python bench/bench_learning.py [--plants simulator,nominal,...] [--seed 0] [--out FILE]
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))
sys.path.insert(0, str(REPO / "test"))

import antagonistic_plant as physical  # noqa: E402
import bench_positioning as positioning  # noqa: E402

PAPER_S = 1000.0
REPEATED = {  # shape: (period [s], periods run)
    "sine 20 s": (20.0, 20),
    "sine 50 s": (50.0, 12),
    "sine 100 s": (100.0, 8),
    "sine 250 s": (250.0, 4),
    "paper's validation, there and back": (2.0 * PAPER_S, 3),
}
MODE = positioning.LOOP_PREVIEW


def form_of(shape: str) -> Callable[[np.ndarray], np.ndarray]:
    """The shape in [-1, 1] of time since it began [s], repeating (the paper's validation shape run forwards, then
    backwards: a period of 2 PAPER_S without a jump where it starts again)."""
    if shape.startswith("paper's validation"):
        return lambda s: physical.paper_validation(PAPER_S - np.abs(np.mod(s, 2.0 * PAPER_S) - PAPER_S)) / 5.0
    return positioning.shapes(0)[shape]


def period_errors(identified: positioning.Identified, shape: str, learning: bool) -> tuple[np.ndarray, float]:
    """The error [% of the stroke] of each period (rows) and the p99 change of the current over the run [% of the
    limit]."""
    period_s, periods = REPEATED[shape]
    positions, currents, wanted = positioning.drive(identified, form_of(shape), MODE, period_s * periods,
                                                    period_s if learning else 0.0)
    low, high = identified.stroke_m
    lead_in = int(positioning.LEAD_IN_S / positioning.PERIOD_S)
    error = 100.0 * (positions - wanted[1:])[lead_in:] / (high - low)
    change = 100.0 * np.abs(np.diff(currents[lead_in - 1:])) / positioning.MAX_CURRENT_A
    return error.reshape(periods, -1), float(np.percentile(change, 99))


def last_rms(errors: np.ndarray) -> float:
    """The RMS error [% of the stroke] of the last period (rows of `errors`)."""
    return float(np.sqrt(np.mean(errors[-1] ** 2)))


def cells(errors: np.ndarray, change_p99: float) -> str:
    rms = np.sqrt(np.mean(errors**2, axis=1))
    within = int(np.sum(rms <= positioning.LOOP_TARGET_PCT))
    return (f"{rms[0]:.2f} / {rms[-1]:.2f} / {rms.min():.2f} | {np.max(np.abs(errors[-1])):.1f} | "
            f"{within} of {rms.size} | {change_p99:.1f}")


def summary(found: dict[str, list[tuple[float, float, float, float]]]) -> list[str]:
    """Per shape, over the plants: the last period's RMS range without and with the learning, the plants within 1 %
    in it, and the plants whose current's p99 change exceeds issue 49's 5 %."""
    lines = ["| setpoint | last period's RMS %: without learning | with it | plants within 1 %: without / with | "
             "p99 change over 5 %: without / with |", "|---|---|---|---|---|"]
    for shape, runs in found.items():
        without, learnt = np.array([run[0] for run in runs]), np.array([run[2] for run in runs])
        noisy = [sum(run[index] > positioning.CHANGE_TARGET_PCT for run in runs) for index in (1, 3)]
        lines.append(f"| {shape} | {without.min():.2f}-{without.max():.2f} | {learnt.min():.2f}-{learnt.max():.2f} | "
                     f"{int(np.sum(without <= positioning.LOOP_TARGET_PCT))} / "
                     f"{int(np.sum(learnt <= positioning.LOOP_TARGET_PCT))} of {len(runs)} | {noisy[0]} / {noisy[1]} |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--plants", default=",".join(positioning.PLANTS))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "learning.md")
    args = parser.parse_args()
    started = time.perf_counter()
    lines = ["| plant | setpoint | RMS %, first / last / best period: without learning | last period's max % | "
             "periods within 1 % | p99 current change % | the same with learning | | | |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    print("\n".join(lines), flush=True)
    found: dict[str, list[tuple[float, float, float, float]]] = {shape: [] for shape in REPEATED}
    for name in args.plants.split(","):
        identified = positioning.identify(name, args.seed)
        for shape in REPEATED:
            without, learnt = period_errors(identified, shape, False), period_errors(identified, shape, True)
            found[shape].append((last_rms(without[0]), without[1], last_rms(learnt[0]), learnt[1]))
            lines.append(f"| {name} | {shape} | {cells(*without)} | {cells(*learnt)} |")
            print(lines[-1], flush=True)
    lines += ["", "Over the plants:", "", *summary(found)]
    print("\n".join(lines[-(len(REPEATED) + 2):]))
    arguments = " ".join(sys.argv[1:])
    note = positioning.run_note(arguments, started, "bench_learning.py")
    positioning.write(args.out, "bench_learning.py", "\n".join(lines) + "\n\n" + note)


if __name__ == "__main__":
    main()
