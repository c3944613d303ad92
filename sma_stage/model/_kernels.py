"""Compiled inner loops of the GPI model (numba); the public API is in forward.py and inverse.py."""

import numba
import numpy as np


@numba.njit(cache=True, nogil=True, fastmath=True)
def _clamp_and_sum(low: float, high: float, r: np.ndarray, p: np.ndarray, states: np.ndarray,
                   store: bool) -> float:
    """sum_i p_i max(low - r_i, min(high + r_i, z_i)); the new z_i are kept when store is true."""
    total = 0.0
    for i in range(r.size):
        z = max(low - r[i], min(high + r[i], states[i]))
        if store:
            states[i] = z
        total += p[i] * z
    return total


@numba.njit(cache=True, nogil=True, fastmath=True)
def _tanh(x: float) -> float:
    """tanh through one exp (vectorises; absolute error below 3e-16)."""
    twice = min(max(2.0 * x, -80.0), 80.0)
    growth = np.exp(twice)
    return (growth - 1.0) / (growth + 1.0)


@numba.njit(cache=True, nogil=True)
def _envelope(v: float, scale: float, gain: float, shift: float, offset: float) -> float:
    return scale * _tanh(gain * v + shift) + offset


@numba.njit(cache=True, nogil=True, fastmath=True)
def envelopes(v: np.ndarray, theta: np.ndarray, low: np.ndarray, high: np.ndarray) -> None:
    """gl(v) and gr(v) [output unit] for every sample of v [A], into low and high."""
    for k in range(v.size):
        low[k] = _envelope(v[k], theta[0], theta[1], theta[2], theta[3])
        high[k] = _envelope(v[k], theta[4], theta[5], theta[6], theta[7])


@numba.njit(cache=True, nogil=True)
def play_forward(v: np.ndarray, theta: np.ndarray, r: np.ndarray, p: np.ndarray,
                 states: np.ndarray, out: np.ndarray) -> None:
    """y_k = sum_i p_i z_i, z_i = max(gl(v_k) - r_i, min(gr(v_k) + r_i, z_i)); states updated in place."""
    low = np.empty(v.size)
    high = np.empty(v.size)
    envelopes(v, theta, low, high)
    for k in range(v.size):
        out[k] = _clamp_and_sum(low[k], high[k], r, p, states, True)


@numba.njit(cache=True, nogil=True)
def output_at(v: float, theta: np.ndarray, r: np.ndarray, p: np.ndarray, states: np.ndarray,
               store: bool = False) -> float:
    """The model output for input v [A] from the given operator states."""
    low = _envelope(v, theta[0], theta[1], theta[2], theta[3])
    high = _envelope(v, theta[4], theta[5], theta[6], theta[7])
    return _clamp_and_sum(low, high, r, p, states, store)


@numba.njit(cache=True, nogil=True)
def exact_inverse_step(target: float, v_previous: float, v_low: float, v_high: float,
                       tolerance: float, theta: np.ndarray, r: np.ndarray, p: np.ndarray,
                       states: np.ndarray, result: np.ndarray) -> None:
    """Input v in [v_low, v_high] nearest v_previous whose output from `states` is `target`.

    The output is non-decreasing in v, so the root is bracketed between v_previous and a limit and
    found by the Illinois method with bisection as a safeguard. Writes result = [v, clipped, y]
    and moves `states` to v.
    """
    y_previous = output_at(v_previous, theta, r, p, states)
    clipped = 0.0
    if abs(target - y_previous) <= tolerance:
        v = v_previous
    else:
        if target > y_previous:
            a, fa = v_previous, y_previous - target
            b = v_high
            fb = output_at(b, theta, r, p, states) - target
        else:
            b, fb = v_previous, y_previous - target
            a = v_low
            fa = output_at(a, theta, r, p, states) - target
        if fb < 0.0:
            v = b
            clipped = 1.0
        elif fa > 0.0:
            v = a
            clipped = -1.0
        else:
            v = _illinois(a, fa, b, fb, target, tolerance, theta, r, p, states)
    result[0] = v
    result[1] = clipped
    result[2] = output_at(v, theta, r, p, states, True)


@numba.njit(cache=True, nogil=True)
def _illinois(a: float, fa: float, b: float, fb: float, target: float, tolerance: float,
              theta: np.ndarray, r: np.ndarray, p: np.ndarray, states: np.ndarray) -> float:
    """Root of output(v) - target in [a, b] with fa <= 0 <= fb, to |residual| <= tolerance."""
    side = 0
    for iteration in range(200):
        if fb - fa > 0.0 and iteration % 4 != 3:
            c = b - fb * (b - a) / (fb - fa)
            if not a < c < b:
                c = 0.5 * (a + b)
        else:
            c = 0.5 * (a + b)
        fc = output_at(c, theta, r, p, states) - target
        if abs(fc) <= tolerance or b - a <= 1e-15 * (1.0 + abs(a) + abs(b)):
            return c
        if fc < 0.0:
            a, fa = c, fc
            if side == -1:
                fb *= 0.5
            side = -1
        else:
            b, fb = c, fc
            if side == 1:
                fa *= 0.5
            side = 1
    return 0.5 * (a + b)


@numba.njit(cache=True, nogil=True)
def exact_inverse(targets: np.ndarray, v_start: float, v_low: float, v_high: float, tolerance: float,
                  theta: np.ndarray, r: np.ndarray, p: np.ndarray, states: np.ndarray,
                  v_out: np.ndarray, clipped_out: np.ndarray) -> float:
    """exact_inverse_step over a whole target sequence; returns the last input."""
    result = np.empty(3)
    v = v_start
    for k in range(targets.size):
        exact_inverse_step(targets[k], v, v_low, v_high, tolerance, theta, r, p, states, result)
        v = result[0]
        v_out[k] = v
        clipped_out[k] = result[1]
    return v


@numba.njit(cache=True, nogil=True)
def classical_play_step(x: float, r: np.ndarray, states: np.ndarray) -> None:
    """Classical play operators F_r: z = max(x - r, min(x + r, z)), in place."""
    for j in range(r.size):
        states[j] = max(x - r[j], min(x + r[j], states[j]))


@numba.njit(cache=True, nogil=True)
def _inverse_envelope(u: float, scale: float, gain: float, shift: float, offset: float) -> float:
    """v with scale tanh(gain v + shift) + offset = u; +-inf beyond the envelope's range."""
    argument = (u - offset) / scale
    if argument >= 1.0:
        return np.inf if gain > 0 else -np.inf
    if argument <= -1.0:
        return -np.inf if gain > 0 else np.inf
    return (np.arctanh(argument) - shift) / gain


@numba.njit(cache=True, nogil=True)
def analytic_inverse_step(target: float, state: np.ndarray, v_low: float, v_high: float,
                          theta: np.ndarray, r_hat: np.ndarray, p_hat: np.ndarray,
                          plays: np.ndarray, result: np.ndarray) -> None:
    """One sample of the paper's eqs 6-8; state = [previous target, direction (+1 rising, -1 falling)].

    Writes result = [v, clipped] and updates state and the play states in place.
    """
    if target > state[0]:
        state[1] = 1.0
    elif target < state[0]:
        state[1] = -1.0
    state[0] = target
    classical_play_step(target, r_hat, plays)
    u = 0.0
    for j in range(r_hat.size):
        u += p_hat[j] * plays[j]
    if state[1] > 0:
        v = _inverse_envelope(u, theta[0], theta[1], theta[2], theta[3])
    else:
        v = _inverse_envelope(u, theta[4], theta[5], theta[6], theta[7])
    clipped = 0.0
    if v > v_high:
        v = v_high
        clipped = 1.0
    elif v < v_low:
        v = v_low
        clipped = -1.0
    result[0] = v
    result[1] = clipped


@numba.njit(cache=True, nogil=True)
def analytic_inverse(targets: np.ndarray, state: np.ndarray, v_low: float, v_high: float,
                     theta: np.ndarray, r_hat: np.ndarray, p_hat: np.ndarray, plays: np.ndarray,
                     v_out: np.ndarray, clipped_out: np.ndarray) -> None:
    """analytic_inverse_step over a whole target sequence."""
    result = np.empty(2)
    for k in range(targets.size):
        analytic_inverse_step(targets[k], state, v_low, v_high, theta, r_hat, p_hat, plays, result)
        v_out[k] = result[0]
        clipped_out[k] = result[1]
