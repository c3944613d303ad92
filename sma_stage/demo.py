"""The demonstration behind `./run.sh demo`: the paper's Table 1, and hysteresis compensation with the
GPI inverse on the paper's validation signal. Writes plots under --out and prints the figures."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from sma_stage.commands.paper import evaluate_paper
from sma_stage.identify.metrics import error_metrics
from sma_stage.model import forward, inverse, load_model_file
from sma_stage.plots import Panel, save_panels
from sma_stage.signals import paper_validation_signal

DEFAULT_MODEL = Path(__file__).resolve().parent.parent / "config" / "model_default.yaml"
MAX_CURRENT_A = 5.0


def compensation_demo(model_path: Path, out_dir: Path) -> dict[str, dict[str, float]]:
    """Track the paper's validation signal (scaled to 80 % of the reachable stroke) through the model:
    with a plain linear map of the setpoint to current, and with the exact and analytic inverses."""
    model = load_model_file(model_path)
    params, operators = model.parameters, model.operators
    t = np.arange(0.0, 1000.0, 0.5)
    reach = forward(np.array([-MAX_CURRENT_A, MAX_CURRENT_A]), params, operators)
    shape = paper_validation_signal(t) / 5.0
    setpoint = reach.mean() + 0.4 * np.ptp(reach) * shape
    linear_current = MAX_CURRENT_A * (setpoint - reach.mean()) / (0.5 * np.ptp(reach))
    currents = {"linear map, no compensation": linear_current}
    for method in ("exact", "analytic"):
        currents[f"{method} inverse"] = inverse(setpoint, params, operators, method=method,
                                                input_range=(-MAX_CURRENT_A, MAX_CURRENT_A))
    figures, errors = [], {}
    for name, current in currents.items():
        achieved = forward(current, params, operators)
        errors[name] = error_metrics(setpoint, achieved).to_dict()
        figures.append(Panel(f"{name}: position", t, [("setpoint", setpoint), ("model stage", achieved)],
                             "time [s]", f"position [{params.output_unit}]"))
        figures.append(Panel(f"{name}: setpoint to position", setpoint, [("achieved", achieved)],
                             f"setpoint [{params.output_unit}]", f"position [{params.output_unit}]"))
    save_panels(out_dir / "compensation.png", figures, columns=2)
    return errors


def main(argv: Sequence[str] | None = None) -> int:
    """Run the demonstration and print its figures."""
    parser = argparse.ArgumentParser(prog="sma_stage.demo", description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/demo"), help="folder for plots and reports")
    parser.add_argument("--model", type=Path, default=DEFAULT_MODEL, help="GPI model file to compensate with")
    args = parser.parse_args(argv)
    paper = evaluate_paper(args.out / "paper", operators=10)
    print("1. The paper's Table 1 under eqs 1-5 as printed "
          f"(plots and summary in {args.out / 'paper'}):")
    print(f"   a10 = {paper['table_1']['a10']}, smallest gl - gr = {paper['smallest_gl_minus_gr']:.3g}:")
    for name, values in paper["readings"].items():
        print(f"   {name:45s} loop width {values['loop_width']:.3g} of span {values['loop_span']:.4g}")
    errors = compensation_demo(args.model, args.out)
    print(f"\n2. Tracking the paper's validation signal through the model {args.model.name} "
          f"(error in % of the setpoint span; plots in {args.out / 'compensation.png'}):")
    print(f"   {'current from':32s} {'rms %':>8s} {'max %':>8s}")
    for name, values in errors.items():
        print(f"   {name:32s} {values['rms_pct']:8.3f} {values['max_pct']:8.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
