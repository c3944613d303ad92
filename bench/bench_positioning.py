"""Positioning stages the control law was not tuned on: each plant identified by the package from the paper's
identification record (the family `diagnose` chooses, as `gpi_tool diagnose` does), then driven by
sma_stage.control.Compensator through setpoints of several shapes: feedforward and with the PI loop, each without
and with a preview (the setpoint Compensator.preview_s() ahead, as a stamped stream sent early gives the node), and
the PI loop with the preview told a sine's period (Compensator.learning_period_s: it learns the error that repeats;
scored over the whole shape as every mode, its first periods included; a shape that does not repeat runs it as the
PI loop with the preview).
Prints one table and writes it to bench/results/positioning.md (--out), with how fast the full current crosses
the setpoints' band on each plant (no law crosses it faster) and, over the plants, each shape's and mode's RMS range
and how many plants are within issue 49's targets.

    .venv/bin/python bench/bench_positioning.py [--plants simulator,nominal,...] [--out FILE] [--seed 0]
        [--record paper|designed|paper+tracking] [--validate-levels] [--families gpi,...]
    .venv/bin/python bench/bench_positioning.py --reversal-speeds 1,2,3,4 [--plants ...]
    .venv/bin/python bench/bench_positioning.py --where [--plants ...] [--seed 0]

With --families, the families `diagnose` compares (default: `gpi_tool diagnose`'s); naming two_wire_compact writes
the table to ..._compact.md unless --out says where.

With --record designed, each plant is identified instead from what `gpi_tool excitation probe` and `designed --probe`
would run on it (a 100 s probe, then the design from it drawn with the seed; 1000 s in all), the setpoints still
over 70 % of the stroke the paper's record reached (bench/results/positioning_designed.md).

With --record paper+tracking, each plant is identified from the paper's record, then the loop with the preview tracks a
70 s sine over 70 % of the stroke for 500 s with that model (a shape the table does not score), and the plant is
identified again on both records, 1560 s in all, as a user would refit on what the stage recorded while it positioned
(bench/results/positioning_tracking.md).

With --validate-levels, each identification is also validated on held random levels (what `gpi_tool excitation
levels --seed N` writes, N the bench's seed, run from the plant's own settled stage), the family, the effects and the
two-wire model's start and tension coupling chosen on the record each predicts worst, as docs/experiment.md tells a
user to do (`diagnose --validate`; bench/results/positioning_levels.md, or positioning_designed_levels.md).

With --reversal-speeds, instead: the held levels in the PI loop (without and with the preview) at each value of the
compensator's REVERSAL_SPEED (the integral's gain while a held setpoint's reversals go through the linear path), one
table written to bench/results/reversal_speed.md (--out).

With --where, instead: where the law the node runs by default (the PI loop with the preview) misses on the 20, 50
and 100 s sines: per plant and sine, the error and the model's own miss (model_miss) by the time since the relay
last switched wire, and the current's p99 change with and without the commands that switch it (two a period: on
the 20 s sine 2 % of the commands, so the p99 of every command is a switch's jump), one table written to
bench/results/positioning_where.md (--out).

Plants: the package's stage simulator; every variant of test/antagonistic_plant.py (a second physical stage the
model code did not make: Preisach hysterons per wire, stress coupling, detwinning, a lever); and three variants
made here from the same physics: `slow_wires` (thicker wires, less convection), `fast_wires` (thinner wires,
more convection) and `upper_band` (transformation temperatures 67 K higher: held currents below about 3 A do
not move the stage, 3.5 A moves it 20 % of its reach, 5 A all of it). Each plant is sampled and commanded every 0.2 s; its identification record is the paper's
decaying sine (1000 s), validated on the paper's validation record from its own settled stage. The tracking
continues the plant that ran the identification record, so that the model's carried state is the stage's.

Setpoints, each over 70 % of the stroke the identification record reached, centred, after 60 s at the shape's
first value (not scored): sines of 20, 50, 100 and 250 s period (400 s; 500 s for 250 s), the paper's validation
shape (1000 s), three draws of eight random levels held 60 s each (settled: the mean error over the last 20 s of
each hold, the position at each instant against the setpoint of that instant; the mean and the largest over the
holds) and a slow ramp (300 s up, 300 s down). Columns: RMS and max error [% of the
stroke] over the scored part, and the current's change from one command to the next (99th percentile, % of the
5 A limit), so that a law that chatters cannot win. A preview is scored against the setpoint of each instant as
everything else: its early departure before a step counts in the settled error of the hold before.
"""

from __future__ import annotations

import argparse
import copy
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "test"))

import antagonistic_plant as physical  # noqa: E402
from record_results import machine  # noqa: E402

from sma_stage.cli import family_list  # noqa: E402
from sma_stage.control import Compensator  # noqa: E402
from sma_stage.control import compensator as compensator_module  # noqa: E402
from sma_stage.control.compensator import imc_gains  # noqa: E402
from sma_stage.experiment.design import designed_signal  # noqa: E402
from sma_stage.experiment.probe import analyse_probe, probe_duration_s, probe_signal  # noqa: E402
from sma_stage.identify.families import FAMILIES  # noqa: E402
from sma_stage.identify.pipeline import identify_recording  # noqa: E402
from sma_stage.io import make_series  # noqa: E402
from sma_stage.io.atomic import atomic_write_text  # noqa: E402
from sma_stage.model.kinds import AnyModel  # noqa: E402
from sma_stage.plant import StageSimulator  # noqa: E402
from sma_stage.signals import held_levels_signal  # noqa: E402

PERIOD_S = 0.2
RECORD_S = 1000.0
PROBE_S = probe_duration_s(RECORD_S)  # of the designed record, the package's default share (100 s)
RECORDS = {  # --record: (the results file's stem, what the title adds)
    "paper": ("positioning", ""),
    "designed": ("positioning_designed", ", each identified from the probe and the designed excitation"),
    "paper+tracking": ("positioning_tracking", ", each identified again with a record of the loop tracking a sine"),
}
TRACKING_PERIOD_S, TRACKING_S = 70.0, 500.0  # paper+tracking: the loop's sine then recorded (no shape of the table)
MAX_CURRENT_A = 5.0
STROKE_FRACTION = 0.7
LEAD_IN_S = 60.0
SINE_PERIODS_S = (20.0, 50.0, 100.0, 250.0)
HOLD_S, SETTLED_S, HOLDS, LEVEL_DRAWS = 60.0, 20.0, 8, 3
LOOP_TARGET_PCT, FEEDFORWARD_TARGET_PCT, HELD_TARGET_PCT, CHANGE_TARGET_PCT = 1.0, 3.0, 0.2, 5.0  # issue 49's targets
NEW_VARIANTS = {
    "slow_wires": replace(physical.Stage(), wire_diameter_m=0.75e-3, convection_w_m2_k=100.0),
    "fast_wires": replace(physical.Stage(), wire_diameter_m=0.4e-3, convection_w_m2_k=250.0),
    "upper_band": replace(physical.Stage(), austenite_start_k=400.0, austenite_finish_k=425.0,
                          martensite_start_k=385.0, martensite_finish_k=360.0),
}
PLANTS = ["simulator", *physical.VARIANTS, *NEW_VARIANTS]


class SimulatorPlant:
    """The package's stage simulator; a record's sample k holds the position after its current was applied."""

    SAMPLE_AFTER_CURRENT = True

    def __init__(self, seed: int) -> None:
        self.stage = StageSimulator(seed=seed)

    def record(self, current: np.ndarray, set_noise: bool = True) -> np.ndarray:  # noqa: ARG002 -- its own noise
        return np.array([self.step(value) for value in current])

    def step(self, current_a: float) -> float:
        """Apply current_a [A] for PERIOD_S; the measured position [m] at the end."""
        return self.stage.step(current_a, PERIOD_S).measured_position_m


class PhysicalPlant:
    """test/antagonistic_plant.py's stage, settled at zero current; a record's sample k holds the position when its
    current starts (as that module records); noise NOISE_PCT % of the identification record's span."""

    SAMPLE_AFTER_CURRENT = False

    def __init__(self, stage: physical.Stage, seed: int) -> None:
        self.plant = physical.AntagonisticStage(stage)
        self.rng = np.random.default_rng(seed)
        self.noise_m = 0.0
        for _ in range(int(physical.HISTORY_S / PERIOD_S)):
            self._advance(0.0)

    def _advance(self, current_a: float) -> None:
        for _ in range(physical.SUBSTEPS):
            self.plant.step(current_a, PERIOD_S / physical.SUBSTEPS)

    def record(self, current: np.ndarray, set_noise: bool = True) -> np.ndarray:
        """The positions [m] as the current [A] runs (noise from this record's span, or with set_noise False the
        noise of the record before)."""
        positions = np.empty(current.size)
        for k, value in enumerate(current):
            positions[k] = self.plant.position_m
            self._advance(float(value))
        if set_noise:
            self.noise_m = physical.NOISE_PCT / 100.0 * float(np.ptp(positions))
        return positions + self.rng.normal(0.0, self.noise_m, positions.size)

    def step(self, current_a: float) -> float:
        """Apply current_a [A] for PERIOD_S; the measured position [m] at the end."""
        self._advance(current_a)
        return self.plant.position_m + self.rng.normal(0.0, self.noise_m)


def make_plant(name: str, seed: int) -> SimulatorPlant | PhysicalPlant:
    if name == "simulator":
        return SimulatorPlant(seed)
    return PhysicalPlant({**physical.VARIANTS, **NEW_VARIANTS}[name], seed)


@dataclass
class Identified:
    """A plant after its identification record, the model the package chose, the stroke it reached [m] and the time of
    the record's last sample [s] (where the model's carried state is)."""

    plant: SimulatorPlant | PhysicalPlant
    model: AnyModel
    name: str
    validation_rms_pct: float
    stroke_m: tuple[float, float]
    seconds: float
    record_end_s: float


def identify(name: str, seed: int, record: str = "paper", levels: bool = False,
             families: tuple[str, ...] = FAMILIES) -> Identified:
    """Run the plant through its identification record and identify it (every family, 4 rounds, as `gpi_tool
    diagnose` does); the validation record (the paper's) runs on a fresh plant of the same kind, and with `levels`
    held random levels (held_levels_signal drawn with the seed) on another. record: "paper" (the paper's decaying
    sine) or "designed" (designed_run), or "paper+tracking" (tracking_run: the paper's record, then the loop with
    the preview tracking a sine with the model from it, identified again on both). The stroke is what the paper's
    record reached in every case, so that every table tracks the same setpoints."""
    started = time.perf_counter()
    t = PERIOD_S * np.arange(int(RECORD_S / PERIOD_S))
    plant = make_plant(name, seed)
    current = physical.paper_identification(t)
    paper_y = y_ident = plant.record(current)
    if record == "designed":
        plant = make_plant(name, seed)
        current, y_ident = designed_run(plant, seed)
    y_valid = make_plant(name, seed + 1).record(physical.paper_validation(t))
    valid = make_series(t, physical.paper_validation(t), y_valid, "validation")
    more = []
    if levels:
        held = held_levels_signal(t, MAX_CURRENT_A, seed=seed)
        more.append(make_series(t, held, make_plant(name, seed + 2).record(held), "held levels"))
    ident = make_series(t, current, y_ident, "identification")
    found = identify_recording(ident, valid, diagnose_rounds=4, workers=2, families=families, more_validation=more)
    stroke = (float(paper_y.min()), float(paper_y.max()))
    if record == "paper+tracking":
        first = Identified(plant, found.model, "", math.nan, stroke, 0.0, float(ident.t[-1]))
        tracked = tracking_run(first)
        both = np.r_[current, tracked]
        ident = make_series(PERIOD_S * np.arange(both.size), both, np.r_[y_ident, plant.record(tracked, False)],
                            "identification and tracking")
        found = identify_recording(ident, valid, diagnose_rounds=4, workers=2, families=families, more_validation=more)
    rows = found.report.get("families") or []
    chosen = [row for row in rows if row["chosen"]]
    valid_rms = chosen[0]["validation"]["rms_pct"] if chosen else found.report["validation"]["rms_pct"]
    described = chosen[0]["model"] if chosen else "gpi"
    return Identified(plant, found.model, described, valid_rms, stroke, time.perf_counter() - started,
                      float(ident.t[-1]))


def tracking_run(identified: Identified) -> np.ndarray:
    """The currents [A] the loop with the preview gives a copy of the plant tracking a sine of TRACKING_PERIOD_S for
    TRACKING_S after the lead-in (`drive`; the compensator's first current first): what a user records while
    positioning, to identify again on."""
    _, currents, _ = drive(identified, lambda s: np.sin(2.0 * np.pi * s / TRACKING_PERIOD_S), LOOP_PREVIEW,
                           TRACKING_S)
    return applied_currents(identified, currents)


def applied_currents(identified: Identified, currents: np.ndarray) -> np.ndarray:
    """Every current [A] a `drive` applied to the plant: the compensator's first (before its first command), then
    the commands."""
    return np.r_[Compensator(identified.model, MAX_CURRENT_A).drive.initial_current(), currents]


def designed_run(plant: SimulatorPlant | PhysicalPlant, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The excitation `gpi_tool excitation probe` and then `designed --probe` would give this plant, run on it
    whole (RECORD_S, the first PROBE_S the probe, the design drawn with `seed`): (current [A], position [m])."""
    t_probe = PERIOD_S * np.arange(int(PROBE_S / PERIOD_S))
    probe_current = probe_signal(t_probe, MAX_CURRENT_A, PROBE_S)
    probe_y = plant.record(probe_current)
    found = analyse_probe(t_probe, probe_current, probe_y)
    t_design = PERIOD_S * np.arange(int((RECORD_S - PROBE_S) / PERIOD_S))
    design_current = designed_signal(t_design, found, RECORD_S - PROBE_S, seed)
    return np.r_[probe_current, design_current], np.r_[probe_y, plant.record(design_current)]


def sine(period_s: float) -> Callable[[np.ndarray], np.ndarray]:
    """A sine of period_s [s] in [-1, 1] of time since it began [s]."""
    return lambda s: np.sin(2.0 * np.pi * s / period_s)


def shapes(seed: int) -> dict[str, Callable[[np.ndarray], np.ndarray]]:
    """Setpoint shapes in [-1, 1] of time since the shape began [s], by name."""
    draws = [np.random.default_rng(seed + 7 + draw).uniform(-1.0, 1.0, HOLDS) for draw in range(LEVEL_DRAWS)]
    held = {f"held levels {draw + 1}": (lambda s, levels=levels: levels[np.minimum((s // HOLD_S).astype(int), HOLDS - 1)])
            for draw, levels in enumerate(draws)}
    sines = {f"sine {period:g} s": sine(period) for period in SINE_PERIODS_S}
    return {**sines,
            "paper's validation": lambda s: physical.paper_validation(s) / 5.0,
            **held,
            "slow ramp": lambda s: 1.0 - 2.0 * np.abs(s / 300.0 - 1.0)}


def repeat_period_s(shape: str) -> float:
    """The shape's period [s] where it repeats within its duration (the sines), else 0."""
    return next((period for period in SINE_PERIODS_S if shape == f"sine {period:g} s"), 0.0)


def duration_s(shape: str) -> float:
    if shape.startswith("held levels"):
        return HOLD_S * HOLDS
    return {"sine 250 s": 500.0, "paper's validation": 1000.0, "slow ramp": 600.0}.get(shape, 400.0)


@dataclass(frozen=True)
class Tracked:
    rms_pct: float
    max_pct: float
    change_p99_pct: float
    settled_mean_pct: float | None = None
    settled_max_pct: float | None = None
    holds_within: int = 0  # held levels: the holds settled within HELD_TARGET_PCT
    model_rms_pct: float = float("nan")  # the model's own RMS error on the currents the plant was given


@dataclass(frozen=True)
class Mode:
    """How the compensator is run: with the PI loop (feedback) or not, given the setpoint preview_s ahead or not, and
    told the period of a setpoint that repeats (learning: Compensator.learning_period_s, the shape's repeat_period_s).
    core: the law's class (the package's Compensator, or a candidate law of bench/bench_candidate_laws.py)."""

    name: str
    feedback: bool
    preview: bool
    learning: bool = False
    core: type[Compensator] = Compensator


LOOP_PREVIEW = Mode("PI loop, preview", True, True)  # the law the node runs by default
MODES = [Mode("feedforward", False, False), Mode("feedforward, preview", False, True),
         Mode("PI loop", True, False), LOOP_PREVIEW, Mode("PI loop, preview, learning", True, True, True)]


def drive(identified: Identified, form: Callable[[np.ndarray], np.ndarray], mode: Mode, seconds: float,
          learning_period_s: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The plant (a copy of it after its identification record) driven for LEAD_IN_S at the shape's first value, then
    `seconds` through the shape, by the compensator; with a preview the compensator is given the setpoint its
    preview_s ahead (to the nearest step); with learning_period_s (the PI loop) the compensator learns a setpoint of
    that period from the shape's start (Compensator.learning_period_s); a law with a `foresee` method (a candidate of
    bench/bench_candidate_laws.py) is told before each command the setpoint any seconds beyond the preview's (the
    shape's last one past its end). (positions [m] after each command, the currents [A], the setpoints
    [m], one more than the commands: positions[k] is measured when setpoint k + 1 is due)."""
    plant = copy.deepcopy(identified.plant)
    model = identified.model
    feedback = mode.feedback
    gains = imc_gains(model, PERIOD_S) if feedback else {"kp": 0.0, "ki": 0.0}
    compensator = mode.core(model, MAX_CURRENT_A, **gains)
    ahead = round(compensator.preview_s(feedback) / PERIOD_S) if mode.preview else 0
    low, high = identified.stroke_m
    span = high - low
    centre, half = 0.5 * (low + high), 0.5 * STROKE_FRACTION * span
    lead_in = int(LEAD_IN_S / PERIOD_S)
    steps = lead_in + int(seconds / PERIOD_S)
    since_s = np.maximum(PERIOD_S * (np.arange(steps + 1 + ahead) - lead_in), 0.0)
    wanted = centre + half * form(since_s)
    foresee = getattr(compensator, "foresee", None)  # a candidate law that looks further ahead than the preview
    measured = plant.step(compensator.drive.initial_current())
    positions, currents = np.empty(steps), np.empty(steps)
    for k in range(steps):
        if k == lead_in:
            compensator.learning_period_s = learning_period_s
        if foresee is not None and ahead:
            foresee(lambda seconds, k=k: wanted[min(k + ahead + round(seconds / PERIOD_S), wanted.size - 1)])
        currents[k] = compensator.command(wanted[k], measured if feedback else None, PERIOD_S if k else 0.0,
                                          ahead_m=wanted[k + ahead] if ahead else None)
        measured = positions[k] = plant.step(currents[k])
    return positions, currents, wanted[:steps + 1]


def scored(identified: Identified, positions: np.ndarray, currents: np.ndarray,
           wanted: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A `drive`'s scored part, after the lead-in: (the error of each position against the setpoint due when it is
    measured [% of the stroke], the current's change into each command from the one before [% of the limit])."""
    low, high = identified.stroke_m
    lead_in = int(LEAD_IN_S / PERIOD_S)
    error = 100.0 * (positions - wanted[1:positions.size + 1])[lead_in:] / (high - low)
    return error, 100.0 * np.abs(np.diff(currents[lead_in - 1:])) / MAX_CURRENT_A


def track(identified: Identified, shape: str, form: Callable[[np.ndarray], np.ndarray], mode: Mode) -> Tracked:
    """`drive` through one shape for its duration_s, scored (see the module's docstring)."""
    learning_period = repeat_period_s(shape) if mode.learning else 0.0
    positions, currents, wanted = drive(identified, form, mode, duration_s(shape), learning_period)
    error, change = scored(identified, positions, currents, wanted)
    result = Tracked(float(np.sqrt(np.mean(error**2))), float(np.max(np.abs(error))), float(np.percentile(change, 99)),
                     model_rms_pct=model_miss_pct(identified, positions, currents))
    if not shape.startswith("held levels"):
        return result
    per_hold, settled_n = int(HOLD_S / PERIOD_S), int(SETTLED_S / PERIOD_S)
    ends = [(hold + 1) * per_hold - 1 for hold in range(HOLDS)]  # error[j] is the position against setpoint j + 1
    settled = [abs(float(np.mean(error[end - settled_n:end]))) for end in ends]
    return replace(result, settled_mean_pct=float(np.mean(settled)), settled_max_pct=float(np.max(settled)),
                   holds_within=sum(value <= HELD_TARGET_PCT for value in settled))


def model_miss(identified: Identified, positions: np.ndarray, currents: np.ndarray) -> np.ndarray:
    """The identified model's error [% of the stroke] on each scored position [m] of a `drive` (all after the
    lead-in but, where the plant samples before its current, the last), the model run from its carried state on
    the currents [A] the plant was given (the compensator's first, then `currents`), each sample read as the
    plant's own records are (SAMPLE_AFTER_CURRENT): what the model gets wrong of the stage on that drive, whatever
    the law."""
    model = identified.model
    applied = applied_currents(identified, currents)
    times = identified.record_end_s + PERIOD_S * np.arange(1, applied.size + 1)
    predicted = model.predict(times, applied, model.state)
    offset = 1 if identified.plant.SAMPLE_AFTER_CURRENT else 2  # positions[k] against predicted[k + offset]
    scored = slice(int(LEAD_IN_S / PERIOD_S), applied.size - offset)
    low, high = identified.stroke_m
    return 100.0 * (positions[scored] - predicted[scored.start + offset:]) / (high - low)


def model_miss_pct(identified: Identified, positions: np.ndarray, currents: np.ndarray) -> float:
    """The identified model's RMS error [% of the stroke] on the scored positions of a `drive` (model_miss)."""
    return float(np.sqrt(np.mean(model_miss(identified, positions, currents) ** 2)))


def held_at(plant: SimulatorPlant | PhysicalPlant, current_a: float, position_m: float,
            reached: Callable[[float], bool]) -> tuple[float, float, float]:
    """current_a [A] held on the plant, from position_m [m], until reached(position) or HOLD_S: (the seconds it took,
    NaN when not reached; the seconds held; the last position [m])."""
    steps, limit = 0, int(HOLD_S / PERIOD_S)
    while not reached(position_m) and steps < limit:
        position_m = plant.step(current_a)
        steps += 1
    return (PERIOD_S * steps if reached(position_m) else float("nan")), PERIOD_S * steps, position_m


def loop_held(plant: SimulatorPlant | PhysicalPlant, compensator: Compensator, level_m: float, position_m: float) -> float:
    """level_m [m] held for HOLD_S by the compensator's PI loop from position_m [m]; the last position [m]."""
    for _ in range(int(HOLD_S / PERIOD_S)):
        position_m = plant.step(compensator.command(level_m, position_m, PERIOD_S))
    return position_m


def fastest_traverse_s(identified: Identified) -> tuple[float, float]:
    """How long [s] the plant takes at the full current to cross the setpoints' band (STROKE_FRACTION of the
    stroke, centred) upwards and then downwards, each from HOLD_S held at the band's far end by the PI loop: no
    law moves it faster, so a sine whose half period is shorter cannot be tracked (NaN: not crossed in HOLD_S)."""
    plant = copy.deepcopy(identified.plant)
    compensator = Compensator(identified.model, MAX_CURRENT_A, **imc_gains(identified.model, PERIOD_S))
    low, high = identified.stroke_m
    centre, half = 0.5 * (low + high), 0.5 * STROKE_FRACTION * (high - low)
    measured = plant.step(compensator.drive.initial_current())
    times = []
    for start, end, current in ((centre - half, centre + half, MAX_CURRENT_A), (centre + half, centre - half, -MAX_CURRENT_A)):
        measured = loop_held(plant, compensator, start, measured)
        took, held, measured = held_at(plant, current, measured, lambda y, s=start, e=end: (e - y) * np.sign(e - s) <= 0.0)
        times.append(took)
        compensator.follow_applied(current, held)
    return times[0], times[1]


def hand_over(identified: Identified) -> dict[str, float]:
    """What a hand-over from one wire to the other costs on the plant itself (no model): the stage at rest at 0 A
    after its identification record (its neutral, % of the stroke from the band's centre); per direction, how
    long the stage held 15 % of the stroke beyond the neutral by the PI loop takes at 0 A to come within 2 % of
    the neutral (drop [s], NaN: not in HOLD_S), and how long full current on the wire taking over takes to move it
    1 % of the stroke from rest (dead [s]). While that wire heats, the other cools: the stage stands near its
    neutral for dead - drop seconds (stall) whatever the law, since the relay heats one wire at a time."""
    low, high = identified.stroke_m
    span, centre = high - low, 0.5 * (low + high)
    rest = copy.deepcopy(identified.plant)
    for _ in range(int(HOLD_S / PERIOD_S)):
        neutral = rest.step(0.0)
    found = {"neutral_pct": 100.0 * (neutral - centre) / span}
    for direction, current in (("down", -MAX_CURRENT_A), ("up", MAX_CURRENT_A)):
        dead, _, _ = held_at(copy.deepcopy(rest), current, neutral, lambda y: abs(y - neutral) >= 0.01 * span)
        plant = copy.deepcopy(rest)
        compensator = Compensator(identified.model, MAX_CURRENT_A, **imc_gains(identified.model, PERIOD_S))
        level = neutral - np.sign(current) * 0.15 * span
        held = loop_held(plant, compensator, level, plant.step(compensator.drive.initial_current()))
        drop, _, _ = held_at(plant, 0.0, held, lambda y: abs(y - neutral) <= 0.02 * span)
        found[f"dead_{direction}_s"], found[f"drop_{direction}_s"] = dead, drop
        found[f"stall_{direction}_s"] = max(0.0, dead - drop) if np.isfinite(dead) and np.isfinite(drop) else 0.0
    return found


def stall_floor_pct(period_s: float, found: dict[str, float]) -> float:
    """The RMS error [% of the stroke] a sine of period_s over STROKE_FRACTION of the stroke suffers from the two
    stalls of hand_over alone, each centred on the setpoint's crossing of the neutral (its best placing): the
    setpoint moves at v there, so a stall of T costs v^2 T^3 / 12 of squared error per period."""
    half = 50.0 * STROKE_FRACTION
    if abs(found["neutral_pct"]) >= half:
        return 0.0
    speed = 2.0 * np.pi / period_s * np.sqrt(half**2 - found["neutral_pct"] ** 2)
    stalls = found["stall_down_s"] ** 3 + found["stall_up_s"] ** 3
    return float(np.sqrt(speed**2 * stalls / (12.0 * period_s)))


WHERE_PERIODS_S = (20.0, 50.0, 100.0)  # --where: the sines whose error is placed
SINCE_SWITCH_BINS_S = (0.0, 2.0, 5.0, 10.0, math.inf)  # --where: the bins of the time since the relay's last switch
HEADER = ("| plant | model (held-out RMS %) | setpoint | RMS / max %: " + "; ".join(m.name for m in MODES)
          + " | settled mean / max %: same order | p99 current change %: same order |\n|---|---|---|---|---|---|")


def law(mode: Mode, shape: str) -> tuple[type[Compensator], bool, bool, bool]:
    """What the compensator runs in a mode on a shape: (its class, the loop, the preview, learning), learning only
    where the shape repeats."""
    return mode.core, mode.feedback, mode.preview, mode.learning and repeat_period_s(shape) > 0.0


def rows(name: str, identified: Identified, seed: int, found: dict[str, list[Tracked]]) -> list[str]:
    """The table's rows of one plant: each shape, in every mode (each shape's runs, in MODES' order, also added to
    found)."""
    lines = []
    for shape, form in shapes(seed).items():
        by_law: dict[tuple[type[Compensator], bool, bool, bool], Tracked] = {}  # a shape with no period: learning runs as without it
        for mode in MODES:
            if law(mode, shape) not in by_law:
                by_law[law(mode, shape)] = track(identified, shape, form, mode)
        runs = found[shape] = [by_law[law(mode, shape)] for mode in MODES]
        errors = "; ".join(f"{run.rms_pct:.2f} / {run.max_pct:.1f}" for run in runs)
        settled = "" if runs[0].settled_mean_pct is None else "; ".join(
            f"{run.settled_mean_pct:.2f} / {run.settled_max_pct:.2f}" for run in runs)
        changes = "; ".join(f"{run.change_p99_pct:.1f}" for run in runs)
        first = f"{name} | {identified.name} ({identified.validation_rms_pct:.2f})" if not lines else " | "
        lines.append(f"| {first} | {shape} | {errors} | {settled} | {changes} |")
    return lines


def target_pct(mode: Mode) -> float:
    """The RMS error [% of the stroke] issue 49 asks of a mode on a moving setpoint: 1 % with the loop, 3 % without."""
    return LOOP_TARGET_PCT if mode.feedback else FEEDFORWARD_TARGET_PCT


def summary(found: dict[str, dict[str, list[Tracked]]]) -> list[str]:
    """Over the plants (found: plant -> shape -> runs in MODES' order), per shape and mode: the RMS range [%] and
    how many plants are within target_pct; for held levels the settled means' range, how many plants settled every
    hold within HELD_TARGET_PCT and how many holds of all did; last, the rows whose current's p99 change exceeds CHANGE_TARGET_PCT."""
    plants = list(found)
    lines = ["| setpoint | " + " | ".join(mode.name for mode in MODES) + " |", "|---|" + "---|" * len(MODES)]
    for shape in found[plants[0]]:
        cells = []
        for index, mode in enumerate(MODES):
            runs = [found[plant][shape][index] for plant in plants]
            if runs[0].settled_mean_pct is None:
                rms = [run.rms_pct for run in runs]
                within = sum(value <= target_pct(mode) for value in rms)
                cells.append(f"{min(rms):.2f}-{max(rms):.2f}; {within} of {len(runs)} within {target_pct(mode):g} %")
            else:
                means = [run.settled_mean_pct for run in runs]
                within = sum(run.settled_max_pct <= HELD_TARGET_PCT for run in runs)
                holds = sum(run.holds_within for run in runs)
                cells.append(f"settled {min(means):.2f}-{max(means):.2f}; {within} of {len(runs)} with every hold within "
                             f"{HELD_TARGET_PCT:g} % ({holds} of {HOLDS * len(runs)} holds)")
        lines.append(f"| {shape} | " + " | ".join(cells) + " |")
    over: dict[str, int] = {}
    for by_shape in found.values():
        for shape, runs in by_shape.items():
            over[shape] = over.get(shape, 0) + sum(run.change_p99_pct > CHANGE_TARGET_PCT for run in runs)
    count = sum(len(runs) for by_shape in found.values() for runs in by_shape.values())
    listed = "; ".join(f"{shape} {number}" for shape, number in over.items() if number)
    lines.append(f"\nRuns (plant, setpoint, mode) whose current's p99 change exceeds {CHANGE_TARGET_PCT:g} % of the limit: "
                 f"{sum(over.values())} of {count}" + (f" ({listed})" if listed else "") + ".")
    return lines


def model_misses(found: dict[str, dict[str, list[Tracked]]], mode: Mode = LOOP_PREVIEW) -> list[str]:
    """Per plant, for each moving shape in one mode: its RMS error and the model's own RMS error on the same drive
    (Tracked.model_rms_pct) [% of the stroke]."""
    index = MODES.index(mode)
    moving = [shape for shape in next(iter(found.values())) if not shape.startswith("held levels")]
    lines = ["| plant | " + " | ".join(moving) + " |", "|---|" + "---|" * len(moving)]
    for plant, by_shape in found.items():
        lines.append(f"| {plant} | " + " | ".join(f"{by_shape[shape][index].rms_pct:.2f} / "
                                                    f"{by_shape[shape][index].model_rms_pct:.2f}" for shape in moving) + " |")
    return lines


def reversal_scan(names: list[str], seed: int, speeds: list[float]) -> list[str]:
    """Held levels in the PI loop, without and with the preview, at each REVERSAL_SPEED: per plant and draw, the
    settled mean / max [%] and the p99 current change [%], then the worst hold and the draws whose every hold
    settled within 0.2 % (of all, per speed), and the mean of the draws' settled means."""
    loops = [mode for mode in MODES if mode.feedback and not mode.learning]
    lines = ["| plant | setpoint | " + " | ".join(f"reversal speed {speed:g}: settled mean / max %, p99 change %: "
                                                  + "; ".join(mode.name for mode in loops) for speed in speeds) + " |",
             "|---|---|" + "---|" * len(speeds)]
    print(lines[0] + "\n" + lines[1], flush=True)
    every: dict[float, list[Tracked]] = {speed: [] for speed in speeds}
    held = {shape: form for shape, form in shapes(seed).items() if shape.startswith("held levels")}
    default_speed = compensator_module.REVERSAL_SPEED
    try:
        for name in names:
            identified = identify(name, seed)
            for shape, form in held.items():
                cells = []
                for speed in speeds:
                    compensator_module.REVERSAL_SPEED = speed
                    runs = [track(identified, shape, form, mode) for mode in loops]
                    every[speed] += runs
                    cells.append("; ".join(f"{run.settled_mean_pct:.2f} / {run.settled_max_pct:.2f}, "
                                           f"{run.change_p99_pct:.1f}" for run in runs))
                lines.append(f"| {name} | {shape} | " + " | ".join(cells) + " |")
                print(lines[-1], flush=True)
    finally:
        compensator_module.REVERSAL_SPEED = default_speed
    lines.append("| every plant | worst hold %; draws with every hold within 0.2 %; mean settled % | " + " | ".join(
        f"{max(run.settled_max_pct for run in runs):.2f}; {sum(run.settled_max_pct <= 0.2 for run in runs)} of "
        f"{len(runs)}; {np.mean([run.settled_mean_pct for run in runs]):.3f}" for runs in every.values()) + " |")
    print(lines[-1], flush=True)
    return lines


def since_switch_s(currents: np.ndarray) -> np.ndarray:
    """For each position of a `drive` (measured at the end of command k), the time [s] since the relay last switched
    wire (the current's sign changed, 0 A switching nothing): a switch at command j gives (k - j + 1) PERIOD_S;
    inf before the first switch."""
    since, side, switched = np.empty(currents.size), 0.0, -math.inf
    for k, current in enumerate(currents):
        if current != 0.0 and np.sign(current) != side:
            switched = k if side != 0.0 else switched
            side = np.sign(current)
        since[k] = (k - switched + 1) * PERIOD_S
    return since


def where_cells(error: np.ndarray, miss: np.ndarray, since: np.ndarray) -> str:
    """Per bin of SINCE_SWITCH_BINS_S (the last one with the positions before the first switch): the share of the
    scored time and of the squared error [%], the RMS error and the model's RMS miss there [% of the stroke] (miss
    one shorter than error where the plant samples first)."""
    cells, total = [], float(np.sum(error**2))
    for start, end in zip(SINCE_SWITCH_BINS_S[:-1], SINCE_SWITCH_BINS_S[1:], strict=True):
        inside = (since >= start) & ((since < end) | (end == math.inf))  # the last bin: before any switch too
        if not inside.any():
            cells.append("-")
            continue
        missed = miss[inside[:miss.size]]
        cells.append(f"{100.0 * inside.mean():.0f} / {100.0 * np.sum(error[inside]**2) / total:.0f} / "
                     f"{np.sqrt(np.mean(error[inside]**2)):.2f} / {np.sqrt(np.mean(missed**2)):.2f}")
    return "; ".join(cells)


def placed(identified: Identified, shape: str, form: Callable[[np.ndarray], np.ndarray],
           mode: Mode) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """`drive` through one shape for its duration_s, scored, and each scored position's time since the relay's last
    switch: (error [%], the current's change [%], since_switch_s [s], where_cells)."""
    positions, currents, wanted = drive(identified, form, mode, duration_s(shape))
    error, change = scored(identified, positions, currents, wanted)
    since = since_switch_s(currents)[int(LEAD_IN_S / PERIOD_S):]
    return error, change, since, where_cells(error, model_miss(identified, positions, currents), since)


def where_errors(names: list[str], seed: int) -> list[str]:
    """Where the default law's error falls on the sines of WHERE_PERIODS_S: per plant and sine, the RMS error, the
    relay's switches per period, the error and the model's miss by the time since the relay's last switch
    (where_cells), and the current's p99 change with and without the commands that switch the relay."""
    bins = "; ".join(f"{start:g}-{end:g}" if math.isfinite(end) else f"from {start:g}"
                     for start, end in zip(SINCE_SWITCH_BINS_S[:-1], SINCE_SWITCH_BINS_S[1:], strict=True))
    lines = ["| plant | setpoint | RMS % | relay switches per period | by the time since the relay's last switch "
             f"[s] ({bins}): share of the time % / of the squared error % / RMS error % / the model's RMS miss % | "
             "p99 current change %: every command; without those that switch the relay |", "|---|---|---|---|---|---|"]
    print(lines[0] + "\n" + lines[1], flush=True)
    forms = shapes(seed)
    for name in names:
        identified = identify(name, seed)
        for period in WHERE_PERIODS_S:
            shape = f"sine {period:g} s"
            error, change, since, cells = placed(identified, shape, forms[shape], LOOP_PREVIEW)
            switches = np.isclose(since, PERIOD_S)
            per_period = switches.sum() * period / (PERIOD_S * since.size)
            lines.append(f"| {name} | {shape} | {np.sqrt(np.mean(error**2)):.2f} | {per_period:.1f} | {cells} | "
                         f"{np.percentile(change, 99):.1f}; {np.percentile(change[~switches], 99):.1f} |")
            print(lines[-1], flush=True)
    return lines


def run_note(arguments: str, started: float, script: str = "bench_positioning.py") -> str:
    """The line under a table: the command with its arguments, the seconds since `started` and the date."""
    return (f"`.venv/bin/python bench/{script} {arguments}`: {time.perf_counter() - started:.0f} s on "
            f"{time.strftime('%Y-%m-%d')} ({machine()}); deterministic for a seed on one machine.")


def write(out: Path, title: str, body: str) -> None:
    """The table written whole (atomic_write_text: a reader sees the old file or the new one)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, f"# {title}\n\n{body}")


def write_table(out: Path, title: str, explained: str, header: str, lines: list[str], note: str) -> None:
    """`write` a results file of one table: what each cell holds, the table's header and rows, then the run's note."""
    write(out, title, explained + "\n\n" + header + "\n" + "\n".join(lines) + "\n\n" + note + "\n")


def plant_names(parser: argparse.ArgumentParser, plants: str) -> list[str]:
    """The plants of a comma-separated --plants, each one of PLANTS; else the parser's one-line error (exit 2)."""
    names = plants.split(",")
    unknown = [name for name in names if name not in PLANTS]
    if unknown:
        parser.error(f"unknown plant {unknown[0]!r} (known: {', '.join(PLANTS)})")
    return names


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--plants", default=",".join(PLANTS), help=f"comma-separated, of {', '.join(PLANTS)}")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--record", choices=RECORDS, default="paper",
                        help="the identification record: the paper's decaying sine; the probe and the designed "
                             "excitation (default out bench/results/positioning_designed.md); or the paper's, then "
                             "the loop tracking a sine (positioning_tracking.md)")
    parser.add_argument("--validate-levels", action="store_true",
                        help="validate on held random levels too, the choice on the worst record (default out "
                             "bench/results/positioning_levels.md or positioning_designed_levels.md)")
    parser.add_argument("--families", type=family_list, default=FAMILIES,
                        help="the model families compared (default: gpi_tool diagnose's)")
    parser.add_argument("--reversal-speeds", help="comma-separated values of REVERSAL_SPEED: the held levels only")
    parser.add_argument("--where", action="store_true",
                        help="where the default law's error falls on the 20, 50 and 100 s sines, by the time since "
                             "the relay's last switch (default out bench/results/positioning_where.md)")
    parser.add_argument("--out", help="the table's file (default bench/results/positioning.md, with --reversal-speeds "
                                      "bench/results/reversal_speed.md)")
    args = parser.parse_args()
    names = plant_names(parser, args.plants)
    started = time.perf_counter()
    if args.where:
        lines = where_errors(names, args.seed)
        note = run_note(f"--where --plants {args.plants} --seed {args.seed}", started)
        write(Path(args.out or REPO / "bench" / "results" / "positioning_where.md"),
              "Where the default law's error falls on the sines, by the time since the relay's last switch",
              "\n".join(lines) + "\n\n" + note + "\n")
        print(note)
        return
    if args.reversal_speeds:
        lines = reversal_scan(names, args.seed, [float(text) for text in args.reversal_speeds.split(",")])
        note = run_note(f"--reversal-speeds {args.reversal_speeds} --plants {args.plants} --seed {args.seed}", started)
        write(Path(args.out or REPO / "bench" / "results" / "reversal_speed.md"),
              "Held levels at each speed of a held setpoint's reversal", "\n".join(lines) + "\n\n" + note + "\n")
        print(note)
        return
    table = [HEADER]
    traverse = ["| plant | fastest crossing of the band up / down [s] | neutral [%] | drop, dead, stall down / up [s] "
                "| stall floor, sine 50 / 100 / 250 s [% RMS] |", "|---|---|---|---|---|"]
    print(HEADER, flush=True)
    tracked: dict[str, dict[str, list[Tracked]]] = {}
    for name in names:
        identified = identify(name, args.seed, args.record, args.validate_levels, args.families)
        for line in rows(name, identified, args.seed, tracked.setdefault(name, {})):
            table.append(line)
            print(line, flush=True)
        up, down = fastest_traverse_s(identified)
        found = hand_over(identified)
        stalls = " / ".join(f"{found[f'drop_{d}_s']:.1f}, {found[f'dead_{d}_s']:.1f}, {found[f'stall_{d}_s']:.1f}"
                            for d in ("down", "up"))
        floors = " / ".join(f"{stall_floor_pct(period, found):.2f}" for period in (50.0, 100.0, 250.0))
        traverse.append(f"| {name} | {up:.1f} / {down:.1f} | {found['neutral_pct']:.1f} | {stalls} | {floors} |")
    print("\n".join(traverse))
    against = summary(tracked)
    print("\n".join(against))
    misses = model_misses(tracked)
    print("\n".join(misses))
    levels = " --validate-levels" if args.validate_levels else ""
    named = f" --families {','.join(args.families)}" if args.families != FAMILIES else ""
    note = run_note(f"--plants {args.plants} --seed {args.seed} --record {args.record}{levels}{named}", started)
    stem, identified_how = RECORDS[args.record]
    compact = "two_wire_compact" in args.families
    default_out = stem + ("_levels" if levels else "") + ("_compact" if compact else "") + ".md"
    write(Path(args.out or REPO / "bench" / "results" / default_out),
          "Positioning stages the control law was not tuned on" + identified_how
          + (", validated on held random levels too" if levels else "")
          + (f", the families {', '.join(args.families)} compared" if args.families != FAMILIES else ""),
          "\n".join(table) + "\n\nOver the plants: the RMS range [% of the stroke] and the plants within issue 49's "
          "targets (RMS within 1 % with the PI loop, 3 % in feedforward; held levels: every hold settled within "
          "0.2 %):\n\n" + "\n".join(against) + "\n\n" + "The full current's crossing of the setpoints' band (no law crosses it faster), "
          "and what a hand-over costs (hand_over, stall_floor_pct; drop or dead NaN: not within 60 s, no stall "
          "counted):\n\n" + "\n".join(traverse) + "\n\nThe PI loop with the preview, RMS error / the model's own RMS "
          "error on the currents the loop gave the plant (model_miss_pct) [% of the stroke]: what no law that trusts "
          "the model can lead, and the loop must close:\n\n" + "\n".join(misses) + "\n\n" + note + "\n")
    print(note)


if __name__ == "__main__":
    main()
