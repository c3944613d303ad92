"""How the two-wire model's tension coupling (k, the hot wire holding the heated one back at a hand-over) sits
between the record it was fitted on and the other validation shapes. Per variant of test/antagonistic_plant.py: the
model identified from the paper's decaying sine as bench_experiment.py does (every family, validated on the paper's
validation record), then, with k scaled and every other parameter as fitted, its RMS on the identification record
itself and its RMS / max on the three validation shapes of bench_experiment.py (% of each record's span). A k the
record's own fit prefers and the other shapes do not says the record lacks what the shapes see at the hand-overs:
the last row of each variant is the model identified instead from held random levels (another draw than the
validation's), k fitted there, its identification record that one.
Prints one table and writes it to bench/results/tension_coupling.md.

    .venv/bin/python bench/bench_tension_coupling.py [--variants nominal,...] [--scales 0,1,2,3]
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "test"))
sys.path.insert(0, str(REPO / "bench"))

import antagonistic_plant as physical  # noqa: E402
from bench_experiment import PERIOD_S, RECORD_S, identified_model, shape_errors, validation_records  # noqa: E402
from record_results import recorded  # noqa: E402

from sma_stage.identify.families import FAMILIES  # noqa: E402
from sma_stage.model.two_wire import TwoWireModel  # noqa: E402

DIAGNOSE_ROUNDS = 4  # as bench_experiment.py's default
UNFITTED_K_A = 0.3  # the k scaled where the fit left it at 0 [A of heating per full transformation]
LEVELS_DRAW = 7  # the held random levels a model is also identified from (the validation's are draw 0)


def scan(variant: str, scales: list[float], noise_seed: int) -> list[str]:
    """The table's rows of one variant: one per scale of k."""
    stage = physical.VARIANTS[variant]
    shapes = validation_records(stage, noise_seed)
    t = np.arange(0.0, RECORD_S, PERIOD_S)
    current = physical.paper_identification(t)
    position = physical.simulate(current, stage, noise_seed)
    _, model = identified_model((t, current, position), shapes["paper"], FAMILIES, DIAGNOSE_ROUNDS)
    if not isinstance(model, TwoWireModel):
        return [f"| {variant} | {type(model).__name__} chosen: no tension coupling |" + " |" * (2 + len(shapes))]
    fitted = model.parameters.values["tension_coupling"]
    lines = []
    for scale in scales:
        values = {**model.parameters.values, "tension_coupling": (fitted or UNFITTED_K_A) * scale}
        scaled = replace(model, parameters=replace(model.parameters, values=values))
        own, _ = shape_errors(scaled, {"identification": (t, current, position)})["identification"]
        cells = [f"{rms:.2f} / {top:.1f}" for rms, top in shape_errors(scaled, shapes).values()]
        lines.append(f"| {variant} | {fitted:.3f} | {scale:g} ({values['tension_coupling']:.3f}) | {own:.3f} | "
                     + " | ".join(cells) + " |")
    return lines


def levels_fit_row(variant: str, noise_seed: int) -> str:
    """The row of the model identified instead from held random levels (another draw than the validation's,
    LEVELS_DRAW): its own fitted k and errors, nothing scaled."""
    stage = physical.VARIANTS[variant]
    shapes = validation_records(stage, noise_seed)
    t = np.arange(0.0, RECORD_S, PERIOD_S)
    current = physical.random_levels(t, LEVELS_DRAW)
    record = (t, current, physical.simulate(current, stage, noise_seed + LEVELS_DRAW))
    _, model = identified_model(record, shapes["paper"], FAMILIES, DIAGNOSE_ROUNDS)
    if not isinstance(model, TwoWireModel):
        return f"| {variant} | {type(model).__name__} chosen from held levels |" + " |" * (2 + len(shapes))
    fitted = model.parameters.values["tension_coupling"]
    own, _ = shape_errors(model, {"identification": record})["identification"]
    cells = [f"{rms:.2f} / {top:.1f}" for rms, top in shape_errors(model, shapes).values()]
    return f"| {variant} | {fitted:.3f} | fitted on held levels | {own:.3f} | " + " | ".join(cells) + " |"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", default=",".join(physical.VARIANTS))
    parser.add_argument("--scales", default="0,0.5,1,1.5,2,3", help="multiples of the fitted k (of 0.3 A if 0)")
    parser.add_argument("--noise-seed", type=int, default=0)
    args = parser.parse_args()
    unknown = [name for name in args.variants.split(",") if name not in physical.VARIANTS]
    if unknown:
        parser.error(f"unknown variant {unknown[0]!r} (known: {', '.join(physical.VARIANTS)})")
    try:
        scales = [float(text) for text in args.scales.split(",")]
    except ValueError:
        parser.error(f"--scales must be comma-separated numbers, got {args.scales!r}")
    names = list(physical.VALIDATION_SHAPES)
    print("| variant | fitted k [A] | scale (k [A]) | identification record RMS % | "
          + " | ".join(f"{name} RMS / max %" for name in names) + " |")
    print("|---" * (4 + len(names)) + "|")
    for variant in args.variants.split(","):
        for line in scan(variant, scales, args.noise_seed):
            print(line, flush=True)
        print(levels_fit_row(variant, args.noise_seed), flush=True)


if __name__ == "__main__":
    with recorded(__file__):
        main()
