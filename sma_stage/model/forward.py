"""GPI forward model: the source paper's eqs 1-5, batch and one sample at a time."""

from __future__ import annotations

import numpy as np

from sma_stage.errors import InputError
from sma_stage.model import _kernels
from sma_stage.model.checks import as_signal
from sma_stage.model.parameters import DEFAULT_OPERATORS, GPIParameters, check_operators


def initial_states(params: GPIParameters, operators: int, initial: np.ndarray | None) -> np.ndarray:
    """Operator states before the first sample [output unit]: zeros (so z(0) = s(v(0), 0)) or initial."""
    operators = check_operators(operators)
    if initial is None:
        return np.zeros(operators)
    states = as_signal(initial, "initial operator states")
    if states.size != operators:
        raise InputError(f"initial operator states have {states.size} values, expected {operators}")
    return states


def shape_arrays(params: GPIParameters, operators: int) -> tuple[np.ndarray, np.ndarray]:
    """(theta = a1..a8 as an array, thresholds r [output unit]) for the kernels: the envelopes and the operators,
    without their weights."""
    return params.as_array()[:8].copy(), params.thresholds(operators)


def model_arrays(params: GPIParameters, operators: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(theta = a1..a8 as an array, thresholds r [output unit], weights p) for the kernels."""
    weights = params.densities(operators)
    if not np.all(np.isfinite(weights)):
        raise InputError("density p(r) = a10 exp(-a11 r) overflows: a11 too negative for this many operators")
    return (*shape_arrays(params, operators), weights)


def forward(v: np.ndarray, params: GPIParameters, operators: int = DEFAULT_OPERATORS,
            initial: np.ndarray | None = None) -> np.ndarray:
    """Model output y [output unit] for the input sequence v [A] (eqs 1-5 of the paper)."""
    return forward_with_states(v, params, operators, initial)[0]


def forward_with_states(v: np.ndarray, params: GPIParameters, operators: int = DEFAULT_OPERATORS,
                        initial: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(output y [output unit], operator states after the last sample)."""
    v = as_signal(v, "input")
    states = initial_states(params, operators, initial)
    theta, thresholds, weights = model_arrays(params, operators)
    output = np.empty_like(v)
    _kernels.play_forward(v, theta, thresholds, weights, states, output)
    return output, states


class GPIForwardStream:
    """The forward model one sample at a time, keeping its operator states between calls."""

    def __init__(self, params: GPIParameters, operators: int = DEFAULT_OPERATORS,
                 initial: np.ndarray | None = None) -> None:
        self.params = params
        self.operators = check_operators(operators)
        self._theta, self._thresholds, self._weights = model_arrays(params, self.operators)
        self._states = initial_states(params, self.operators, initial)

    @property
    def states(self) -> np.ndarray:
        """A copy of the operator states [output unit]."""
        return self._states.copy()

    def reset(self, initial: np.ndarray | None = None) -> None:
        """Forget the history: states back to zeros, or to initial."""
        self._states = initial_states(self.params, self.operators, initial)

    def step(self, v: float) -> float:
        """Output [output unit] for the next input sample v [A]."""
        v = float(v)
        if not np.isfinite(v):
            raise InputError(f"input must be finite, got {v}")
        return _kernels.output_at(v, self._theta, self._thresholds, self._weights, self._states, True)
