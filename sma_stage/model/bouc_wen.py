"""The Bouc-Wen model, a model family beside the GPI (no ROS): the hysteresis model of the ROS 1 hysteresis
package users know, here as a baseline from outside the Prandtl-Ishlinskii family.

The wires' heating drives it through a first-order lag: h = u |u| / u_ref (u_ref = HEATING_REFERENCE_A; the sign
of the current says which wire heats), tau dx/dt = h - x. The hysteretic part follows x:
dw = (1 - |w|^n (beta sgn(dx w) + gamma)) dx, integrated in steps of at most MAX_DX in x; the output is
y = k_x x + k_w w + offset. With beta > 0 and |gamma| <= beta, |w| stays within (beta + gamma)^(-1/n) and the
output rises with x for k_x, k_w >= 0, which the exact inverse needs.

Sampling as the two-wire model's (sma_stage.model.two_wire): y[k] is measured at t[k], u[k] is held from t[k] to
t[k+1]; the exact inverse is the current that, held over the next period, brings the output to the target.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numba
import numpy as np

from sma_stage.errors import InputError
from sma_stage.model.checks import finite_value
from sma_stage.model.held import HeldCurrentModel, HeldState

KIND = "bouc_wen"
NAMES = ("tau_s", "k_x", "k_w", "offset", "beta", "gamma", "n")
HEATING_REFERENCE_A = 5.0
MAX_DX = 0.01  # the hysteretic part's integration step [A of heating]
HEADER = ("# sma_stage Bouc-Wen model: the wires' heating through a lag, a Bouc-Wen hysteresis of it (input in A,\n"
          "# output in output_unit; see sma_stage.model.bouc_wen)\n")
INVERSE_ITERATIONS = 100
CURRENT_TOLERANCE = 1e-14


@dataclass(frozen=True)
class BoucWenParameters:
    """tau_s [s], k_x and k_w [output unit per A of heating], offset [output unit], beta and gamma [per A of
    heating to the n], n (dimensionless, 1 to 5)."""

    values: Mapping[str, float]

    def __post_init__(self) -> None:
        values = dict(self.values)
        missing = [name for name in NAMES if name not in values]
        unknown = [str(name) for name in values if name not in NAMES]
        if missing:
            raise InputError(f"Bouc-Wen parameters missing: {', '.join(missing)}")
        if unknown:
            raise InputError(f"unknown Bouc-Wen parameter {unknown[0]!r} (known: {', '.join(NAMES)})")
        values = {name: finite_value(values[name], name, "Bouc-Wen") for name in NAMES}
        if values["tau_s"] <= 0.0 or values["beta"] <= 0.0:
            raise InputError("Bouc-Wen tau_s and beta must be > 0")
        if abs(values["gamma"]) > values["beta"]:
            raise InputError(f"Bouc-Wen |gamma| must be at most beta (a bounded hysteresis), got gamma "
                             f"{values['gamma']:g} and beta {values['beta']:g}")
        if values["k_x"] < 0.0 or values["k_w"] < 0.0:
            raise InputError("Bouc-Wen k_x and k_w must be >= 0 (the output rises with the heating)")
        if not 1.0 <= values["n"] <= 5.0:
            raise InputError(f"Bouc-Wen n must be from 1 to 5, got {values['n']:g}")
        object.__setattr__(self, "values", values)

    def as_array(self) -> np.ndarray:
        """The kernel's vector, in NAMES order."""
        return np.array([self.values[name] for name in NAMES])

    def to_dict(self) -> dict[str, float]:
        return dict(self.values)

    @property
    def parameter_count(self) -> int:
        return len(NAMES)


@numba.njit(cache=True, nogil=True)
def _advance(state: np.ndarray, p: np.ndarray, current: float, step_s: float) -> float:
    """Hold current [A] for step_s [s] from state (x, w, y; changed in place); the output at the end."""
    heating = current * abs(current) / HEATING_REFERENCE_A
    x_new = heating + (state[0] - heating) * math.exp(-step_s / p[0])
    dx = x_new - state[0]
    steps = max(1, int(math.ceil(abs(dx) / MAX_DX)))
    h = dx / steps
    w = state[1]
    for _ in range(steps):
        sign = 1.0 if h * w > 0.0 else -1.0
        w += h * (1.0 - abs(w) ** p[6] * (p[4] * sign + p[5]))
    state[0], state[1] = x_new, w
    state[2] = p[1] * x_new + p[2] * w + p[3]
    return state[2]


@numba.njit(cache=True, nogil=True)
def _run(t: np.ndarray, u: np.ndarray, p: np.ndarray, state: np.ndarray, held: float, first_step_s: float,
         out: np.ndarray) -> None:
    if first_step_s > 0.0:
        out[0] = _advance(state, p, held, first_step_s)
    else:
        out[0] = state[2]
    for k in range(1, t.size):
        out[k] = _advance(state, p, u[k - 1], t[k] - t[k - 1])


@numba.njit(cache=True, nogil=True)
def _held(state: np.ndarray, p: np.ndarray, current: float, step_s: float, target: float, trial: np.ndarray) -> float:
    trial[:] = state
    return _advance(trial, p, current, step_s) - target


@numba.njit(cache=True, nogil=True)
def _command_for(state: np.ndarray, p: np.ndarray, target: float, step_s: float, low: float, high: float,
                 trial: np.ndarray) -> float:
    """The current in [low, high] [A] that, held for step_s, brings the output closest to target (the output at
    the step's end rises with the current: bisection)."""
    if _held(state, p, high, step_s, target, trial) <= 0.0:
        return high
    if _held(state, p, low, step_s, target, trial) >= 0.0:
        return low
    for _ in range(INVERSE_ITERATIONS):
        if high - low <= CURRENT_TOLERANCE * (abs(low) + abs(high) + 1.0):
            break
        middle = 0.5 * (low + high)
        if _held(state, p, middle, step_s, target, trial) < 0.0:
            low = middle
        else:
            high = middle
    below = abs(_held(state, p, low, step_s, target, trial))
    return low if below <= abs(_held(state, p, high, step_s, target, trial)) else high


@dataclass(frozen=True)
class BoucWenModel(HeldCurrentModel):
    """A Bouc-Wen model: parameters, output unit, the state a record left (None: not known) and metadata."""

    parameters: BoucWenParameters
    output_unit: str = "m"
    state: HeldState | None = None
    metadata: Mapping[str, object] = field(default_factory=dict, compare=False)

    KIND = KIND
    FAMILY = "Bouc-Wen"
    HEADER = HEADER
    state_size = 3  # x, w, y

    def __post_init__(self) -> None:
        if not isinstance(self.parameters, BoucWenParameters):
            raise InputError(f"parameters must be BoucWenParameters, got {type(self.parameters).__name__}")
        self._check_common()

    @property
    def parameter_count(self) -> int:
        return self.parameters.parameter_count

    @property
    def tau_s(self) -> float:
        """The heating lag [s] the compensator's lead undoes."""
        return self.parameters.values["tau_s"]

    def rest_state(self) -> np.ndarray:
        """x, w and y of a stage long at zero current."""
        return np.array([0.0, 0.0, self.parameters.values["offset"]])

    def _advance_record(self, t: np.ndarray, u: np.ndarray, values: np.ndarray, held: float, first_step_s: float,
                        out: np.ndarray) -> None:
        _run(t, u, self.parameters.as_array(), values, held, first_step_s, out)

    @staticmethod
    def _parameters_from_dict(document: object) -> BoucWenParameters:
        if not isinstance(document, dict):
            raise InputError("Bouc-Wen parameters must be a mapping")
        return BoucWenParameters(document)

    def stream(self, state: HeldState | None = None, max_current_a: float = 5.0) -> BoucWenStream:
        return BoucWenStream(self, state, max_current_a)


class BoucWenStream:
    """The model one sample at a time: `step` follows an applied current, `current_for` is the exact inverse
    over a horizon (the state does not move), `command_for` the same over one step, held."""

    def __init__(self, model: BoucWenModel, state: HeldState | None = None, max_current_a: float = 5.0) -> None:
        if not max_current_a > 0.0:
            raise InputError(f"max_current_a must be > 0, got {max_current_a!r}")
        self.model = model
        self.max_current_a = float(max_current_a)
        self._p = model.parameters.as_array()
        self._state = model.rest_state() if state is None else np.array(state.values, dtype=float)
        self._trial = np.empty_like(self._state)
        self.last_clipped = 0

    @property
    def output(self) -> float:
        return float(self._state[2])

    def step(self, current_a: float, step_s: float) -> float:
        """Hold current_a [A] for step_s [s]; the output at the end [output unit]."""
        return float(_advance(self._state, self._p, float(current_a), float(step_s)))

    def current_for(self, target: float, horizon_s: float) -> float:
        """The current [A] within +-max_current_a that, held for horizon_s [s], brings the output nearest target;
        last_clipped +1 (-1) when the target is above (below) what the limit reaches."""
        limit = self.max_current_a
        current = _command_for(self._state, self._p, float(target), float(horizon_s), -limit, limit, self._trial)
        short = _held(self._state, self._p, current, float(horizon_s), float(target), self._trial)
        self.last_clipped = (current == limit and short < 0.0) - (current == -limit and short > 0.0)
        return current

    def command_for(self, target: float, step_s: float) -> float:
        current = self.current_for(target, step_s)
        self.step(current, step_s)
        return current
