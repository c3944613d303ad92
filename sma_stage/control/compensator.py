"""The compensator's control law (no ROS): the inverse GPI model, an optional thermal-lag lead, a PI loop.

Per call, with e = setpoint - measured position [m] when a measurement is given (feedback):

    integral += ki e dt, except while the command saturates in the direction of e (anti-windup)
    target    = setpoint + kp e + integral                      (target = setpoint without feedback)
    v*        = GPI inverse(target)                             within the inverse's input range [A]
    current   = the lead: v* + tau dv*/dt in the limit of short steps, clipped to the input range
                (tau = 0: current = v*)

The lead inverts the thermal lag tau v' = u - v that `identify.effects` fits (the GPI sees v, not the
current u). It keeps the lag's state v, advanced exactly over each step with the command actually sent
(held constant, as the stage holds it), and sends the current that brings v to v* at the end of a step
as long as the last positive dt_s: u = (v* - a v) / (1 - a), a = exp(-dt / tau). Unclipped and with v
on v*'s previous value this is v* + a / (1 - a) (v* - v*_previous) ~ v* + tau dv*/dt; when the clip
stops the current short, v lags v* and the lead keeps pushing on the following steps. The state starts
at 0 A (an idle stage, as the identification assumes). With heating_reference_a > 0 the lag filters the
Joule heating u |u| / heating_reference_a instead of u (the wires heat as i^2 R) and the lead works in
those units.
"""

from __future__ import annotations

import math

from sma_stage.errors import InputError, finite_number
from sma_stage.model import GPIInverseStream


def _non_negative(name: str, value: float) -> float:
    number = finite_number(name, value)
    if number < 0.0:
        raise InputError(f"{name} must be at least 0, got {value!r}")
    return number


GAIN_PARAMETERS = ("lag_tau_s", "heating_reference_a", "kp", "ki")


def checked_gains(lag_tau_s: float, heating_reference_a: float, kp: float, ki: float) -> dict[str, float]:
    """The lead's and the loop's settings (lag [s], heating reference [A], kp [m/m], ki [1/s]) as floats;
    InputError unless each is finite and >= 0."""
    values = {"lag_tau_s": lag_tau_s, "heating_reference_a": heating_reference_a, "kp": kp, "ki": ki}
    return {name: _non_negative(name, value) for name, value in values.items()}


class _NonNegative:
    """A float setting of the Compensator, kept as `_<name>`; setting it to anything but a finite number
    >= 0 raises InputError naming it."""

    def __set_name__(self, owner: type, name: str) -> None:
        self.name, self.slot = name, f"_{name}"

    def __get__(self, instance: object, owner: type | None = None) -> float:
        return self if instance is None else getattr(instance, self.slot)

    def __set__(self, instance: object, value: float) -> None:
        setattr(instance, self.slot, _non_negative(self.name, value))


class Compensator:
    """Setpoint [m] (and measured position [m]) in, current [A] out; see the module's docstring.

    inverse: the streaming GPI inverse (its input_range is the current limit [A]); lag_tau_s: the thermal
    lag's time constant [s] (0: no lead); kp [m/m] and ki [1/s]: the PI gains (used only when a
    measurement is given); heating_reference_a [A]: 0, the lag filters the current u; above 0, it
    filters the Joule heating u |u| / heating_reference_a [A] (signed by the relay; the thermal_lag
    effect's joule_reference_a), the model's input v is in those units, and the lead sends the current
    whose heating it wants.
    """

    lag_tau_s = _NonNegative()  # time constant of the thermal lag the lead inverts [s]; 0: no lead
    heating_reference_a = _NonNegative()  # [A] of the lagged heating u |u| / reference; 0: the current is lagged
    kp = _NonNegative()  # proportional gain [m of target per m of error]
    ki = _NonNegative()  # integral gain [1/s]

    def __init__(self, inverse: GPIInverseStream, lag_tau_s: float = 0.0, kp: float = 0.0,
                 ki: float = 0.0, heating_reference_a: float = 0.0) -> None:
        self.heating_reference_a = heating_reference_a
        self.lag_tau_s = lag_tau_s
        self.kp = kp
        self.ki = ki
        self.command_a = 0.0
        self.set_inverse(inverse)

    @property
    def inverse(self) -> GPIInverseStream:
        """The streaming GPI inverse in use."""
        return self._inverse

    def set_inverse(self, inverse: GPIInverseStream) -> None:
        """Use another inverse (a new model); the integral and the lead's history start again."""
        if not isinstance(inverse, GPIInverseStream):
            raise InputError(f"inverse must be a GPIInverseStream, got {type(inverse).__name__}")
        self._inverse = inverse
        self.reset()

    def reset(self) -> None:
        """Integral to 0, the lag's state to an idle stage (the inverse keeps its states)."""
        self.integral_m = 0.0
        self.target_m = 0.0
        self.saturated = 0
        self.lag_state_a = 0.0
        self._hold_s = 0.0

    def command(self, setpoint_m: float, measured_m: float | None = None, dt_s: float = 0.0) -> float:
        """The current [A] for setpoint_m [m]; with measured_m [m] the PI loop acts, integrating the error
        over dt_s [s], the time since the previous call (0 for a call at the same instant)."""
        setpoint = finite_number("setpoint_m", setpoint_m)
        dt = _non_negative("dt_s", dt_s)
        self.target_m = setpoint
        if measured_m is not None:
            self.target_m = self._pi_target(setpoint, finite_number("measured_m", measured_m), dt)
        lag_input = self._inverse.step(self.target_m)
        self.command_a = self._lead(lag_input, dt)
        return self.command_a

    def _pi_target(self, setpoint: float, measured: float, dt: float) -> float:
        error = setpoint - measured
        if self.saturated * error <= 0.0:
            self.integral_m += self._ki * error * dt
        return setpoint + self._kp * error + self.integral_m

    def _lead(self, lag_input: float, dt: float) -> float:
        if dt > 0.0:
            self._hold_s = dt
            self.lag_state_a = self._lagged(self.lag_state_a, self._heating(self.command_a), dt)
        wanted = lag_input
        if self._lag_tau_s > 0.0 and self._hold_s > 0.0:
            kept = math.exp(-self._hold_s / self._lag_tau_s)
            wanted = (lag_input - kept * self.lag_state_a) / (1.0 - kept)
        low, high = (self._heating(limit) for limit in self._inverse.input_range)
        clipped = min(high, max(low, wanted))
        self.saturated = self._inverse.last_clipped or (wanted > clipped) - (wanted < clipped)
        return self._current_for(clipped)

    def _heating(self, current_a: float) -> float:
        """What the lag filters [A]: the current, or u |u| / heating_reference_a."""
        reference = self._heating_reference_a
        return current_a * abs(current_a) / reference if reference > 0.0 else current_a

    def _current_for(self, heating: float) -> float:
        """The current [A] whose heating (see _heating) is `heating` [A]."""
        reference = self._heating_reference_a
        return math.copysign(math.sqrt(abs(heating) * reference), heating) if reference > 0.0 else heating

    def _lagged(self, state_a: float, drive_a: float, dt: float) -> float:
        """The lag's state [A] after its input drive_a [A] (see _heating) held for dt [s] from state_a."""
        if self._lag_tau_s == 0.0:
            return drive_a
        return drive_a + (state_a - drive_a) * math.exp(-dt / self._lag_tau_s)
