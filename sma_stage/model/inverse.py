"""GPI inverse: the exact inverse (root of the monotone map at each sample) and the paper's
analytic inverse (eqs 6-8), batch and one sample at a time."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sma_stage.errors import InputError
from sma_stage.model import _kernels
from sma_stage.model.checks import as_signal
from sma_stage.model.forward import forward, initial_states, model_arrays
from sma_stage.model.parameters import DEFAULT_OPERATORS, GPIParameters, check_operators

METHODS = ("exact", "analytic")
RELATIVE_TOLERANCE = 1e-10  # solver stopping rule, ten times inside the 1e-9 promised
TARGET_MARGIN_SPANS = 10.0  # targets are clipped this many output spans beyond the reach: no overflow, same answer
SATURATED_TANH_ARGUMENT = 20.0


@dataclass(frozen=True)
class InverseResult:
    """Inputs [A] for the targets, where they were clipped (+1 above reach, -1 below, 0 reached),
    and the forward output [output unit] that the inputs give."""

    input: np.ndarray
    clipped: np.ndarray
    output: np.ndarray
    method: str
    input_range: tuple[float, float]

    @property
    def any_clipped(self) -> bool:
        """True when some target lay beyond what the input range reaches."""
        return bool(np.any(self.clipped))


def default_input_range(params: GPIParameters) -> tuple[float, float]:
    """The inputs [A] over which either envelope still changes (beyond it both are saturated)."""
    ends = []
    for gain, shift in ((params.a2, params.a3), (params.a6, params.a7)):
        ends += [(-SATURATED_TANH_ARGUMENT - shift) / gain, (SATURATED_TANH_ARGUMENT - shift) / gain]
    return min(ends), max(ends)


def check_input_range(params: GPIParameters, input_range: tuple[float, float] | None) -> tuple[float, float]:
    """The input range [A] as two finite floats low < high (the default when None)."""
    if input_range is None:
        return default_input_range(params)
    try:
        low, high = (float(value) for value in input_range)
    except (TypeError, ValueError):
        raise InputError(f"input range must be two numbers (low, high), got {input_range!r}") from None
    if not (np.isfinite(low) and np.isfinite(high) and low < high):
        raise InputError(f"input range must be finite with low < high, got ({low}, {high})")
    return low, high


def output_reach(params: GPIParameters, operators: int, input_range: tuple[float, float]) -> tuple[float, float]:
    """The lowest and highest model output over a full input sweep [output unit].

    Taken from the output itself, not from the envelopes: envelopes that cancel (a huge a1 with an
    opposite a4) would otherwise give a range far larger than the output's.
    """
    low, high = input_range
    outputs = forward(np.concatenate([np.linspace(low, high, 201), np.linspace(high, low, 201)]), params, operators)
    return float(np.min(outputs)), float(np.max(outputs))


def output_span(params: GPIParameters, operators: int, input_range: tuple[float, float]) -> float:
    """The width of output_reach [output unit] (1 when the output is constant): the solver's tolerance scale."""
    low, high = output_reach(params, operators, input_range)
    return (high - low) or 1.0


def check_invertible(params: GPIParameters, operators: int) -> None:
    """Refuse parameters whose output is not an increasing function of the input."""
    problems = params.invertibility_problems(operators)
    if problems:
        raise InputError("model is not invertible: " + "; ".join(problems))


def analytic_coefficients(params: GPIParameters, operators: int) -> tuple[np.ndarray, np.ndarray]:
    """Inverse thresholds r^_j (eq 7) [output unit] and weights p^_j (eq 8) of the paper."""
    thresholds, weights = params.thresholds(operators), params.densities(operators)
    partial_sums = np.cumsum(weights)
    r_hat = np.array([np.sum(weights[: j + 1] * (thresholds[j] - thresholds[: j + 1]))
                      for j in range(operators)])
    p_hat = np.empty(operators)
    p_hat[0] = 1.0 / weights[0]
    p_hat[1:] = -weights[1:] / (partial_sums[1:] * partial_sums[:-1])
    return r_hat, p_hat


def analytic_play_states(params: GPIParameters, operators: int, states: np.ndarray) -> np.ndarray:
    """Play states of the inverse that match forward operator states z_i (composition rule):
    x_j = sum_{i<=j} p_i z_i + (sum_{i>j} p_i) z_j."""
    weights = params.densities(operators)
    remaining = weights.sum() - np.cumsum(weights)
    return np.cumsum(weights * states) + remaining * states


class GPIInverseStream:
    """The inverse one target at a time [output unit] -> input [A], keeping its states."""

    def __init__(self, params: GPIParameters, operators: int = DEFAULT_OPERATORS, method: str = "exact",
                 initial: np.ndarray | None = None, input_range: tuple[float, float] | None = None) -> None:
        if method not in METHODS:
            raise InputError(f"inverse method must be one of {', '.join(METHODS)}, got {method!r}")
        self.params = params
        self.operators = check_operators(operators)
        self.method = method
        check_invertible(params, self.operators)
        self.input_range = check_input_range(params, input_range)
        self._theta, self._thresholds, self._weights = model_arrays(params, self.operators)
        self._r_hat, self._p_hat = analytic_coefficients(params, self.operators)
        reach_low, reach_high = output_reach(params, self.operators, self.input_range)
        span = (reach_high - reach_low) or 1.0
        self._tolerance = RELATIVE_TOLERANCE * span
        self.target_bounds = (reach_low - TARGET_MARGIN_SPANS * span, reach_high + TARGET_MARGIN_SPANS * span)
        self._result = np.empty(3)
        self.last_clipped = 0
        self.reset(initial)

    def reset(self, initial: np.ndarray | None = None, previous_input: float = 0.0) -> None:
        """Forget the history: operator states back to zeros, or to initial [output unit]; previous_input [A]
        is where the exact inverse's next search starts (the input nearest it is chosen)."""
        self._states = initial_states(self.params, self.operators, initial)
        self._plays = analytic_play_states(self.params, self.operators, self._states)
        self._direction = np.array([float(self._weights @ self._states), 1.0])
        self._input = float(np.clip(previous_input, *self.input_range))
        self.last_clipped = 0

    @property
    def states(self) -> np.ndarray:
        """A copy of the forward operator states [output unit] (exact method)."""
        return self._states.copy()

    def step(self, target: float) -> float:
        """Input [A] for the next target output; last_clipped says whether the target was out of reach."""
        target = float(target)
        if not np.isfinite(target):
            raise InputError(f"target output must be finite, got {target}")
        target = min(self.target_bounds[1], max(self.target_bounds[0], target))
        low, high = self.input_range
        if self.method == "exact":
            _kernels.exact_inverse_step(target, self._input, low, high, self._tolerance, self._theta,
                                        self._thresholds, self._weights, self._states, self._result)
        else:
            _kernels.analytic_inverse_step(target, self._direction, low, high, self._theta, self._r_hat,
                                           self._p_hat, self._plays, self._result)
        self._input = float(self._result[0])
        self.last_clipped = int(self._result[1])
        return self._input

    def run(self, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Inputs [A] and clip flags for a whole target sequence, continuing from the current states."""
        targets = np.clip(as_signal(targets, "target output"), *self.target_bounds)
        inputs, clipped = np.empty_like(targets), np.empty_like(targets)
        low, high = self.input_range
        if self.method == "exact":
            self._input = _kernels.exact_inverse(targets, self._input, low, high, self._tolerance,
                                                 self._theta, self._thresholds, self._weights, self._states,
                                                 inputs, clipped)
        else:
            _kernels.analytic_inverse(targets, self._direction, low, high, self._theta, self._r_hat,
                                      self._p_hat, self._plays, inputs, clipped)
            self._input = float(inputs[-1])
        self.last_clipped = int(clipped[-1])
        return inputs, clipped.astype(np.int8)


def inverse(y: np.ndarray, params: GPIParameters, operators: int = DEFAULT_OPERATORS, method: str = "exact",
            initial: np.ndarray | None = None, input_range: tuple[float, float] | None = None,
            full_output: bool = False) -> np.ndarray | InverseResult:
    """Input sequence [A] whose model output follows y [output unit].

    exact: at each sample the input nearest the previous one whose output equals the target to
    1e-9 of the output span; targets beyond reach give the input range's end and are flagged.
    analytic: the paper's eqs 6-8. With full_output, an InverseResult (flags, achieved output).
    """
    stream = GPIInverseStream(params, operators, method, initial, input_range)
    inputs, clipped = stream.run(y)
    if not full_output:
        return inputs
    achieved = forward(inputs, params, operators, initial)
    return InverseResult(inputs, clipped, achieved, method, stream.input_range)
