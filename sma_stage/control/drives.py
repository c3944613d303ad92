"""What the compensator runs backwards, per model family (no ROS): a drive takes the loop's target [m] and
gives the current [A], steps the model with the current the stage was given, and bounds the targets.

- GPIDrive (an IdentifiedModel): the GPI's inverse gives what its input should be, the thermal effect's lead
  (sma_stage.control.thermal) the current that brings its state there, the drift's offset is taken off the
  target (see sma_stage.control.compensator).
- StreamDrive (a TwoWireModel, a BoucWenModel: a model whose input is a held current, with a `stream`): the
  model's own exact inverse through its heating lag: the current that, held over a horizon, brings the output
  to the target (sma_stage.model.two_wire, sma_stage.model.bouc_wen). The horizon is the lead limit's: a
  first-order lag driven by s + g (v* - s) reaches v* after -tau ln(1 - 1/g), so a lead of gain at most g is
  the inverse over at least that horizon (and over one hold when that needs less).
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np

from sma_stage.control.thermal import ThermalState
from sma_stage.errors import InputError
from sma_stage.model import GPIForwardStream, GPIInverseStream, IdentifiedModel
from sma_stage.model.bouc_wen import BoucWenModel
from sma_stage.model.effects import Effect, EffectState, joule_heating
from sma_stage.model.identified import ModelState
from sma_stage.model.inverse import TARGET_MARGIN_SPANS
from sma_stage.model.kinds import AnyModel, StreamModel

SETTLED_TAUS = 30.0  # a hold this many time constants long is a steady state (e^-30: 1e-13)
DEAD_BAND_SLOPE = 0.1  # a current where the model's output moves by less than this share of its mean slope is dead
DEAD_BAND_BINS = 40  # the current range is looked at in this many bins
DEAD_BAND_PERIODS_TAU = 40.0  # the major loop the dead band is read from: a sine this many time constants long
DEAD_BAND_MIN_PERIOD_S = 400.0  # (at least this long), its third period


class Drive(Protocol):
    """The model-specific half of the compensator."""

    model: AnyModel
    target_bounds: tuple[float, float]  # targets are clipped to these [m]
    method: str  # the inverse's method, for the log
    out_of_reach: int  # +1 (-1) when the last target was above (below) what the current limit reaches, else 0

    @property
    def tau_s(self) -> float:
        """The slowest thermal time constant the lead undoes [s] (0: none)."""

    @property
    def evolves(self) -> bool:
        """Whether the command changes with time at a constant target (a thermal state or a drift)."""

    def initial_current(self) -> float:
        """The current [A] the model's carried state was left with (0 at rest)."""

    def advance(self, current_a: float, dt_s: float) -> None:
        """Step the model's states with the command sent, held for dt_s [s]."""

    def current_for(self, target_m: float, hold_s: float, lead_limit: float) -> tuple[float, int]:
        """(the current [A] to hold for hold_s [s] towards target_m, +1/-1 when it saturates towards a target
        out of reach, else 0); the lead's gain at most lead_limit."""

    def follow_applied(self, current_a: float, dt_s: float) -> None:
        """Step the states with a current the stage applied for dt_s [s] that the compensator did not send."""

    @property
    def predicted_m(self) -> float:
        """The position [m] the model gives at its states now."""

    def describe(self) -> str:
        """One line naming the model and its inverse."""


def drive_for(model: object, max_current_a: float, method: str) -> Drive:
    """The drive of a model of any family (InputError when it cannot be inverted within +-max_current_a [A])."""
    if isinstance(model, IdentifiedModel):
        return GPIDrive(model, max_current_a, method)
    if isinstance(model, StreamModel):
        return StreamDrive(model, max_current_a, method)
    raise InputError(f"model must be a GPI, a two-wire or a Bouc-Wen model, got {type(model).__name__}")


def model_tau_s(model: AnyModel) -> float:
    """The slowest thermal time constant of a model [s] (0: none): what the PI loop's tuning takes as the lag."""
    if isinstance(model, StreamModel):
        return model.tau_s
    return ThermalState(thermal_effect(model)).tau_s


def thermal_effect(model: IdentifiedModel) -> Effect | None:
    """The model's thermal effect (thermal_lag or wire_thermal), which the lead undoes; None without one."""
    return model.effect("thermal_lag") or model.effect("wire_thermal")


class GPIDrive:
    """The GPI inverse, the thermal effect's lead and the drift's offset (see sma_stage.control.compensator)."""

    def __init__(self, model: IdentifiedModel, max_current_a: float, method: str) -> None:
        thermal = thermal_effect(model)
        reference = thermal.parameters.get("joule_reference_a", 0.0) if thermal is not None else 0.0
        reach = (float(joule_heating(-max_current_a, reference)), float(joule_heating(max_current_a, reference)))
        state = model.state
        self.model = model
        self.inverse = GPIInverseStream(model.parameters, model.operators, method,
                                        initial=None if state is None else np.array(state.operators),
                                        input_range=reach)
        self.target_bounds = self.inverse.target_bounds
        self.method = self.inverse.method
        self._thermal_effect = thermal
        self._drift = model.effect("drift")
        self.thermal = ThermalState(thermal, self._carried_state(thermal, state))
        drift_state = self._carried_state(self._drift, state)
        self.drift_elapsed_s = float(drift_state.values[0]) if drift_state is not None and drift_state.values else 0.0
        self._compile()

    def _compile(self) -> None:
        """Run the inverse and the forward step once on throwaway streams, so that their compiled kernels are
        loaded (or built, seconds on a cold cache) here and not in the first command."""
        throwaway = GPIInverseStream(self.model.parameters, self.model.operators, self.method,
                                     input_range=self.inverse.input_range)
        throwaway.step(0.5 * sum(self.target_bounds))
        GPIForwardStream(self.model.parameters, self.model.operators, initial=throwaway.states).step(0.0)

    def _carried_state(self, effect: Effect | None, state: ModelState | None) -> EffectState | None:
        if effect is None or state is None:
            return None
        return state.effects[self.model.effects.index(effect)]

    @property
    def tau_s(self) -> float:
        return self.thermal.tau_s

    @property
    def evolves(self) -> bool:
        return self.tau_s > 0.0 or self._drift is not None

    @property
    def out_of_reach(self) -> int:
        return self.inverse.last_clipped

    def initial_current(self) -> float:
        return self.thermal.current(self.thermal.last_drive)

    def advance(self, current_a: float, dt_s: float) -> None:
        self.drift_elapsed_s += dt_s
        if dt_s > 0.0:
            self.thermal.advance(current_a, dt_s)

    def current_for(self, target_m: float, hold_s: float, lead_limit: float) -> tuple[float, int]:
        lag_input = self.inverse.step(target_m - self._drift_offset())
        wanted = self.thermal.lead(lag_input, hold_s, lead_limit)
        low, high = self.inverse.input_range
        clipped = min(high, max(low, wanted))
        saturated = self.inverse.last_clipped or (wanted > clipped) - (wanted < clipped)
        return self.thermal.current(clipped), saturated

    def follow_applied(self, current_a: float, dt_s: float) -> None:
        self.thermal.advance(current_a, dt_s)
        seen = self.thermal.seen
        forward = GPIForwardStream(self.model.parameters, self.model.operators, initial=self.inverse.states)
        forward.step(seen)
        self.inverse.reset(initial=forward.states, previous_input=seen)
        self.drift_elapsed_s += dt_s

    @property
    def predicted_m(self) -> float:
        """The operators played from the inverse's states to what the thermal state lets the GPI see, plus the
        drift's offset."""
        forward = GPIForwardStream(self.model.parameters, self.model.operators, initial=self.inverse.states)
        return float(forward.step(self.thermal.seen)) + self._drift_offset()

    def _drift_offset(self) -> float:
        if self._drift is None:
            return 0.0
        return float(self._drift.drift_at(self.drift_elapsed_s)[0])

    def describe(self) -> str:
        effects = " + ".join(self.model.effect_names) or "no effect"
        return f"{self.method} inverse of a {self.model.operators}-operator GPI with {effects}"


class StreamDrive:
    """A held-current model's exact inverse through its heating lag, over the lead limit's horizon."""

    method = "exact"

    def __init__(self, model: StreamModel, max_current_a: float, method: str) -> None:
        if method != "exact":
            raise InputError(f"a {model.kind.replace('_', '-')} model has an exact inverse only; inverse_method is "
                             f"{method!r}")
        self.model = model
        self.stream = model.stream(model.state, max_current_a)
        self.reach = _stream_reach(model, max_current_a, self.tau_s)
        low, high = self.reach
        margin = TARGET_MARGIN_SPANS * (high - low)
        self.target_bounds = (low - margin, high + margin)
        self.out_of_reach = 0
        # the inverse's compiled kernel loaded (or built, seconds on a cold cache) here, not in the first command
        model.stream(None, max_current_a).current_for(0.5 * (low + high), lead_horizon_s(self.tau_s, 1.0))

    @property
    def tau_s(self) -> float:
        return model_tau_s(self.model)

    @property
    def evolves(self) -> bool:
        return True

    def initial_current(self) -> float:
        return self.model.state.current_a if self.model.state is not None else 0.0

    def advance(self, current_a: float, dt_s: float) -> None:
        if dt_s > 0.0:
            self.stream.step(current_a, dt_s)

    def current_for(self, target_m: float, hold_s: float, lead_limit: float) -> tuple[float, int]:
        low, high = self.reach
        self.out_of_reach = (target_m > high) - (target_m < low)
        current = self.stream.current_for(target_m, max(hold_s, lead_horizon_s(self.tau_s, lead_limit)))
        return current, self.stream.last_clipped

    def follow_applied(self, current_a: float, dt_s: float) -> None:
        self.advance(current_a, dt_s)

    @property
    def predicted_m(self) -> float:
        return self.stream.output

    def describe(self) -> str:
        if isinstance(self.model, BoucWenModel):
            return f"exact inverse of a Bouc-Wen model (heating lag {self.tau_s:.3g} s)"
        params = self.model.parameters
        return (f"exact inverse of a two-wire model ({params.wire_operators} operators per wire, "
                f"{params.output_operators} at the output)")


def reach_span_m(drive: Drive) -> float:
    """The span [m] of the outputs the drive's model reaches within the current limit (its target bounds are
    that reach and TARGET_MARGIN_SPANS spans beyond it each way)."""
    low, high = drive.target_bounds
    return (high - low) / (1.0 + 2.0 * TARGET_MARGIN_SPANS)


def lead_horizon_s(tau_s: float, lead_limit: float) -> float:
    """The hold [s] over which a first-order lag of tau_s [s] driven with a lead of gain lead_limit reaches its
    target: -tau ln(1 - 1/g); SETTLED_TAUS time constants for a gain of 1 (no lead)."""
    if lead_limit <= 1.0:
        return SETTLED_TAUS * tau_s
    return min(SETTLED_TAUS * tau_s, -tau_s * math.log1p(-1.0 / lead_limit))


def _stream_reach(model: StreamModel, max_current_a: float, tau_s: float) -> tuple[float, float]:
    """The outputs [m] the current limit settles to from rest, each way (low, high)."""
    ends = []
    for current in (-max_current_a, max_current_a):
        stream = model.stream(None, max_current_a)
        ends.append(stream.step(current, SETTLED_TAUS * tau_s))
    low, high = min(ends), max(ends)
    span = high - low
    if not span > 0.0:
        raise InputError("the model's output does not move with the current: it cannot be inverted")
    return low, high


def dead_band_a(model: AnyModel, max_current_a: float) -> tuple[float, float]:
    """The currents (low <= 0 <= high) [A] around zero where neither wire moves the stage in the model: along its
    major loop (a slow sine to +-max_current_a, from rest) the output moves by less than DEAD_BAND_SLOPE of its
    mean slope in every bin of the range between them; (0, 0) when the bins either side of zero move it."""
    period = max(DEAD_BAND_MIN_PERIOD_S, DEAD_BAND_PERIODS_TAU * model_tau_s(model))
    t = np.linspace(0.0, 3.0 * period, 6001)
    u = max_current_a * np.sin(2.0 * np.pi * t / period)
    y = model.predict(t, u)
    last = t >= 2.0 * period
    current, du, dy = u[last][1:], np.diff(u[last]), np.diff(y[last])
    mean_slope = float(np.ptp(y[last])) / (2.0 * max_current_a)
    edges = np.linspace(-max_current_a, max_current_a, DEAD_BAND_BINS + 1)
    bins = np.clip(np.searchsorted(edges, current, side="right") - 1, 0, DEAD_BAND_BINS - 1)
    moving = np.abs(du) > 0.0
    dead = np.array([np.median(np.abs(dy[moving & (bins == b)] / du[moving & (bins == b)]))
                     < DEAD_BAND_SLOPE * mean_slope for b in range(DEAD_BAND_BINS)])
    middle = DEAD_BAND_BINS // 2
    if not (dead[middle - 1] and dead[middle]):
        return 0.0, 0.0
    low, high = middle - 1, middle
    while low > 0 and dead[low - 1]:
        low -= 1
    while high < DEAD_BAND_BINS - 1 and dead[high + 1]:
        high += 1
    return float(edges[low]), float(edges[high + 1])
