"""Tracking the paper's validation signal on the stage simulator, in process and deterministic.

Identification: the paper's identification signal (1000 s) drives the simulator, stepped every
PLANT_STEP_S; the record kept every RECORD_EVERY steps goes through the package's identification
pipeline (identify_recording, as gpi_tool diagnose and ~/refit run it), validated on the paper's
validation signal run the same way. Two models: the plain GPI it fits and the identified model it
deploys (the GPI with the effects the diagnosis added).
Tracking: a fresh simulator
follows the validation signal scaled to STROKE_FRACTION of the stroke measured during the identification
(after SETTLE_S at the bottom of the range and SETTLE_S at the signal's first value, as the demo does),
commanded by sma_stage.control.Compensator every CONTROL_STEP_S (--control-step-s), each model
feedforward and with the PI loop (the same gains for all). Errors: the measured
position after each step against the setpoint at that time, over the signal, in % of the stroke; and
how smooth the current is: its change from one command to the next (RMS and 99th percentile over the
signal) in % of the current limit.
Holding: every mode holds a setpoint at each of HOLD_FRACTIONS of the stroke, from rest, for HOLD_S; the
settled error (|mean - setpoint| over the last half, % of the stroke) and the ripple (RMS about the mean,
um, the largest over the setpoints).

    .venv/bin/python bench/bench_tracking.py           # the table
    .venv/bin/python bench/bench_tracking.py --scan    # also the PI gain scan that chose the gains
"""

from __future__ import annotations

import argparse
import time
from collections import deque
from dataclasses import dataclass

import numpy as np
from record_results import recorded

from sma_stage.control import Compensator
from sma_stage.control.compensator import DEFAULT_LEAD_LIMIT, imc_gains
from sma_stage.identify.pipeline import identify_recording
from sma_stage.io import make_series
from sma_stage.model import IdentifiedModel
from sma_stage.plant import StageSimulator, simulate
from sma_stage.signals import IDENTIFICATION_DURATION_S, paper_identification_signal, paper_validation_signal

PLANT_STEP_S = 0.1
RECORD_EVERY = 10
CONTROL_STEP_S = 0.1
MAX_CURRENT_A = 5.0
STROKE_FRACTION = 0.8
SETTLE_S = 60.0
RUN_S = 1000.0
IDENTIFICATION_SEED = 0
TRACKING_SEED = 1
TARGETS_PCT = {False: 2.0, True: 0.5}  # RMS % of the stroke: feedforward, PI loop
HOLD_FRACTIONS = (0.2, 0.4, 0.55, 0.7, 0.85, 0.95)  # held setpoints: fractions of the stroke from its bottom
HOLD_S = 1200.0
HOLD_TARGETS_PCT = {False: 3.0, True: 0.5}  # settled error, % of the stroke: feedforward, PI loop
SCAN_KP = (0.0, 0.5, 1.0, 2.0, 4.0)
SCAN_KI = (0.3, 1.0, 2.0, 4.0, 8.0)


@dataclass(frozen=True)
class Model:
    """A model the compensator inverts, with the name the table gives it."""

    name: str
    model: IdentifiedModel
    identification_rms_pct: float


@dataclass(frozen=True)
class Identified:
    """The fitted models and the stroke [m] measured during the identification run."""

    models: tuple[Model, ...]
    stroke_m: tuple[float, float]
    seconds: float


@dataclass(frozen=True)
class Mode:
    """One tracking configuration: the model, the PI loop on or off, and its gains."""

    model: Model
    feedback: bool
    kp: float = 0.0
    ki: float = 0.0
    lead_limit: float = DEFAULT_LEAD_LIMIT  # the PI loop's lead limit [A/A]

    @property
    def name(self) -> str:
        """How the table names it."""
        loop = f"PI kp {self.kp:.3g} ki {self.ki:.3g}/s" if self.feedback else "feedforward"
        return f"{self.model.name}, {loop}"


def record(signal: np.ndarray, name: str) -> tuple:
    """(series kept every RECORD_EVERY plant steps, the whole run) of the simulator driven by signal [A]."""
    run = simulate(signal, PLANT_STEP_S, seed=IDENTIFICATION_SEED)
    kept = slice(RECORD_EVERY - 1, None, RECORD_EVERY)
    series = make_series(run.t_s[kept], run.current_a[kept], run.measured_position_m[kept], name)
    return series, run


def identify(families: tuple[str, ...] = ("gpi",)) -> Identified:
    """Run the identification and validation signals through the simulator and identify the models (the
    pipeline comparing `families`)."""
    started = time.perf_counter()
    applied_from_s = PLANT_STEP_S * np.arange(int(round(IDENTIFICATION_DURATION_S / PLANT_STEP_S)))
    ident, run = record(paper_identification_signal(applied_from_s), "identification")
    valid, _ = record(paper_validation_signal(applied_from_s), "validation")
    found = identify_recording(ident, valid, diagnose_rounds=4, families=families)
    names = getattr(found.model, "effect_names", None)  # a GPI's effects; another family is named by itself
    effects = (" + ".join(names) or "nothing added") if names is not None else f"{found.model.FAMILY} model"
    after = found.diagnosis.after.rms_pct if found.diagnosis else found.report["validation"]["rms_pct"]
    models = (Model("GPI inverse", IdentifiedModel(found.fit.parameters, found.fit.operators),
                    found.fit.identification.rms_pct),
              Model(f"identified model ({effects})", found.model.without_state(), after))
    stroke = (float(run.measured_position_m.min()), float(run.measured_position_m.max()))
    return Identified(models, stroke, time.perf_counter() - started)


def setpoints(stroke_m: tuple[float, float], t_s: np.ndarray) -> np.ndarray:
    """Setpoint [m] at times t_s [s]: SETTLE_S at the bottom, SETTLE_S at the signal's start, the signal."""
    low, high = stroke_m
    middle, half_span = 0.5 * (low + high), 0.5 * STROKE_FRACTION * (high - low)
    shape = paper_validation_signal(np.maximum(t_s - 2.0 * SETTLE_S, 0.0)) / 5.0
    return np.where(t_s < SETTLE_S, middle - half_span, middle + half_span * shape)


def compensator_for(mode: Mode) -> Compensator:
    """The control core for the mode's model and gains."""
    return Compensator(mode.model.model, MAX_CURRENT_A, kp=mode.kp, ki=mode.ki, lead_limit=mode.lead_limit)


def track(identified: Identified, mode: Mode, control_step_s: float, delay: int = 0
          ) -> tuple[float, float, float, float]:
    """(RMS, max) tracking error [% of the stroke] over the validation signal, commands every
    control_step_s [s], the loop given the position measured `delay` commands earlier, and the current's
    sample-to-sample change over it (RMS, 99th percentile) [% of MAX_CURRENT_A]."""
    compensator = compensator_for(mode)
    stage = StageSimulator(seed=TRACKING_SEED)
    steps = int(round((2.0 * SETTLE_S + RUN_S) / control_step_s))
    times = control_step_s * np.arange(steps + 1)
    wanted = setpoints(identified.stroke_m, times)
    measured, currents = np.empty(steps), np.empty(steps)
    seen = deque([stage.state.measured_position_m] * (delay + 1), maxlen=delay + 1)
    for k in range(steps):
        currents[k] = compensator.command(wanted[k], seen[0] if mode.feedback else None, control_step_s)
        measured[k] = stage.step(currents[k], control_step_s).measured_position_m
        seen.append(measured[k])
    on_signal = times[1:] >= 2.0 * SETTLE_S
    error = 100.0 * (measured - wanted[1:])[on_signal] / np.ptp(identified.stroke_m)
    change = 100.0 * np.abs(np.diff(currents[on_signal])) / MAX_CURRENT_A
    return (float(np.sqrt(np.mean(error**2))), float(np.max(np.abs(error))), float(np.sqrt(np.mean(change**2))),
            float(np.percentile(change, 99)))


def hold(identified: Identified, mode: Mode, control_step_s: float, fraction: float) -> tuple[float, float]:
    """A setpoint at `fraction` of the stroke, from a stage at rest, held for HOLD_S: (settled error
    |mean position - setpoint| over the last half [% of the stroke], ripple: RMS about that mean [um])."""
    compensator = compensator_for(mode)
    stage = StageSimulator(seed=TRACKING_SEED)
    low, high = identified.stroke_m
    target = low + fraction * (high - low)
    steps = int(round(HOLD_S / control_step_s))
    position = stage.state.measured_position_m
    positions = np.empty(steps)
    for k in range(steps):
        current = compensator.command(target, position if mode.feedback else None, control_step_s if k else 0.0)
        position = positions[k] = stage.step(current, control_step_s).measured_position_m
    settled = positions[steps // 2:]
    return (float(100.0 * abs(settled.mean() - target) / (high - low)),
            float(1e6 * np.sqrt(np.mean((settled - settled.mean())**2))))


def print_hold(identified: Identified, control_step_s: float) -> None:
    """Hold setpoints in every mode and print the table."""
    print(f"\nHolding a setpoint from rest, {HOLD_S:g} s: settled error [% of the stroke] at each fraction of the "
          "stroke; the largest ripple [um RMS]")
    print("| mode | " + " | ".join(f"{100 * fraction:g} %" for fraction in HOLD_FRACTIONS)
          + " | largest | target % | result | ripple um |")
    print("|---|" + "---|" * (len(HOLD_FRACTIONS) + 4))
    for mode in modes(identified, control_step_s):
        errors, ripples = zip(*(hold(identified, mode, control_step_s, fraction) for fraction in HOLD_FRACTIONS), strict=True)
        target = HOLD_TARGETS_PCT[mode.feedback]
        print(f"| {mode.name} | " + " | ".join(f"{error:.2f}" for error in errors)
              + f" | {max(errors):.2f} | {target:g} | {'pass' if max(errors) <= target else 'FAIL'} "
              f"| {max(ripples):.2f} |", flush=True)


def modes(identified: Identified, control_step_s: float) -> list[Mode]:
    """The table's modes: every model feedforward, then with the PI loop at the gains the compensator derives
    from it (imc_gains), all at the compensator node's defaults."""
    return ([Mode(model, False) for model in identified.models]
            + [Mode(model, True, **imc_gains(model.model, control_step_s)) for model in identified.models])


def print_identification(identified: Identified) -> None:
    """The fitted models the tracking uses."""
    low, high = identified.stroke_m
    print(f"Identification ({identified.seconds:.1f} s): stroke {1e6 * low:.1f} to {1e6 * high:.1f} um")
    for model in identified.models:
        effects = "; ".join(f"{effect.kind} {effect.parameters}" for effect in model.model.effects) or "no effect"
        print(f"  {model.name}: {model.model.operators} operators, {effects}; "
              f"{model.identification_rms_pct:.2f} % RMS ({'validation' if model.model.effects else 'identification'})")


def print_table(identified: Identified, control_step_s: float) -> dict[bool, float]:
    """Track in every mode and print the table; the best RMS [%] without and with the PI loop."""
    print("\n| mode | RMS % of stroke | max % of stroke | target RMS % | result | current step RMS % | "
          "current step p99 % | seconds |")
    print("|---|---|---|---|---|---|---|---|")
    best = {False: np.inf, True: np.inf}
    for mode in modes(identified, control_step_s):
        started = time.perf_counter()
        rms, peak, step_rms, step_p99 = track(identified, mode, control_step_s)
        target = TARGETS_PCT[mode.feedback]
        best[mode.feedback] = min(best[mode.feedback], rms)
        print(f"| {mode.name} | {rms:.3f} | {peak:.3f} | {target:g} | {'pass' if rms <= target else 'FAIL'} "
              f"| {step_rms:.2f} | {step_p99:.2f} | {time.perf_counter() - started:.1f} |", flush=True)
    return best


def print_scan(identified: Identified, control_step_s: float) -> None:
    """RMS (max) tracking error [% of stroke] over a grid of PI gains, for every model."""
    for model in identified.models:
        print(f"\nPI gain scan, {model.name}: RMS % (max %) of the stroke")
        print("| kp \\ ki [1/s] | " + " | ".join(f"{ki:g}" for ki in SCAN_KI) + " |")
        print("|---|" + "---|" * len(SCAN_KI))
        for kp in SCAN_KP:
            cells = [track(identified, Mode(model, True, kp, ki), control_step_s)[:2] for ki in SCAN_KI]
            print(f"| {kp:g} | " + " | ".join(f"{rms:.3f} ({peak:.2f})" for rms, peak in cells) + " |", flush=True)


def main() -> int:
    """Identify, track in every mode, print the table (and the gain scan with --scan)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scan", action="store_true", help="also scan the PI gains")
    parser.add_argument("--control-step-s", type=float, default=CONTROL_STEP_S,
                        help=f"control period [s] (default {CONTROL_STEP_S:g})")
    args = parser.parse_args()
    started = time.perf_counter()
    print(f"Plant stepped every {PLANT_STEP_S:g} s in the identification, record every "
          f"{PLANT_STEP_S * RECORD_EVERY:g} s; control and plant step every {args.control_step_s:g} s in "
          f"the tracking; validation signal over {100 * STROKE_FRACTION:g} % of the stroke, {RUN_S:g} s.")
    identified = identify()
    print_identification(identified)
    best = print_table(identified, args.control_step_s)
    for feedback, label in ((False, "feedforward"), (True, "with the PI loop")):
        met = "met" if best[feedback] <= TARGETS_PCT[feedback] else "NOT met"
        print(f"target {label}: at most {TARGETS_PCT[feedback]:g} % RMS: {met} (best {best[feedback]:.3f} %)")
    print_hold(identified, args.control_step_s)
    if args.scan:
        print_scan(identified, args.control_step_s)
    print(f"\nwall time {time.perf_counter() - started:.1f} s")
    return 0


if __name__ == "__main__":
    with recorded(__file__):
        raise SystemExit(main())
