"""Where the probe puts each wire's band start, against the stage itself: on every physical plant of
bench/bench_positioning.py (the variants of test/antagonistic_plant.py and the three made there), the probe
(`gpi_tool excitation probe`, 100 s to 5 A) and what it found, then each wire held 60 s at a few currents below the
probe's lowest held current (2 A), from where the probe's schedule has the stage when that wire's first stair
begins (wire a: rest; wire b: after wire a's staircase and the rest): how far the stage moved, in % of the wire's
travel the probe measured, read from the plant without sensor noise. Prints a table and writes it to
bench/results/probe_bands.md.

    .venv/bin/python bench/bench_probe_bands.py [--plants nominal,thin_wires,...]
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "test"))
sys.path.insert(0, str(REPO / "bench"))

import antagonistic_plant as physical  # noqa: E402
from bench_positioning import NEW_VARIANTS, PERIOD_S, make_plant  # noqa: E402
from record_results import recorded  # noqa: E402

from sma_stage.experiment.probe import analyse_probe, probe_signal  # noqa: E402

PROBE_S, LIMIT_A, HOLD_S = 100.0, 5.0, 60.0
HELD_A = (0.5, 1.0, 1.5, 2.0)


def held_motions(name: str, prefix: np.ndarray, currents_a: list[float]) -> list[float]:
    """How far [m] the plant moves, noise-free, held at each current for HOLD_S after the probe's first samples
    (each from a copy of the plant there)."""
    start = make_plant(name, 0)
    if prefix.size:
        start.record(prefix)
    moved = []
    for current_a in currents_a:
        plant = copy.deepcopy(start)
        plant.record(np.full(int(HOLD_S / PERIOD_S), current_a))
        moved.append(plant.plant.position_m - start.plant.position_m)
    return moved


def main() -> None:
    physical_plants = [*physical.VARIANTS, *NEW_VARIANTS]
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--plants", default=",".join(physical_plants))
    args = parser.parse_args()
    plants = args.plants.split(",")
    unknown = [name for name in plants if name not in physical_plants]
    if unknown:
        parser.error(f"unknown plant {unknown[0]!r} (known: {', '.join(physical_plants)})")
    t = np.arange(0.0, PROBE_S, PERIOD_S)
    current = probe_signal(t, LIMIT_A, PROBE_S)
    first_stair = {"a": 0, "b": int(np.argmax(current < 0.0))}
    print("| plant | wire | the probe's band [A] | start between held currents | held 60 s at "
          + ", ".join(f"{level:g}" for level in HELD_A) + " A: motion, % of the wire's travel |")
    print("|---|---|---|---|---|")
    for name in plants:
        found = analyse_probe(t, current, make_plant(name, 0).record(current))
        for band, sign in zip(found.wires, (1.0, -1.0), strict=True):
            prefix = current[:first_stair[band.wire]]
            moved = [100.0 * value / band.travel for value in held_motions(name, prefix, [sign * level for level in HELD_A])]
            print(f"| {name} | {band.wire} | {band.start_a:.2f}-{band.end_a:.2f} | {'yes' if band.resolved else 'no'} | "
                  + ", ".join(f"{value:.1f}" for value in moved) + " |", flush=True)


if __name__ == "__main__":
    with recorded(__file__):
        main()
