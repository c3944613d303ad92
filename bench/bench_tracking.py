"""Tracking the paper's validation signal on the stage simulator, in process and deterministic.

Identification: the paper's identification signal (1000 s) drives the simulator, stepped every
PLANT_STEP_S; the record kept every RECORD_EVERY steps is fitted with a GPI (fit_gpi's own operator
count), with the thermal_lag effect (the GPI sees the current through tau v' = u - v; its operator count
chosen again) and, here in the benchmark, with the same lag on the Joule heating u |u| / 5 A instead of
the current ("power lag": tau searched on the GPI's RMS error, then fit_gpi's own operator count).
Tracking: a fresh simulator
follows the validation signal scaled to STROKE_FRACTION of the stroke measured during the identification
(after SETTLE_S at the bottom of the range and SETTLE_S at the signal's first value, as the demo does),
commanded by sma_stage.control.Compensator every CONTROL_STEP_S (--control-step-s), each model
feedforward and with the PI loop (the same gains for all). Errors: the measured
position after each step against the setpoint at that time, over the signal, in % of the stroke.

    .venv/bin/python bench/bench_tracking.py           # the table
    .venv/bin/python bench/bench_tracking.py --scan    # also the PI gain scan that chose the gains
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

from sma_stage.control import Compensator
from sma_stage.identify.effects import fit_effect, lagged_input, recount_effect
from sma_stage.identify.fit import fit_gpi
from sma_stage.model import GPIInverseStream, GPIParameters
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
TARGETS_PCT = {False: 3.0, True: 0.5}  # RMS % of the stroke: feedforward, PI loop
PI_GAINS = (2.0, 4.0)  # kp [m/m], ki [1/s]: from the scan (--scan), the same for every model
POWER_LAG_TAU_RANGE_S = (1.0, 100.0)
SCAN_KP = (0.0, 0.5, 1.0, 2.0, 4.0)
SCAN_KI = (0.3, 1.0, 2.0, 4.0, 8.0)


@dataclass(frozen=True)
class Model:
    """A fitted model the compensator inverts: the GPI, its lag [s] (0: none), lag on the Joule heating."""

    name: str
    parameters: GPIParameters
    operators: int
    tau_s: float
    power_lag: bool
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

    @property
    def name(self) -> str:
        """How the table names it."""
        loop = f"PI kp {self.kp:g} ki {self.ki:g}/s" if self.feedback else "feedforward"
        return f"{self.model.name}, {loop}"


def heating(u: np.ndarray) -> np.ndarray:
    """The Joule heating the relay routes to one wire, signed, in units of current: u |u| / 5 A."""
    return u * np.abs(u) / MAX_CURRENT_A


def fit_power_lag(t: np.ndarray, u: np.ndarray, y: np.ndarray, operators: int) -> Model:
    """The GPI driven by v with tau v' = heating(u) - v: tau [s] minimising the fit's RMS error (at
    `operators`), then the fit at that tau with fit_gpi's own operator count."""
    def rms_pct(log_tau: float) -> float:
        return fit_gpi(lagged_input(t, heating(u), np.exp(log_tau)), y, operators=operators).identification.rms_pct

    bounds = np.log(POWER_LAG_TAU_RANGE_S)
    tau = float(np.exp(minimize_scalar(rms_pct, bounds=bounds, method="bounded", options={"xatol": 1e-2}).x))
    fit = fit_gpi(lagged_input(t, heating(u), tau), y)
    return Model("GPI + power-lag lead", fit.parameters, fit.operators, tau, True, fit.identification.rms_pct)


def identify() -> Identified:
    """Run the identification signal through the simulator and fit the three models."""
    started = time.perf_counter()
    steps = int(round(IDENTIFICATION_DURATION_S / PLANT_STEP_S))
    applied_from_s = PLANT_STEP_S * np.arange(steps)
    current = paper_identification_signal(applied_from_s)
    run = simulate(current, PLANT_STEP_S, seed=IDENTIFICATION_SEED)
    kept = slice(RECORD_EVERY - 1, None, RECORD_EVERY)
    t, u, y = run.t_s[kept], run.current_a[kept], run.measured_position_m[kept]
    gpi = fit_gpi(u, y)
    lag = recount_effect(fit_effect("thermal_lag", t, u, y, gpi), t, u, y)
    models = (Model("GPI inverse", gpi.parameters, gpi.operators, 0.0, False, gpi.identification.rms_pct),
              Model("GPI + lag lead", lag.gpi_parameters, lag.operators, lag.parameters["tau_s"], False,
                    lag.identification.rms_pct),
              fit_power_lag(t, u, y, gpi.operators))
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
    model = mode.model
    inverse = GPIInverseStream(model.parameters, model.operators, "exact",
                               input_range=(-MAX_CURRENT_A, MAX_CURRENT_A))
    return Compensator(inverse, lag_tau_s=model.tau_s, kp=mode.kp, ki=mode.ki, power_lag=model.power_lag)


def track(identified: Identified, mode: Mode, control_step_s: float) -> tuple[float, float]:
    """(RMS, max) tracking error [% of the stroke] over the validation signal, commands every
    control_step_s [s]."""
    compensator = compensator_for(mode)
    stage = StageSimulator(seed=TRACKING_SEED)
    steps = int(round((2.0 * SETTLE_S + RUN_S) / control_step_s))
    times = control_step_s * np.arange(steps + 1)
    wanted = setpoints(identified.stroke_m, times)
    measured = np.empty(steps)
    position = stage.state.measured_position_m
    for k in range(steps):
        current = compensator.command(wanted[k], position if mode.feedback else None, control_step_s)
        position = stage.step(current, control_step_s).measured_position_m
        measured[k] = position
    on_signal = times[1:] >= 2.0 * SETTLE_S
    error = 100.0 * (measured - wanted[1:])[on_signal] / np.ptp(identified.stroke_m)
    return float(np.sqrt(np.mean(error**2))), float(np.max(np.abs(error)))


def modes(identified: Identified) -> list[Mode]:
    """The table's modes: every model feedforward, then every model with the PI loop at PI_GAINS."""
    return ([Mode(model, False) for model in identified.models]
            + [Mode(model, True, *PI_GAINS) for model in identified.models])


def print_identification(identified: Identified) -> None:
    """The fitted models the tracking uses."""
    low, high = identified.stroke_m
    print(f"Identification ({identified.seconds:.1f} s): stroke {1e6 * low:.1f} to {1e6 * high:.1f} um")
    for model in identified.models:
        print(f"  {model.name}: {model.operators} operators, tau {model.tau_s:.2f} s, "
              f"{model.identification_rms_pct:.2f} % RMS on the identification record")


def print_table(identified: Identified, control_step_s: float) -> dict[bool, float]:
    """Track in every mode and print the table; the best RMS [%] without and with the PI loop."""
    print("\n| mode | RMS % of stroke | max % of stroke | target RMS % | result | seconds |")
    print("|---|---|---|---|---|---|")
    best = {False: np.inf, True: np.inf}
    for mode in modes(identified):
        started = time.perf_counter()
        rms, peak = track(identified, mode, control_step_s)
        target = TARGETS_PCT[mode.feedback]
        best[mode.feedback] = min(best[mode.feedback], rms)
        print(f"| {mode.name} | {rms:.3f} | {peak:.3f} | {target:g} | {'pass' if rms <= target else 'FAIL'} "
              f"| {time.perf_counter() - started:.1f} |", flush=True)
    return best


def print_scan(identified: Identified, control_step_s: float) -> None:
    """RMS (max) tracking error [% of stroke] over a grid of PI gains, for every model."""
    for model in identified.models:
        print(f"\nPI gain scan, {model.name}: RMS % (max %) of the stroke")
        print("| kp \\ ki [1/s] | " + " | ".join(f"{ki:g}" for ki in SCAN_KI) + " |")
        print("|---|" + "---|" * len(SCAN_KI))
        for kp in SCAN_KP:
            cells = [track(identified, Mode(model, True, kp, ki), control_step_s) for ki in SCAN_KI]
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
    if args.scan:
        print_scan(identified, args.control_step_s)
    print(f"\nwall time {time.perf_counter() - started:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
