"""How far the model `gpi_tool diagnose` chooses depends on the last bits of its record: on physical plants of
test/antagonistic_plant.py, the identification record as made and copies of it whose positions are multiplied by
1 + eps N(0, 1) (eps 1e-14 by default: some tens of the doubles' last bits, a billionth of the sensor's noise),
each identified as `diagnose` does (every family, 4 rounds, validated on the paper's validation record, which is
not changed) and the chosen model scored from rest on the three validation shapes of bench/bench_experiment.py.
Another CPU rounds the same arithmetic differently (its compiled kernels and BLAS): where a choice flips under
such copies, it may flip from one machine to another. Prints the runs and a summary per plant and writes them to
bench/results/rounding.md (--record designed: rounding_designed.md, _seedN.md for a design seed N above 0).

    .venv/bin/python bench/bench_rounding.py [--variants nominal,thin_wires] [--copies 5] [--eps 1e-14]
        [--record paper|designed] [--design-seed 0]
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "test"))
sys.path.insert(0, str(REPO / "bench"))

import antagonistic_plant as physical  # noqa: E402
from bench_experiment import designed_record, identified_errors, validation_records  # noqa: E402
from record_results import recorded  # noqa: E402

from sma_stage.identify.families import FAMILIES  # noqa: E402

DEFAULT_VARIANTS = "nominal,thin_wires,hot_alloy,stiff_flexure,prestrained"
ROUNDS = 4


def perturbed(record: tuple, copy: int, eps: float) -> tuple:
    """The record (t, current, position) with its positions multiplied by 1 + eps N(0, 1), drawn by `copy`
    (-1: the record as made)."""
    t, u, y = record
    if copy < 0:
        return record
    return t, u, y * (1.0 + eps * np.random.default_rng(copy).standard_normal(y.size))


def choice(described: str) -> str:
    """What a description chose, its measured figures left out (the family, counts, the start, the coupling's
    verdict)."""
    kept = re.sub(r"[-+]?\d+\.\d+(e[-+]?\d+)?", "", described)
    return re.sub(r"\(.*?\)|BIC change .*|validation RMS .*", "", kept).strip(" :;")


def arguments() -> argparse.Namespace:
    """The command line, checked (a bad value ends in one line, status 2)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", default=DEFAULT_VARIANTS)
    parser.add_argument("--copies", type=int, default=5, help="perturbed copies beside the record as made")
    parser.add_argument("--eps", type=float, default=1e-14, help="the perturbation's relative size")
    parser.add_argument("--record", choices=("paper", "designed"), default="paper",
                        help="the paper's identification record, or the probe and the design from it")
    parser.add_argument("--design-seed", type=int, default=0, help="with --record designed: the design's seed")
    args = parser.parse_args()
    variants = args.variants.split(",")
    unknown = [name for name in variants if name not in physical.VARIANTS]
    if unknown:
        parser.exit(2, f"bench_rounding.py: unknown variant {unknown[0]!r} (known: {', '.join(physical.VARIANTS)})\n")
    if not 1 <= args.copies <= 50:
        parser.exit(2, f"bench_rounding.py: --copies must be from 1 to 50, got {args.copies}\n")
    if not 0.0 < args.eps <= 1e-3:
        parser.exit(2, f"bench_rounding.py: --eps must be above 0 and at most 1e-3, got {args.eps!r}\n")
    if args.design_seed < 0:
        parser.exit(2, f"bench_rounding.py: --design-seed must be 0 or more, got {args.design_seed}\n")
    return args


def main(args: argparse.Namespace) -> None:
    shape_names = list(physical.VALIDATION_SHAPES)
    design = f" (design seed {args.design_seed})" if args.record == "designed" else ""
    print(f"record: {args.record}{design}; copies: {args.copies}, eps {args.eps:g}; families {','.join(FAMILIES)}\n")
    print("| variant | copy | model chosen | " + " | ".join(f"{name} RMS / max %" for name in shape_names)
          + " | worst RMS % |")
    print("|---" * (4 + len(shape_names)) + "|")
    summary = []
    for variant in args.variants.split(","):
        stage = physical.VARIANTS[variant]
        shapes = validation_records(stage, 0)
        record = (designed_record(stage, 0, args.design_seed)[:3] if args.record == "designed"
                  else physical.records(stage, 0)["identification"])
        choices, worst, largest = [], [], []
        for copy in range(-1, args.copies):
            described, errors = identified_errors(perturbed(record, copy, args.eps), shapes["paper"], shapes,
                                                  FAMILIES, ROUNDS)
            choices.append(choice(described))
            worst.append(max(rms for rms, _ in errors.values()))
            largest.append(max(top for _, top in errors.values()))
            cells = " | ".join(f"{errors[name][0]:.2f} / {errors[name][1]:.1f}" for name in shape_names)
            print(f"| {variant} | {'as made' if copy < 0 else copy} | {described} | {cells} | {worst[-1]:.2f} |",
                  flush=True)
        distinct = len(set(choices))
        kept = sum("coupling kept" in chosen for chosen in choices)
        summary.append(f"| {variant} | {len(choices)} | {distinct} | {kept} | {min(worst):.2f}-{max(worst):.2f} | "
                       f"{min(largest):.1f}-{max(largest):.1f} |")
    print("\n| variant | fits | distinct choices (family, counts, start, coupling) | tension coupling kept | "
          "worst-shape RMS %: range | largest max error %: range |")
    print("|---|---|---|---|---|---|")
    print("\n".join(summary))


if __name__ == "__main__":
    checked = arguments()
    name = "rounding" if checked.record == "paper" else "rounding_designed" + (
        f"_seed{checked.design_seed}" if checked.design_seed else "")
    with recorded(__file__, name):
        main(checked)
