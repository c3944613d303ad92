"""The demonstration behind `./run.sh demo`: the paper's Table 1, hysteresis compensation with the GPI
inverse on the paper's validation signal, and the three nodes end to end on the simulated stage.
Writes plots under --out and prints the figures."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from contextlib import ExitStack
from pathlib import Path

import numpy as np

from sma_stage.cli import family_list
from sma_stage.commands.paper import evaluate_paper
from sma_stage.errors import InputError
from sma_stage.identify.metrics import error_metrics
from sma_stage.model import forward, inverse, load_model_file
from sma_stage.nodes.end_to_end import (
    MAX_CURRENT_A,
    RUN_ORDER,
    EndToEndSettings,
    default_domain_id,
    describe_diagnosis,
    run_end_to_end,
    sigterm_as_exit,
    start_nodes,
)
from sma_stage.nodes.launch import DEFAULT_MODEL_FILE
from sma_stage.plots import Panel, save_panels
from sma_stage.signals import paper_validation_signal


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


# --- part 3: the three nodes as separate processes ------------------------------------------------


def print_end_to_end(result: dict, settings: EndToEndSettings, out_dir: Path) -> None:
    """The end-to-end figures as the README quotes them."""
    report, (low, high) = result["report"], result["stroke_m"]
    seconds = result["seconds"]
    print(f"\n3. End to end: stage_node, compensator_node and identification_node as separate processes "
          f"(ROS_DOMAIN_ID {result['domain_id']}, logs in {result['work_dir']}); the simulated stage runs "
          f"{settings.time_scale:g}x faster than real time, {settings.rate_hz:g} steps per wall second; one step, "
          f"one control period and one setpoint every {settings.step_s:g} s of simulated time.")
    print(f"   nodes launched before part 1, serving {seconds['start']:.1f} s later; ~/excite ({settings.excite_duration_s:g} s of the paper's "
          f"identification signal) and ~/refit took {seconds['excite_and_refit']:.1f} s")
    ident, valid = report["identification"], report["validation"]
    print(f"   ~/refit: {report['gpi_fit']['operators']} operators on {ident['samples']} samples in "
          f"{report['fit_seconds']:.1f} s; error rms {ident['rms_pct']:.2f} % max {ident['max_pct']:.2f} %; "
          f"held-out tail ({valid['samples']} samples) rms {valid['rms_pct']:.2f} % max {valid['max_pct']:.2f} %")
    print(f"   {describe_diagnosis(report)}")
    print(f"   model file {report['model_file']}; {report['compensator']['message']}; the compensator "
          f"{'holds' if result['compensator_holds_fit'] else 'does NOT hold'} the fitted parameters")
    print(f"   measured stroke {1e6 * low:.1f} to {1e6 * high:.1f} um; the paper's validation signal scaled to "
          f"{100 * settings.stroke_fraction:g} % of it, {settings.run_s:g} s, through the exact inverse alone "
          f"(feedforward) and with the PI loop (the compensator's default: gains derived from the model); error "
          f"in % of the stroke, current_cmd's change from one message to the next in % of {MAX_CURRENT_A:g} A, "
          f"the pace achieved in simulated s per wall s (the stage's time_scale when every node keeps up) and the "
          f"longest time between two setpoints the demo published, in simulated s ({settings.step_s:g} when it "
          f"kept up), plots in {out_dir / 'tracking.png'}:")
    print(f"   {'compensator model, mode':40s} {'rms %':>8s} {'max %':>8s} {'step rms %':>11s} {'step p99 %':>11s} "
          f"{'pace':>6s} {'gap s':>6s}")
    for key in RUN_ORDER:
        run = result["runs"].get(key)
        if run is None:
            print(f"   {key:40s} not run: {report['compensator']['message']}")
        else:
            still = np.ptp(run.current[np.isfinite(run.current)]) == 0.0
            print(f"   {key:40s} {run.rms_pct:8.3f} {run.max_pct:8.2f} {run.current_step_rms_pct:11.2f} "
                  f"{run.current_step_p99_pct:11.2f} {run.pace:6.1f} {run.setpoint_gap_s:6.1f}"
                  + (f"   (current_cmd stayed at {run.current[-1]:g} A throughout)" if still else ""))
    print(f"   wall time from the nodes' launch to their exit: {seconds['total']:.1f} s")


def main(argv: Sequence[str] | None = None) -> int:
    """Run the demonstration and print its figures."""
    parser = argparse.ArgumentParser(prog="sma_stage.demo", description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/demo"), help="folder for plots and reports")
    parser.add_argument("--model", type=Path, default=DEFAULT_MODEL_FILE, help="GPI model file to compensate with")
    parser.add_argument("--no-nodes", action="store_true", help="skip part 3 (the ROS 2 nodes end to end)")
    parser.add_argument("--time-scale", type=float, default=EndToEndSettings.time_scale,
                        help="simulated seconds per wall second in part 3")
    parser.add_argument("--domain-id", type=int, default=None,
                        help="ROS_DOMAIN_ID for part 3 (default: $ROS_DOMAIN_ID, else derived from the pid)")
    parser.add_argument("--families", type=family_list, default=EndToEndSettings.families,
                        help="model families the refit in part 3 compares, comma-separated (default: all, "
                             "gpi,gpi_free,two_wire,bouc_wen; the GPI alone: gpi)")
    args = parser.parse_args(argv)
    began = time.monotonic()
    with ExitStack() as stack:
        nodes, settings, launched_at = None, EndToEndSettings(time_scale=args.time_scale, families=args.families), time.monotonic()
        if not args.no_nodes:
            from sma_stage.nodes.launch import NodeProcesses

            domain_id = default_domain_id() if args.domain_id is None else args.domain_id
            stack.enter_context(sigterm_as_exit())
            nodes = stack.enter_context(NodeProcesses(args.out / "nodes", domain_id))
            start_nodes(nodes, settings)  # they start up while parts 1 and 2 run
        model_parts(args.out, args.model)
        if nodes is None:
            return 0
        sys.stdout.flush()
        try:
            result = run_end_to_end(nodes, settings, args.out, launched_at)
        except InputError as error:
            print(f"error: part 3 (nodes end to end): {error}", file=sys.stderr)
            return 2
    print_end_to_end(result, settings, args.out)
    print(f"\nDemonstration wall time: {time.monotonic() - began:.1f} s")
    return 0


def model_parts(out_dir: Path, model_path: Path) -> None:
    """Parts 1 and 2: the paper's Table 1, and compensation through the model alone."""
    paper = evaluate_paper(out_dir / "paper", operators=10)
    print("1. The paper's Table 1 under eqs 1-5 as printed "
          f"(plots and summary in {out_dir / 'paper'}):")
    print(f"   a10 = {paper['table_1']['a10']}, smallest gl - gr = {paper['smallest_gl_minus_gr']:.3g}:")
    for name, values in paper["readings"].items():
        print(f"   {name:45s} loop width {values['loop_width']:.3g} of span {values['loop_span']:.4g}")
    errors = compensation_demo(model_path, out_dir)
    print(f"\n2. Tracking the paper's validation signal through the model {model_path.name} "
          f"(error in % of the setpoint span; plots in {out_dir / 'compensation.png'}):")
    print(f"   {'current from':32s} {'rms %':>8s} {'max %':>8s}")
    for name, values in errors.items():
        print(f"   {name:32s} {values['rms_pct']:8.3f} {values['max_pct']:8.3f}")


def run(argv: Sequence[str] | None = None) -> int:
    """main(), with Ctrl-C ending it quietly (status 130) once every child process has been stopped."""
    try:
        return main(argv)
    except KeyboardInterrupt:
        print("\nsma_stage.demo: interrupted; the node processes were stopped", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(run())
