"""The PI loop when the measurement comes late, for each model family the compensator runs: tracking error
against the measurement's delay, at two lead limits. In process and deterministic (no ROS).

Through the nodes a measurement reaches the compensator a few milliseconds after the stage's step, which at the
demo's 60x pace is several control periods of simulated time. The models are identified as
bench/bench_tracking.py identifies them (the stage simulator on the paper's signals, 1 s samples): the GPI
with the effects the diagnosis adds, and the two-wire model (sma_stage.identify.two_wire.fit_two_wire,
told apart on the validation record as the pipeline does). A fresh simulator then tracks the paper's
validation signal over 80 % of the stroke as bench_tracking does, the compensator's PI loop at the gains the
compensator node derives (imc_gains for its lead limit) commanding every 0.1 s with the position measured
`delay` commands earlier. Error: the measured position after each step against the setpoint, RMS and max,
% of the stroke.

With --model-files the models are read from those files in place (say, the models the demo's refit wrote,
`out/demo/nodes/identified_model.yaml` of several `./run.sh demo --families ... --out out/demo`), run from rest.

    .venv/bin/python bench/bench_loop_delay.py [--delays 0,1,2,4,8] [--leads 2,3] [--model-files A.yaml,B.yaml]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from record_results import recorded

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_tracking import CONTROL_STEP_S, PLANT_STEP_S, Identified, Mode, Model, record, track  # noqa: E402

from sma_stage.control.compensator import imc_gains  # noqa: E402
from sma_stage.identify.pipeline import identify_recording  # noqa: E402
from sma_stage.identify.two_wire import HeldOut, fit_two_wire  # noqa: E402
from sma_stage.model.kinds import (
    AnyModel,  # noqa: E402
    load_any_model_file,  # noqa: E402
)
from sma_stage.signals import IDENTIFICATION_DURATION_S, paper_identification_signal, paper_validation_signal  # noqa: E402


def identify_both(model_files: list[str]) -> tuple[dict[str, AnyModel], tuple[float, float]]:
    """The GPI (with its diagnosed effects) and the two-wire model of the simulator, or the models in
    model_files, without state; and the stroke [m] the simulator's identification run measured."""
    applied_from_s = PLANT_STEP_S * np.arange(int(round(IDENTIFICATION_DURATION_S / PLANT_STEP_S)))
    ident, run = record(paper_identification_signal(applied_from_s), "identification")
    stroke = (float(run.measured_position_m.min()), float(run.measured_position_m.max()))
    if model_files:
        return {path: load_any_model_file(path).without_state() for path in model_files}, stroke
    valid, _ = record(paper_validation_signal(applied_from_s), "validation")
    gpi = identify_recording(ident, valid, diagnose_rounds=4).model.without_state()
    two_wire = fit_two_wire(ident.t, ident.input, ident.output,
                            held_out=HeldOut(valid.t, valid.input, valid.output)).model
    return {f"GPI ({' + '.join(gpi.effect_names) or 'no effect'})": gpi, "two-wire": two_wire}, stroke


def track_late(model: AnyModel, stroke_m: tuple[float, float], lead_limit: float, delay: int) -> tuple[float, float]:
    """(RMS, max) tracking error [% of the stroke] with the PI loop fed the position `delay` commands late."""
    gains = imc_gains(model, CONTROL_STEP_S, lead_limit)
    mode = Mode(Model("", model, float("nan")), True, gains["kp"], gains["ki"], lead_limit)
    return track(Identified((), stroke_m, 0.0), mode, CONTROL_STEP_S, delay)[:2]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--delays", default="0,1,2,4,8", help="measurement delays [control periods of 0.1 s]")
    parser.add_argument("--leads", default="2,3", help="the PI loop's lead limits (the compensator's default: 3)")
    parser.add_argument("--model-files", default="", help="comma-separated model files tracked in place of identifying")
    args = parser.parse_args(argv)
    started = time.perf_counter()
    delays = [int(text) for text in args.delays.split(",")]
    models, stroke = identify_both([path for path in args.model_files.split(",") if path])
    print(f"identified in {time.perf_counter() - started:.0f} s; tracking error RMS (max), % of the stroke\n")
    print("| model | lead limit | " + " | ".join(f"delay {delay} ({delay * CONTROL_STEP_S:g} s)" for delay in delays)
          + " |")
    print("|---|---|" + "---|" * len(delays))
    for name, model in models.items():
        for lead in (float(text) for text in args.leads.split(",")):
            cells = (track_late(model, stroke, lead, delay) for delay in delays)
            print(f"| {name} | {lead:g} | " + " | ".join(f"{rms:.2f} ({peak:.1f})" for rms, peak in cells) + " |",
                  flush=True)
    print(f"\nwall time {time.perf_counter() - started:.0f} s")
    return 0


if __name__ == "__main__":
    with recorded(__file__):
        raise SystemExit(main())
