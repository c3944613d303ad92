"""The effects an identified model can carry beside the GPI, as forward models (no fitting here): the
input transforms `thermal_lag` and `delay`, the rate-dependent thresholds of `rate`, and the output
offset of `drift`. Identification fits them (sma_stage.identify.effects) and the compensator steps them
(sma_stage.control) with this same code.

Time t is in s, currents in A, outputs in the model's output unit. A record starts either from an idle
stage (the current switched on one sample period before the first sample, held at u[0] over that
period, zero before; every state at rest) or from a carried state (`EffectState`, what a record that
went before left).

The thermal lag is the wire temperature's first-order response tau v' = d - v to the drive d (the
current u, or the Joule heating u |u| / u_ref), stepped exactly for a drive linear between samples
(`lag_step`): a sampled record interpolates its drive so; a compensator's command is held, the special
case of equal ends, which `lag_drive_for` inverts.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numba
import numpy as np

from sma_stage.errors import InputError

EFFECT_KINDS = ("thermal_lag", "delay", "rate", "drift", "wire_thermal")
START_KINDS = ("rest", "held", "free")


@numba.njit(cache=True, nogil=True)
def lag_step(state: float, start_drive: float, end_drive: float, step_s: float, tau_s: float) -> float:
    """The lag's state [A] after step_s [s] from `state`, its drive going linearly from start_drive to
    end_drive [A] (equal: a held drive); tau_s 0: the drive itself."""
    if tau_s <= 0.0:
        return end_drive
    slope = (end_drive - start_drive) / step_s
    return end_drive - slope * tau_s + (state - start_drive + slope * tau_s) * math.exp(-step_s / tau_s)


@numba.njit(cache=True, nogil=True)
def lag_drive_for(state: float, target: float, step_s: float, tau_s: float) -> float:
    """The drive [A] that, held for step_s [s] from `state`, brings the lag's state to `target` (lag_step
    with equal ends, solved for the drive)."""
    if tau_s <= 0.0 or step_s <= 0.0 or target == state:
        return target
    closed = -math.expm1(-step_s / tau_s)  # the fraction of the gap a held drive closes over step_s
    if closed == 0.0:  # a step too short to move the state at all: no finite drive does it
        return state + math.copysign(math.inf, target - state)
    return state + (target - state) / closed


@numba.njit(cache=True, nogil=True)
def _lag_run(t: np.ndarray, drive: np.ndarray, tau_s: float, state: float, start_drive: float,
             first_step_s: float, out: np.ndarray) -> None:
    out[0] = lag_step(state, start_drive, drive[0], first_step_s, tau_s)
    for k in range(1, t.size):
        out[k] = lag_step(out[k - 1], drive[k - 1], drive[k], t[k] - t[k - 1], tau_s)


def joule_heating(u: np.ndarray | float, reference_a: float) -> np.ndarray | float:
    """The Joule heating in current units [A], u |u| / reference_a (signed by the relay: which wire it
    heats), equal to u at +-reference_a; reference_a 0: the current itself."""
    return u * np.abs(u) / reference_a if reference_a > 0.0 else u


def current_for_heating(heating: float, reference_a: float) -> float:
    """The current [A] whose Joule heating (see joule_heating) is `heating` [A]."""
    if reference_a <= 0.0:
        return heating
    return math.copysign(math.sqrt(abs(heating) * reference_a), heating)


def first_step(t: np.ndarray, state: EffectState | None) -> float:
    """The step [s] that ends at the record's first sample: from the carried state's time, or one sample
    period (the idle start)."""
    if state is not None and state.time_s is not None and state.time_s < t[0]:
        return float(t[0] - state.time_s)
    return float(t[1] - t[0]) if t.size > 1 else 1.0


def idle_start(t: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(t, u) with the moment the current was switched on ahead of them: one sample period before the
    first sample, at u[0] (zero before it)."""
    return np.concatenate(([t[0] - first_step(t, None)], t)), np.concatenate(([u[0]], u))


@dataclass(frozen=True)
class EffectState:
    """Where a record left an effect: the time of its last sample [s] and the effect's own state values
    (the lag's state and its last drive [A]; the delay line's recent (t, u) pairs; the drift's elapsed time
    [s]; the rate's last input [A])."""

    time_s: float | None = None
    values: tuple[float, ...] = field(default_factory=tuple)

    def to_dict(self) -> dict[str, object]:
        """Plain values for YAML."""
        return {"time_s": self.time_s, "values": [float(value) for value in self.values]}


@dataclass(frozen=True)
class Effect:
    """One effect of an identified model: its kind (EFFECT_KINDS) and parameters (units in the names)."""

    kind: str
    parameters: Mapping[str, float]

    def __post_init__(self) -> None:
        if self.kind not in EFFECT_KINDS:
            raise InputError(f"unknown effect {self.kind!r}; known: {', '.join(EFFECT_KINDS)}")
        required, optional = PARAMETERS[self.kind]
        names = set(self.parameters)
        unknown = sorted(names - set(required) - set(optional))
        if unknown:
            raise InputError(f"effect {self.kind}: unknown parameter {unknown[0]!r} "
                             f"(expected {', '.join(required + optional)})")
        missing = [name for name in required if name not in names]
        if missing:
            raise InputError(f"effect {self.kind}: parameter {missing[0]!r} is missing")
        values = {}
        for name in (*required, *optional):
            if name in names:
                value = self.parameters[name]
                if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)) \
                        or not math.isfinite(float(value)):
                    raise InputError(f"effect {self.kind}: parameter {name!r} must be a finite number, got {value!r}")
                values[name] = float(value)
        for name in NON_NEGATIVE[self.kind]:
            if name in values and values[name] < 0.0:
                raise InputError(f"effect {self.kind}: parameter {name!r} must be at least 0, got {values[name]}")
        if self.kind == "drift" and ("creep_m" in values) != ("creep_tau_s" in values):
            raise InputError("effect drift: creep_m and creep_tau_s go together")
        if self.kind == "drift" and values.get("creep_tau_s", 1.0) <= 0.0:
            raise InputError("effect drift: creep_tau_s must be above 0")
        if self.kind == "rate" and not values:
            raise InputError("effect rate: give rate_gain_s_per_A (multiplicative) or rate_shift_m_s_per_A (additive)")
        if self.kind == "wire_thermal" and values["joule_reference_a"] <= 0.0:
            raise InputError("effect wire_thermal: joule_reference_a must be above 0")
        object.__setattr__(self, "parameters", values)

    @property
    def role(self) -> str:
        """'input' (transforms what the GPI sees), 'output' (adds to its output) or 'gpi' (changes it)."""
        return ROLES[self.kind]

    def to_dict(self) -> dict[str, object]:
        """Plain values for YAML."""
        return {"kind": self.kind, "parameters": dict(self.parameters)}

    # --- input transforms ----------------------------------------------------------------------

    def transform(self, t: np.ndarray, u: np.ndarray, state: EffectState | None = None
                  ) -> tuple[np.ndarray, EffectState]:
        """(what the GPI sees [A] for the record (t, u), the state at its last sample); input effects."""
        if self.kind == "thermal_lag":
            return self._lagged(t, u, state)
        if self.kind == "delay":
            return self._delayed(t, u, state)
        if self.kind == "wire_thermal":
            return self._wires(t, u, state)
        raise InputError(f"effect {self.kind} does not transform the input")

    def _wires(self, t: np.ndarray, u: np.ndarray, state: EffectState | None) -> tuple[np.ndarray, EffectState]:
        """The difference of the two wires' temperatures [A of heating], each lagging its own share of the
        Joule heating (wire a heated by u > 0, wire b by u < 0) with its own time constant."""
        reference = self.parameters["joule_reference_a"]
        heating = joule_heating(u, reference)
        drives = (np.ascontiguousarray(np.maximum(heating, 0.0)), np.ascontiguousarray(np.maximum(-heating, 0.0)))
        carried = state is not None and len(state.values) == 4
        temperatures = []
        for wire, (drive, tau) in enumerate(zip(drives, (self.parameters["tau_a_s"], self.parameters["tau_b_s"]), strict=True)):
            start, start_drive = (state.values[2 * wire], state.values[2 * wire + 1]) if carried else (0.0, drive[0])
            out = np.empty(drive.size)
            _lag_run(t, drive, tau, float(start), float(start_drive), first_step(t, state), out)
            temperatures.append(out)
        wire_a, wire_b = temperatures
        end = (float(wire_a[-1]), float(drives[0][-1]), float(wire_b[-1]), float(drives[1][-1]))
        return wire_a - wire_b, EffectState(float(t[-1]), end)

    # --- how a record starts -------------------------------------------------------------------

    def settled(self, u0: float) -> float:
        """What an input effect gives [A] once its input has been held at u0 [A] long enough."""
        if self.kind in ("thermal_lag", "wire_thermal"):
            return float(joule_heating(u0, self.parameters.get("joule_reference_a", 0.0)))
        return float(u0)

    def start_state(self, t: np.ndarray, u: np.ndarray, kind: str, values: tuple[float, ...] = ()
                    ) -> EffectState | None:
        """The state before the record (t [s], u [A] as this effect sees them) starts: None from rest; held
        at u[0] long enough to settle; or free, the FREE_VALUES given."""
        if kind == "rest":
            return None
        step = float(t[1] - t[0]) if t.size > 1 else 1.0
        before = float(t[0]) - step
        u0 = float(u[0])
        if kind == "free" and len(values) != len(FREE_VALUES[self.kind]):
            raise InputError(f"effect {self.kind}: a free start takes {len(FREE_VALUES[self.kind])} values")
        free = kind == "free"
        if self.kind == "thermal_lag":
            drive = self.settled(u0)
            return EffectState(before, (float(values[0]) if free else drive, drive))
        if self.kind == "wire_thermal":
            heating = self.settled(u0)
            a, b = max(heating, 0.0), max(-heating, 0.0)
            return EffectState(before, ((float(values[0]), a, float(values[1]), b) if free else (a, a, b, b)))
        if self.kind == "delay":
            held = float(values[0]) if free else u0
            earliest = before - self.parameters["delay_s"] - step
            return EffectState(before, (earliest, held, before, held))
        if self.kind == "drift":
            return EffectState(float(t[0]), (float(values[0]) if free else 0.0,))
        return EffectState(before, (u0,))

    def _lagged(self, t: np.ndarray, u: np.ndarray, state: EffectState | None) -> tuple[np.ndarray, EffectState]:
        reference = self.parameters.get("joule_reference_a", 0.0)
        drive = np.ascontiguousarray(joule_heating(u, reference), dtype=float)
        out = np.empty(drive.size)
        carried = state is not None and len(state.values) == 2
        start, start_drive = (state.values if carried else (0.0, drive[0]))
        _lag_run(t, drive, self.parameters["tau_s"], float(start), float(start_drive), first_step(t, state), out)
        return out, EffectState(float(t[-1]), (float(out[-1]), float(drive[-1])))

    def _delayed(self, t: np.ndarray, u: np.ndarray, state: EffectState | None) -> tuple[np.ndarray, EffectState]:
        delay = self.parameters["delay_s"]
        if state is not None and state.values:
            history = np.reshape(np.asarray(state.values, dtype=float), (-1, 2))
            times, currents = np.concatenate((history[:, 0], t)), np.concatenate((history[:, 1], u))
        else:
            times, currents = idle_start(t, u)
        out = np.interp(t - delay, times, currents, left=0.0)
        keep = times >= t[-1] - delay - (times[-1] - times[-2] if times.size > 1 else 0.0)
        kept = np.column_stack((times[keep], currents[keep])).ravel()
        return out, EffectState(float(t[-1]), tuple(float(value) for value in kept))

    # --- output offsets ------------------------------------------------------------------------

    def offset(self, t: np.ndarray, state: EffectState | None = None) -> tuple[np.ndarray, EffectState]:
        """(what the effect adds to the output [output unit] at times t, the state at the last sample);
        drift: k (t - t0) [+ A (1 - exp(-(t - t0) / tau_c))], t0 the record's start (or carried on)."""
        if self.kind != "drift":
            raise InputError(f"effect {self.kind} adds nothing to the output")
        before = state.values[0] + (t[0] - state.time_s) if state is not None and state.values else 0.0
        elapsed = t - t[0] + before
        return self.drift_at(elapsed), EffectState(float(t[-1]), (float(elapsed[-1]),))

    def drift_at(self, elapsed_s: np.ndarray) -> np.ndarray:
        """The drift's offset [output unit] elapsed_s [s] after the record's start."""
        if self.kind != "drift":
            raise InputError(f"effect {self.kind} adds nothing to the output")
        names = ("drift_m_per_s", "creep_m") if "creep_m" in self.parameters else ("drift_m_per_s",)
        columns = drift_regressors(np.atleast_1d(np.asarray(elapsed_s, dtype=float)), self.parameters.get("creep_tau_s"))
        return columns @ np.array([self.parameters[name] for name in names])

    # --- rate-dependent thresholds -------------------------------------------------------------

    def rate_input(self, t: np.ndarray, u: np.ndarray, state: EffectState | None = None
                   ) -> tuple[np.ndarray, np.ndarray, EffectState]:
        """(u and |du/dt| [A, A/s] with one sample ahead of the record's first: the carried last input, or
        the idle start's; the state at the last sample) for the rate model, which runs over both and
        drops the first output."""
        if state is not None and state.values:
            times, currents = np.concatenate(([state.time_s], t)), np.concatenate(([state.values[0]], u))
        else:
            times, currents = idle_start(t, u)
        return currents, input_rate(times, currents), EffectState(float(t[-1]), (float(u[-1]),))


PARAMETERS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "thermal_lag": (("tau_s",), ("joule_reference_a",)),
    "delay": (("delay_s",), ()),
    "rate": ((), ("rate_gain_s_per_A", "rate_shift_m_s_per_A")),
    "drift": (("drift_m_per_s",), ("creep_m", "creep_tau_s")),
    "wire_thermal": (("tau_a_s", "tau_b_s", "joule_reference_a"), ()),
}
NON_NEGATIVE = {"thermal_lag": ("tau_s", "joule_reference_a"), "delay": ("delay_s",),
                "rate": ("rate_gain_s_per_A", "rate_shift_m_s_per_A"), "drift": (),
                "wire_thermal": ("tau_a_s", "tau_b_s", "joule_reference_a")}
ROLES = {"thermal_lag": "input", "delay": "input", "rate": "gpi", "drift": "output", "wire_thermal": "input"}
# The values a free start gives each effect (units in the names); the GPI's operators take one more, the
# last turning point of what the GPI sees [A] (see sma_stage.model.identified.Start).
FREE_VALUES: dict[str, tuple[str, ...]] = {
    "thermal_lag": ("lag_state_a",), "delay": ("held_current_a",), "rate": (), "drift": ("elapsed_s",),
    "wire_thermal": ("wire_a_a", "wire_b_a"),
}


def input_rate(t: np.ndarray, u: np.ndarray) -> np.ndarray:
    """|du/dt| [A/s] by second-order finite differences."""
    return np.abs(np.gradient(u, t))


def drift_regressors(elapsed_s: np.ndarray, creep_tau_s: float | None) -> np.ndarray:
    """Columns elapsed [s] and, with a creep time constant, 1 - exp(-elapsed / tau_c); elapsed is the time
    since the record's start."""
    columns = [elapsed_s] if creep_tau_s is None else [elapsed_s, -np.expm1(-elapsed_s / creep_tau_s)]
    return np.column_stack(columns)


@numba.njit(cache=True, nogil=True)
def _rate_output(u: np.ndarray, rate: np.ndarray, theta: np.ndarray, operators: int, gain: float, shift: float,
                 states: np.ndarray, out: np.ndarray) -> None:
    """GPI output with thresholds a9 i (1 + gain rate_k) + shift rate_k and weights a10 exp(-a11 a9 i);
    states in place."""
    nominal = theta[8] * np.arange(operators)
    weights = theta[9] * np.exp(-theta[10] * nominal)
    for k in range(u.size):
        low = theta[0] * math.tanh(theta[1] * u[k] + theta[2]) + theta[3]
        high = theta[4] * math.tanh(theta[5] * u[k] + theta[6]) + theta[7]
        stretch = 1.0 + gain * rate[k]
        widen = shift * rate[k]
        total = 0.0
        for i in range(operators):
            threshold = nominal[i] * stretch + widen
            z = max(low - threshold, min(high + threshold, states[i]))
            states[i] = z
            total += weights[i] * z
        out[k] = total


def rate_forward(u: np.ndarray, rate: np.ndarray, theta: np.ndarray, operators: int, gain_s_per_A: float,
                 states: np.ndarray | None = None, shift_s_per_A: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(GPI output [output unit] with thresholds a9 i (1 + c |du/dt|) + b |du/dt|, the operator states at
    the end); theta is a1..a11, rate |du/dt| [A/s], c [s/A], b [output unit s/A]; states start at zero
    unless given."""
    out = np.empty(np.size(u))
    end = np.zeros(int(operators)) if states is None else np.array(states, dtype=float)
    _rate_output(np.ascontiguousarray(u, dtype=float), np.ascontiguousarray(rate, dtype=float),
                 np.ascontiguousarray(theta, dtype=float), int(operators), float(gain_s_per_A),
                 float(shift_s_per_A), end, out)
    return out, end
