"""The two-wire model of an antagonistic SMA stage, a model family beside the GPI (no ROS).

Each wire has its own temperature and its own hysteresis in it; the stage's output is a hysteresis of what the
two wires' transformations pull together. Per wire w (a: heated by u > 0, b: by u < 0, the relay):
- temperature, in A of heating: tau_w dtheta_w/dt = drive_w - theta_w, drive_a = (u^2 / u_ref) (1 - d xhat_a) for
  u > 0 (else 0), drive_b the same for u < 0 (u_ref = heating_reference_a): theta settles at the current's Joule
  heating, which falls as the wire transforms (austenite conducts better than martensite: d = resistance_drop,
  xhat_w the wire's transformed share x_w / sum_j p_wj at the start of the step);
- transformation: what the wire sees is its temperature shifted by the stress the stage's position puts on it
  and by the tension the other wire's transformation pulls into the pair (Clausius-Clapeyron),
  seen_a = theta_a - coupling_a y - k xhat_b, seen_b = theta_b + coupling_b y - k xhat_a, k = tension_coupling
  >= 0 (at a hand-over the wire still hot holds the heated one back until it cools, and the heated one then pulls
  it out of its transformation); the transformed
  fraction x_w = sum_j p_wj sigma((P_rj[seen_w] - centre_w) / width_w), P_r the play operator of threshold
  r_j = hysteresis_w j / (n - 1) and sigma(s) = (1 + tanh s) / 2 (a Preisach-like family of transformation
  curves, the weights p_wj >= 0 free); with compact_onset 1 instead sigma(s) = h((s + 1.5) / 3), h(x) = 3x^2 - 2x^3
  on [0, 1] (0 below, 1 above): the same slope at the centre, but a wire seen 1.5 widths below its centre does
  not transform at all, as a real wire below its transformation start does not (tanh's tail moves it a little);
- output: m = stroke_a x_a - stroke_b x_b, y = offset + sum_k q_k P_sk[m], s_k = output_threshold k / (m - 1),
  q_k >= 0 (the detwinning left in the cold wire, which makes the output lag what the wires pull).

Sampling: y[k] is the position measured at t[k]; the current u[k] is applied from t[k] to t[k+1] (held, as a
sampled drive and a compensator's command are). So y[k] depends on u[0..k-1] and the state before the record,
and the exact inverse is the current that, held over the next period, brings the output to the target (from the
last command, to KEEP_TOLERANCE of the strokes: see _command_for). A hold
longer than FIRST_SUBSTEP_S (a compensator's lead horizon, the reach) is taken in sub-steps, as if sampled: in one
step the position's pull on each wire and the heating's fall would stay where the hold began.
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

KIND = "two_wire"
SCALARS = ("tau_a_s", "tau_b_s", "heating_reference_a", "coupling_a", "coupling_b", "centre_a", "centre_b",
           "width_a", "width_b", "hysteresis_a", "hysteresis_b", "stroke_a", "stroke_b", "offset",
           "output_threshold", "resistance_drop", "tension_coupling", "compact_onset")
WEIGHTS = ("weights_a", "weights_b", "output_weights")
POSITIVE = ("tau_a_s", "tau_b_s", "heating_reference_a", "width_a", "width_b")
NON_NEGATIVE = ("hysteresis_a", "hysteresis_b", "stroke_a", "stroke_b", "output_threshold", "resistance_drop",
                "tension_coupling")
DEFAULTS = {"resistance_drop": 0.0, "tension_coupling": 0.0, "compact_onset": 0.0}  # what a model file written
# before each existed was fitted with
FIXED = ("heating_reference_a", "compact_onset")  # set by the fit, not fitted
FIRST_WEIGHT = len(SCALARS)  # where the weights start in the kernel's parameter vector
RESISTANCE_DROP = SCALARS.index("resistance_drop")
TENSION_COUPLING = SCALARS.index("tension_coupling")
COMPACT_ONSET = SCALARS.index("compact_onset")
ONSETS = ("tanh", "compact")  # the transformation curve's shape, compact_onset 0 and 1
MAX_OPERATORS = 50
HEADER = ("# sma_stage two-wire model: each wire's temperature and its own hysteresis in it, the output a\n"
          "# hysteresis of the two wires' pull (input in A, output in output_unit; see sma_stage.model.two_wire)\n")
INVERSE_ITERATIONS = 100  # at most this many trial steps per inverse call (a few are the rule)
OUTPUT_TOLERANCE = 1e-13  # a trial within this fraction of the strokes and offset of the target ends the search
KEEP_TOLERANCE = 1e-4  # the last command is kept while it brings the output within this fraction of them of the
# target; beyond, the search aims at the near edge of that band
CURRENT_TOLERANCE = 1e-14  # a bracket narrower than this (relative) ends it
GUESS_FIRST_STEP = 1e-3  # the bracket is sought from the last command first in steps of this fraction of the range ..
GUESS_GROWTH = 8.0  # .. each this many times the one before
FIRST_SUBSTEP_S = 1.0  # a longer hold is taken in sub-steps this long (a record's step, 1 s or less, is one) ..
SETTLING_TAUS = 3.0  # .. over the first this many time constants of the slower wire, then ..
SUBSTEP_GROWTH = 1.5  # .. each this many times the one before
SETTLING_SUBSTEPS = 30  # sub-steps over those time constants at most (longer ones for a slow wire)


@dataclass(frozen=True)
class TwoWireParameters:
    """The model's scalars (units: s, A of heating, output unit; couplings in A per output unit; resistance_drop
    dimensionless, 0 to 1; tension_coupling in A of heating per wire's full transformation; compact_onset 0 (the
    tanh transformation curve) or 1 (the compact one); each of the last three 0 when a model file has none) and
    its three weight vectors (dimensionless, >= 0)."""

    values: Mapping[str, float]
    weights_a: tuple[float, ...]
    weights_b: tuple[float, ...]
    output_weights: tuple[float, ...]

    def __post_init__(self) -> None:
        values = {**DEFAULTS, **self.values}
        missing = [name for name in SCALARS if name not in values]
        unknown = [str(name) for name in values if name not in SCALARS]
        if missing:
            raise InputError(f"two-wire parameters missing: {', '.join(missing)}")
        if unknown:
            raise InputError(f"unknown two-wire parameter {unknown[0]!r} (known: {', '.join(SCALARS)})")
        values = {name: _finite(values[name], name) for name in SCALARS}
        for name in POSITIVE:
            if values[name] <= 0.0:
                raise InputError(f"two-wire parameter {name} must be > 0, got {values[name]:g}")
        for name in NON_NEGATIVE:
            if values[name] < 0.0:
                raise InputError(f"two-wire parameter {name} must be >= 0, got {values[name]:g}")
        if values["compact_onset"] not in (0.0, 1.0):
            raise InputError(f"two-wire parameter compact_onset must be 0 (tanh) or 1 (compact), got "
                             f"{values['compact_onset']:g}")
        if values["resistance_drop"] >= 1.0:
            raise InputError(f"two-wire parameter resistance_drop must be < 1 (a share of the cold wire's "
                             f"resistance), got {values['resistance_drop']:g}")
        object.__setattr__(self, "values", values)
        for name in WEIGHTS:
            weights = getattr(self, name)
            if not isinstance(weights, (list, tuple, np.ndarray)):
                raise InputError(f"two-wire {name} must be a list of numbers")
            weights = tuple(_finite(value, name) for value in weights)
            if not 1 <= len(weights) <= MAX_OPERATORS:
                raise InputError(f"two-wire {name} must hold 1 to {MAX_OPERATORS} weights, got {len(weights)}")
            if min(weights) < 0.0:
                raise InputError(f"two-wire {name} must be >= 0 (the model must rise with each wire's heating)")
            object.__setattr__(self, name, weights)
        if len(self.weights_a) != len(self.weights_b):
            raise InputError(f"weights_a and weights_b differ in length ({len(self.weights_a)}, {len(self.weights_b)})")

    @property
    def wire_operators(self) -> int:
        """Play operators per wire."""
        return len(self.weights_a)

    @property
    def output_operators(self) -> int:
        """Play operators of the output layer."""
        return len(self.output_weights)

    def as_array(self) -> np.ndarray:
        """The kernel's parameter vector: the scalars in SCALARS order, then weights_a, weights_b, output_weights."""
        return np.array([self.values[name] for name in SCALARS] + list(self.weights_a) + list(self.weights_b)
                        + list(self.output_weights))

    @classmethod
    def from_array(cls, vector: np.ndarray, wire_operators: int, output_operators: int) -> TwoWireParameters:
        """The inverse of as_array."""
        vector = np.asarray(vector, dtype=float).ravel()
        count = len(SCALARS)
        if vector.size != count + 2 * wire_operators + output_operators:
            raise InputError(f"expected {count + 2 * wire_operators + output_operators} two-wire values, "
                             f"got {vector.size}")
        split = (count, count + wire_operators, count + 2 * wire_operators)
        return cls(dict(zip(SCALARS, vector[:count].tolist(), strict=True)), tuple(vector[split[0]:split[1]]),
                   tuple(vector[split[1]:split[2]]), tuple(vector[split[2]:]))

    def to_dict(self) -> dict[str, object]:
        """Plain values for YAML."""
        return {**self.values, **{name: list(getattr(self, name)) for name in WEIGHTS}}

    @classmethod
    def from_dict(cls, document: object) -> TwoWireParameters:
        """The parameters from a mapping of SCALARS and WEIGHTS."""
        if not isinstance(document, dict):
            raise InputError("two-wire parameters must be a mapping")
        weights = {name: document.get(name) for name in WEIGHTS}
        for name, value in weights.items():
            if value is None:
                raise InputError(f"two-wire parameters missing: {name}")
        scalars = {key: value for key, value in document.items() if key not in WEIGHTS}
        return cls(scalars, *(weights[name] for name in WEIGHTS))

    @property
    def parameter_count(self) -> int:
        """Free parameters, the FIXED ones left out (the heating reference is the record's largest current; the
        onset's shape is chosen, not fitted)."""
        return len(SCALARS) - len(FIXED) + 2 * self.wire_operators + self.output_operators


def state_size(wire_operators: int, output_operators: int) -> int:
    """Length of the state vector: theta_a, theta_b, the wires' plays, the output plays, the last output."""
    return 3 + 2 * wire_operators + output_operators


@numba.njit(cache=True, nogil=True)
def transformation_curve(value: float, compact: float) -> tuple[float, float]:
    """The transformation curve at value (widths from the centre) and its slope there: tanh's, or the compact
    one (compact > 0)."""
    if compact > 0.0:
        x = min(max((value + 1.5) / 3.0, 0.0), 1.0)
        return x * x * (3.0 - 2.0 * x), 2.0 * x * (1.0 - x)
    tanh = math.tanh(value)
    return 0.5 * (1.0 + tanh), 0.5 * (1.0 - tanh * tanh)


@numba.njit(cache=True, nogil=True)
def _sigma(value: float, compact: float) -> float:
    return transformation_curve(value, compact)[0]


@numba.njit(cache=True, nogil=True)
def _play(state: float, value: float, threshold: float) -> float:
    if value - threshold > state:
        return value - threshold
    if value + threshold < state:
        return value + threshold
    return state


@numba.njit(cache=True, nogil=True)
def _transformed_share(state: np.ndarray, p: np.ndarray, n: int, wire: int) -> float:
    """The wire's transformed fraction as a share of its full transformation (0 to 1), from its plays now."""
    total, transformed = 0.0, 0.0
    for j in range(n):
        weight = p[FIRST_WEIGHT + wire * n + j]
        total += weight
        transformed += weight * _sigma((state[2 + wire * n + j] - p[5 + wire]) / p[7 + wire], p[COMPACT_ONSET])
    return transformed / total if total > 0.0 else 0.0


@numba.njit(cache=True, nogil=True)
def _shares(state: np.ndarray, p: np.ndarray, n: int) -> tuple[float, float]:
    """Both wires' transformed shares (_transformed_share)."""
    return _transformed_share(state, p, n, 0), _transformed_share(state, p, n, 1)


@numba.njit(cache=True, nogil=True)
def _advance(state: np.ndarray, p: np.ndarray, n: int, m: int, current: float, step_s: float) -> float:
    """Hold `current` [A] for step_s [s] from `state` (changed in place); the output at the end."""
    read = p[RESISTANCE_DROP] > 0.0 or p[TENSION_COUPLING] > 0.0  # else the shares are not read
    share_a, share_b = _shares(state, p, n) if read else (0.0, 0.0)
    return _advance_from(state, p, n, m, current, step_s, share_a, share_b)[0]


@numba.njit(cache=True, nogil=True)
def _advance_from(state: np.ndarray, p: np.ndarray, n: int, m: int, current: float, step_s: float,
                  share_a: float, share_b: float) -> tuple[float, float, float]:
    """_advance given the wires' transformed shares at the step's start (what the last step left); the output
    at the end and the shares there. A hold longer than FIRST_SUBSTEP_S is taken in sub-steps that long (at most
    SETTLING_SUBSTEPS over SETTLING_TAUS time constants), growing by SUBSTEP_GROWTH each after those, so that the
    position's pull on each wire and its heating follow the hold as they follow a sampled record."""
    if not math.isfinite(step_s):
        return _substep(state, p, n, m, current, step_s, share_a, share_b)
    settling_s = SETTLING_TAUS * max(p[0], p[1])
    left, length, growing_after = step_s, max(FIRST_SUBSTEP_S, settling_s / SETTLING_SUBSTEPS), step_s - settling_s
    while True:
        last = left <= length * (1.0 + 1e-9)  # a record's step of FIRST_SUBSTEP_S, give or take rounding
        substep = left if last else length
        y, share_a, share_b = _substep(state, p, n, m, current, substep, share_a, share_b)
        if last:
            return y, share_a, share_b
        left -= substep
        if left < growing_after:
            length *= SUBSTEP_GROWTH


@numba.njit(cache=True, nogil=True)
def _substep(state: np.ndarray, p: np.ndarray, n: int, m: int, current: float, step_s: float,
             share_a: float, share_b: float) -> tuple[float, float, float]:
    """One step of the model's recursion (the module's equations, the position and the shares those at its
    start); the output at the end and the shares there."""
    reference = p[2]
    heating = current * current / reference
    y_before = state[2 + 2 * n + m]
    pull = 0.0
    shares = (share_a, share_b)
    share_a, share_b = 0.0, 0.0
    for wire in range(2):
        drive = heating if (current > 0.0) == (wire == 0) and current != 0.0 else 0.0
        if drive > 0.0 and p[RESISTANCE_DROP] > 0.0:
            drive *= 1.0 - p[RESISTANCE_DROP] * shares[wire]
        state[wire] = drive + (state[wire] - drive) * math.exp(-step_s / p[wire])
        sign = 1.0 if wire == 0 else -1.0
        seen = state[wire] - sign * p[3 + wire] * y_before - p[TENSION_COUPLING] * shares[1 - wire]
        centre, width, hysteresis = p[5 + wire], p[7 + wire], p[9 + wire]
        fraction, total = 0.0, 0.0
        for j in range(n):
            threshold = hysteresis * j / (n - 1) if n > 1 else 0.0
            index = 2 + wire * n + j
            state[index] = _play(state[index], seen, threshold)
            weight = p[FIRST_WEIGHT + wire * n + j]
            total += weight
            fraction += weight * _sigma((state[index] - centre) / width, p[COMPACT_ONSET])
        share = fraction / total if total > 0.0 else 0.0
        if wire == 0:
            share_a = share
        else:
            share_b = share
        pull += sign * p[11 + wire] * fraction
    y = p[13]
    for k in range(m):
        threshold = p[14] * k / (m - 1) if m > 1 else 0.0
        index = 2 + 2 * n + k
        state[index] = _play(state[index], pull, threshold)
        y += p[FIRST_WEIGHT + 2 * n + k] * state[index]
    state[2 + 2 * n + m] = y
    return y, share_a, share_b


@numba.njit(cache=True, nogil=True)
def _rest(p: np.ndarray, n: int, m: int, state: np.ndarray) -> None:
    """The state of a stage long at zero current: cold wires, plays at what they see, the output settled."""
    state[:] = 0.0
    y = 0.0
    shares = np.zeros(2)
    for _ in range(200):  # the couplings make rest a fixed point of the output
        state[2 + 2 * n + m] = y
        pull = 0.0
        before = shares.copy()
        for wire in range(2):
            sign = 1.0 if wire == 0 else -1.0
            seen = -sign * p[3 + wire] * y - p[TENSION_COUPLING] * before[1 - wire]
            fraction, total = 0.0, 0.0
            for j in range(n):
                state[2 + wire * n + j] = seen
                weight = p[FIRST_WEIGHT + wire * n + j]
                total += weight
                fraction += weight * _sigma((seen - p[5 + wire]) / p[7 + wire], p[COMPACT_ONSET])
            pull += sign * p[11 + wire] * fraction
            shares[wire] = 0.5 * (before[wire] + (fraction / total if total > 0.0 else 0.0))
        y_new = p[13]
        for k in range(m):
            state[2 + 2 * n + k] = pull
            y_new += p[FIRST_WEIGHT + 2 * n + k] * pull
        settled = p[TENSION_COUPLING] == 0.0 or np.all(np.abs(shares - before) <= 1e-15)
        if abs(y_new - y) <= 1e-15 * (1.0 + abs(y)) and settled:
            y = y_new
            break
        y = 0.5 * (y + y_new)  # damped: a strong coupling would make the plain iteration oscillate
    state[2 + 2 * n + m] = y


@numba.njit(cache=True, nogil=True)
def _run(t: np.ndarray, u: np.ndarray, p: np.ndarray, n: int, m: int, state: np.ndarray, held: float,
         first_step_s: float, out: np.ndarray) -> None:
    """Outputs at each sample of a record (see the module's sampling rule): `held` is the current applied
    before the first sample, for first_step_s (0: the state is at the first sample already)."""
    share_a, share_b = _shares(state, p, n)
    if first_step_s > 0.0:
        out[0], share_a, share_b = _advance_from(state, p, n, m, held, first_step_s, share_a, share_b)
    else:
        out[0] = state[2 + 2 * n + m]
    for k in range(1, t.size):
        out[k], share_a, share_b = _advance_from(state, p, n, m, u[k - 1], t[k] - t[k - 1], share_a, share_b)


@numba.njit(cache=True, nogil=True)
def _held(state: np.ndarray, p: np.ndarray, n: int, m: int, current: float, step_s: float, target: float,
          trial: np.ndarray, share_a: float, share_b: float) -> float:
    """How far above target the output ends when current is held for step_s from state (state unchanged),
    share_a and share_b the wires' transformed shares in state."""
    trial[:] = state
    return _advance_from(trial, p, n, m, current, step_s, share_a, share_b)[0] - target


@numba.njit(cache=True, nogil=True)
def _clipped(current: float, above: float, lowest: float, highest: float) -> int:
    """+1 (-1) when current is the range's top (bottom) and the output held there ends `above` < 0 (> 0): the
    target is beyond what the range reaches; else 0."""
    return int(current == highest and above < 0.0) - int(current == lowest and above > 0.0)


@numba.njit(cache=True, nogil=True)
def _command_for(state: np.ndarray, p: np.ndarray, n: int, m: int, target: float, step_s: float,
                 low: float, high: float, guess: float, trial: np.ndarray) -> tuple[float, int]:
    """The current in [low, high] [A] that, held for step_s, brings the output closest to target, and whether the
    target is beyond the range (_clipped): the output at the end of the step rises with the current over the
    whole range (u < 0 heats wire b less as u rises, u > 0 heats wire a more), so a bracketing search finds it
    (regula falsi, Illinois variant, bisecting when a step would leave the bracket); the range's end when the
    target is out of reach. guess (NaN: none), the last command, is where the bracket is sought first: steps
    from it growing by GUESS_GROWTH until the output crosses the target, a few trials where the target moved
    little since, in place of the range's ends. The guess is kept while it brings the output within KEEP_TOLERANCE of
    the strokes of the target, and beyond that the search aims at the near edge of that band: where the output is
    flat in the current (a wire cooled back through its hysteresis, the other not yet transforming) the answer to a
    target a few nanometres off is amperes away, and a held level fell 4 % of the stroke after such a jump (see
    sma_stage.control.compensator's docstring)."""
    share_a, share_b = _shares(state, p, n)
    scale = abs(p[11]) + abs(p[12]) + abs(p[13]) + 1e-300
    close = OUTPUT_TOLERANCE * scale
    lowest, highest = low, high
    if low < guess < high:
        above = _held(state, p, n, m, guess, step_s, target, trial, share_a, share_b)
        keep = KEEP_TOLERANCE * scale
        if abs(above) <= keep:
            return guess, 0
        target, above = (target + keep, above - keep) if above > 0.0 else (target - keep, above + keep)
        rising = above < 0.0  # the answer lies above the guess
        end = high if rising else low
        width = GUESS_FIRST_STEP * (high - low)
        near, above_near = guess, above
        while True:
            far = min(end, near + width) if rising else max(end, near - width)
            above_far = _held(state, p, n, m, far, step_s, target, trial, share_a, share_b)
            if abs(above_far) <= close or far == end and (above_far > 0.0) != rising:
                return far, _clipped(far, above_far, lowest, highest)  # reached, or beyond the range's end
            if (above_far > 0.0) == rising:
                break
            near, above_near, width = far, above_far, width * GUESS_GROWTH
        low, above_low, high, above_high = (near, above_near, far, above_far) if rising else (far, above_far, near,
                                                                                              above_near)
    else:
        above_high = _held(state, p, n, m, high, step_s, target, trial, share_a, share_b)
        if above_high <= 0.0:
            return high, _clipped(high, above_high, lowest, highest)
        above_low = _held(state, p, n, m, low, step_s, target, trial, share_a, share_b)
        if above_low >= 0.0:
            return low, _clipped(low, above_low, lowest, highest)
    side = 0
    for _ in range(INVERSE_ITERATIONS):
        if high - low <= CURRENT_TOLERANCE * (abs(low) + abs(high) + 1.0):
            break
        trial_current = (low * above_high - high * above_low) / (above_high - above_low)
        if not low < trial_current < high:
            trial_current = 0.5 * (low + high)
        above = _held(state, p, n, m, trial_current, step_s, target, trial, share_a, share_b)
        if abs(above) <= close:
            return trial_current, 0
        if above < 0.0:
            low, above_low = trial_current, above
            if side == -1:
                above_high *= 0.5
            side = -1
        else:
            high, above_high = trial_current, above
            if side == 1:
                above_low *= 0.5
            side = 1
    below = abs(_held(state, p, n, m, low, step_s, target, trial, share_a, share_b))
    return (low if below <= abs(_held(state, p, n, m, high, step_s, target, trial, share_a, share_b)) else high), 0


TwoWireState = HeldState  # what a record leaves the model in (sma_stage.model.held)


@dataclass(frozen=True)
class TwoWireModel(HeldCurrentModel):
    """A two-wire model: parameters, output unit, the state a record left (None: not known) and metadata."""

    parameters: TwoWireParameters
    output_unit: str = "m"
    state: TwoWireState | None = None
    metadata: Mapping[str, object] = field(default_factory=dict, compare=False)

    KIND = KIND
    FAMILY = "two-wire"
    HEADER = HEADER

    def __post_init__(self) -> None:
        if not isinstance(self.parameters, TwoWireParameters):
            raise InputError(f"parameters must be TwoWireParameters, got {type(self.parameters).__name__}")
        self._check_common()

    @property
    def state_size(self) -> int:
        """Length of the state vector."""
        return state_size(self.parameters.wire_operators, self.parameters.output_operators)

    @property
    def parameter_count(self) -> int:
        """Free parameters (for an information criterion)."""
        return self.parameters.parameter_count

    @property
    def tau_s(self) -> float:
        """The slower wire's time constant [s]: the lag the compensator's lead undoes."""
        return max(self.parameters.values["tau_a_s"], self.parameters.values["tau_b_s"])

    def rest_state(self) -> np.ndarray:
        """The state vector of a stage long at zero current."""
        params = self.parameters
        state = np.empty(self.state_size)
        _rest(params.as_array(), params.wire_operators, params.output_operators, state)
        return state

    def _advance_record(self, t: np.ndarray, u: np.ndarray, values: np.ndarray, held: float, first_step_s: float,
                        out: np.ndarray) -> None:
        params = self.parameters
        _run(t, u, params.as_array(), params.wire_operators, params.output_operators, values, held, first_step_s, out)

    @staticmethod
    def _parameters_from_dict(document: object) -> TwoWireParameters:
        return TwoWireParameters.from_dict(document)

    def stream(self, state: TwoWireState | None = None, max_current_a: float = 5.0) -> TwoWireStream:
        """A sample-at-a-time forward and exact inverse, from rest or from state."""
        return TwoWireStream(self, state, max_current_a)


class TwoWireStream:
    """The model one sample at a time: `step` follows an applied current, `command_for` is the exact inverse
    (the current that, held over the next period, brings the output to a target) and commits it."""

    def __init__(self, model: TwoWireModel, state: TwoWireState | None = None, max_current_a: float = 5.0) -> None:
        if not max_current_a > 0.0:
            raise InputError(f"max_current_a must be > 0, got {max_current_a!r}")
        self.model = model
        self.max_current_a = float(max_current_a)
        params = model.parameters
        self._p = params.as_array()
        self._n, self._m = params.wire_operators, params.output_operators
        self._state = model.rest_state() if state is None else np.array(state.values, dtype=float)
        self._trial = np.empty_like(self._state)
        self._last_current = math.nan  # the last current_for's answer [A]: where the next one's search starts
        self.last_clipped = 0

    @property
    def output(self) -> float:
        """The model's output now [output unit]."""
        return float(self._state[-1])

    @property
    def temperatures(self) -> tuple[float, float]:
        """The two wires' temperatures [A of heating]."""
        return float(self._state[0]), float(self._state[1])

    def step(self, current_a: float, step_s: float) -> float:
        """Hold current_a [A] for step_s [s]; the output at the end [output unit]."""
        return float(_advance(self._state, self._p, self._n, self._m, float(current_a), float(step_s)))

    def current_for(self, target: float, horizon_s: float) -> float:
        """The current [A] within +-max_current_a that, held for horizon_s [s], brings the output nearest
        target [output unit]; the state does not move. last_clipped: +1 (-1) when the target is above (below)
        what the limit reaches over the horizon, else 0."""
        limit = self.max_current_a
        current, self.last_clipped = _command_for(self._state, self._p, self._n, self._m, float(target),
                                                  float(horizon_s), -limit, limit, self._last_current, self._trial)
        self._last_current = current
        return current

    def command_for(self, target: float, step_s: float) -> float:
        """The current [A] within +-max_current_a that, held for step_s [s], brings the output nearest target
        [output unit]; the stream then holds it (its state moves to the end of the step)."""
        current = self.current_for(target, step_s)
        self.step(current, step_s)
        return current


def _finite(value: object, name: str) -> float:
    return finite_value(value, name, "two-wire")
