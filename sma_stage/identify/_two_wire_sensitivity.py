"""Compiled forward-mode sensitivities of the two-wire model (numba) for its fit's Jacobian.

One pass over a record gives the outputs and d(output)/d(parameter) for every entry of the kernel's parameter
vector (sma_stage.model.two_wire, TwoWireParameters.as_array), by carrying each state's derivative through the
model's recursion beside it (the play operators' derivative is that of the clamp in force, or the one carried,
as in the GPI's sensitivities). A finite-difference Jacobian runs the model once per parameter; this costs a few
runs. The sub-steps a long hold is taken in are held fixed (their lengths follow the slower wire's time
constant, a dependence left out: a record's step of 1 s or less is one sub-step). The rest state's derivative
is taken by central differences of `_rest` (a fixed point of a few hundred cheap iterations, no record).
"""

import math

import numba
import numpy as np

from sma_stage.model.two_wire import (
    COMPACT_ONSET,
    FIRST_SUBSTEP_S,
    FIRST_WEIGHT,
    RESISTANCE_DROP,
    SETTLING_SUBSTEPS,
    SETTLING_TAUS,
    SUBSTEP_GROWTH,
    TENSION_COUPLING,
    _rest,
    transformation_curve,
)

REST_STEP = 1e-6  # the central differences of the rest state, relative to each parameter (absolute near 0)


@numba.njit(cache=True, nogil=True)
def _add_operator_fraction(state: np.ndarray, dstate: np.ndarray, p: np.ndarray, n: int, wire: int, j: int,
                           dfraction: np.ndarray) -> float:
    """The wire's operator j's share of its transformed fraction, weight sigma((z - centre) / width); its
    derivative is added into dfraction."""
    index, weight_index = 2 + wire * n + j, FIRST_WEIGHT + wire * n + j
    weight, width = p[weight_index], p[7 + wire]
    argument = (state[index] - p[5 + wire]) / width
    sigma, dsigma = transformation_curve(argument, p[COMPACT_ONSET])
    slope = weight * dsigma / width
    for c in range(p.size):
        dfraction[c] += slope * dstate[index, c]
    dfraction[5 + wire] -= slope
    dfraction[7 + wire] -= slope * argument
    dfraction[weight_index] += sigma
    return weight * sigma


@numba.njit(cache=True, nogil=True)
def _tangent_substep(state: np.ndarray, dstate: np.ndarray, p: np.ndarray, n: int, m: int, current: float,
                     step_s: float, shares: np.ndarray, dshares: np.ndarray, work: np.ndarray) -> float:
    """The model's _substep with every state's derivative (dstate, one row per state) carried beside it; shares
    and dshares (the wires' transformed shares at the step's start and their derivatives) are replaced by those
    at its end. work: scratch rows (8, parameters). Returns the output at the end."""
    count = p.size
    y_row = 2 + 2 * n + m
    reference = p[2]
    heating = current * current / reference
    y_before = state[y_row]
    dy_before = work[0]
    dy_before[:] = dstate[y_row]
    ddrive, dseen, dfraction, dtotal, dpull = work[1], work[2], work[3], work[4], work[5]
    pull = 0.0
    dpull[:] = 0.0
    coupling = p[TENSION_COUPLING]
    first_shares = (shares[0], shares[1])  # the step's start's: the loop replaces them
    first_dshares = work[6:8]
    first_dshares[:] = dshares
    for wire in range(2):
        drive = 0.0
        ddrive[:] = 0.0
        if (current > 0.0) == (wire == 0) and current != 0.0:
            drive = heating
            ddrive[2] = -heating / reference
            if drive > 0.0 and p[RESISTANCE_DROP] > 0.0:
                factor = 1.0 - p[RESISTANCE_DROP] * shares[wire]
                for c in range(count):
                    ddrive[c] = ddrive[c] * factor - heating * p[RESISTANCE_DROP] * dshares[wire, c]
                ddrive[RESISTANCE_DROP] -= heating * shares[wire]
                drive *= factor
        decay = math.exp(-step_s / p[wire])
        before = state[wire]
        for c in range(count):
            dstate[wire, c] = ddrive[c] * (1.0 - decay) + dstate[wire, c] * decay
        dstate[wire, wire] += (before - drive) * decay * step_s / (p[wire] * p[wire])
        state[wire] = drive + (before - drive) * decay
        sign = 1.0 if wire == 0 else -1.0
        other = 1 - wire
        seen = state[wire] - sign * p[3 + wire] * y_before - coupling * first_shares[other]
        for c in range(count):
            dseen[c] = dstate[wire, c] - sign * p[3 + wire] * dy_before[c] - coupling * first_dshares[other, c]
        dseen[TENSION_COUPLING] -= first_shares[other]
        dseen[3 + wire] -= sign * y_before
        hysteresis = p[9 + wire]
        fraction, total = 0.0, 0.0
        dfraction[:] = 0.0
        dtotal[:] = 0.0
        for j in range(n):
            share_of_width = j / (n - 1) if n > 1 else 0.0
            threshold = hysteresis * share_of_width
            index = 2 + wire * n + j
            if seen - threshold > state[index]:
                state[index] = seen - threshold
                for c in range(count):
                    dstate[index, c] = dseen[c]
                dstate[index, 9 + wire] -= share_of_width
            elif seen + threshold < state[index]:
                state[index] = seen + threshold
                for c in range(count):
                    dstate[index, c] = dseen[c]
                dstate[index, 9 + wire] += share_of_width
            total += p[FIRST_WEIGHT + wire * n + j]
            dtotal[FIRST_WEIGHT + wire * n + j] += 1.0
            fraction += _add_operator_fraction(state, dstate, p, n, wire, j, dfraction)
        if total > 0.0:
            share = fraction / total
            for c in range(count):
                dshares[wire, c] = (dfraction[c] - share * dtotal[c]) / total
        else:
            share = 0.0
            dshares[wire, :] = 0.0
        shares[wire] = share
        stroke = p[11 + wire]
        pull += sign * stroke * fraction
        for c in range(count):
            dpull[c] += sign * stroke * dfraction[c]
        dpull[11 + wire] += sign * fraction
    y = p[13]
    dstate[y_row, :] = 0.0
    dstate[y_row, 13] = 1.0
    for k in range(m):
        share_of_width = k / (m - 1) if m > 1 else 0.0
        threshold = p[14] * share_of_width
        index = 2 + 2 * n + k
        if pull - threshold > state[index]:
            state[index] = pull - threshold
            for c in range(count):
                dstate[index, c] = dpull[c]
            dstate[index, 14] -= share_of_width
        elif pull + threshold < state[index]:
            state[index] = pull + threshold
            for c in range(count):
                dstate[index, c] = dpull[c]
            dstate[index, 14] += share_of_width
        weight_index = FIRST_WEIGHT + 2 * n + k
        weight = p[weight_index]
        y += weight * state[index]
        for c in range(count):
            dstate[y_row, c] += weight * dstate[index, c]
        dstate[y_row, weight_index] += state[index]
    state[y_row] = y
    return y


@numba.njit(cache=True, nogil=True)
def _tangent_advance(state: np.ndarray, dstate: np.ndarray, p: np.ndarray, n: int, m: int, current: float,
                     step_s: float, shares: np.ndarray, dshares: np.ndarray, work: np.ndarray) -> float:
    """The model's _advance_from with the derivatives carried (_tangent_substep), its sub-steps as there."""
    settling_s = SETTLING_TAUS * max(p[0], p[1])
    left, length, growing_after = step_s, max(FIRST_SUBSTEP_S, settling_s / SETTLING_SUBSTEPS), step_s - settling_s
    while True:
        last = left <= length * (1.0 + 1e-9)
        substep = left if last else length
        y = _tangent_substep(state, dstate, p, n, m, current, substep, shares, dshares, work)
        if last:
            return y
        left -= substep
        if left < growing_after:
            length *= SUBSTEP_GROWTH


@numba.njit(cache=True, nogil=True)
def _initial_shares(state: np.ndarray, dstate: np.ndarray, p: np.ndarray, n: int, shares: np.ndarray,
                    dshares: np.ndarray) -> None:
    """The wires' transformed shares of a state (the model's _shares) and their derivatives."""
    count = p.size
    for wire in range(2):
        total, fraction = 0.0, 0.0
        dshares[wire, :] = 0.0
        for j in range(n):
            total += p[FIRST_WEIGHT + wire * n + j]
        if total <= 0.0:
            shares[wire] = 0.0
            continue
        for j in range(n):
            fraction += _add_operator_fraction(state, dstate, p, n, wire, j, dshares[wire])
        share = fraction / total
        for j in range(n):
            dshares[wire, FIRST_WEIGHT + wire * n + j] -= share
        for c in range(count):
            dshares[wire, c] /= total
        shares[wire] = share


@numba.njit(cache=True, nogil=True)
def run_with_sensitivities(t: np.ndarray, u: np.ndarray, p: np.ndarray, n: int, m: int, state: np.ndarray,
                           dstate: np.ndarray, out: np.ndarray, dout: np.ndarray) -> None:
    """The model's _run from `state` (at the first sample; its derivatives dstate, one row per state) with the
    outputs' derivatives: out[k] and dout[k, c] = d out[k] / d p[c]. state and dstate are advanced in place."""
    count = p.size
    shares = np.empty(2)
    dshares = np.empty((2, count))
    work = np.empty((8, count))
    _initial_shares(state, dstate, p, n, shares, dshares)
    y_row = 2 + 2 * n + m
    out[0] = state[y_row]
    dout[0] = dstate[y_row]
    for k in range(1, t.size):
        out[k] = _tangent_advance(state, dstate, p, n, m, u[k - 1], t[k] - t[k - 1], shares, dshares, work)
        dout[k] = dstate[y_row]


@numba.njit(cache=True, nogil=True)
def rest_with_sensitivities(p: np.ndarray, n: int, m: int) -> tuple[np.ndarray, np.ndarray]:
    """The rest state (the model's _rest) and its derivative over p (one row per state), by central differences."""
    size = 3 + 2 * n + m
    state = np.empty(size)
    _rest(p, n, m, state)
    dstate = np.empty((size, p.size))
    above, below = np.empty(size), np.empty(size)
    for c in range(p.size):
        step = REST_STEP * (abs(p[c]) if p[c] != 0.0 else 1.0)
        shifted = p.copy()
        shifted[c] = p[c] + step
        _rest(shifted, n, m, above)
        shifted[c] = p[c] - step
        _rest(shifted, n, m, below)
        dstate[:, c] = (above - below) / (2.0 * step)
    return state, dstate
