"""Numerical core of the stage simulator: wire thermal model, phase kinetics, force balance (numba).

Everything here works on flat float64 arrays so that one compiled loop serves both the
per-sample `StageSimulator.step` and the batched `simulate`. Indices are named below.
"""

import math

import numpy as np
from numba import njit

# Parameter vector layout (built by config.pack_parameters).
P_HEAT_CAPACITY = 0  # J/(K m): density * specific heat * cross-section
P_HEAT_LOSS = 1  # W/(K m): convection coefficient * perimeter
P_RES_MARTENSITE = 2  # Ohm/m
P_RES_AUSTENITE = 3  # Ohm/m
P_E_AUSTENITE = 4  # Pa
P_E_MARTENSITE = 5  # Pa
P_RECOVERY_STRAIN = 6
P_DETWIN_START = 7  # Pa
P_DETWIN_FINISH = 8  # Pa
P_SLOPE_AUSTENITE = 9  # Pa/K
P_SLOPE_MARTENSITE = 10  # Pa/K
P_MF = 11  # K
P_MS = 12
P_AS = 13
P_AF = 14
P_AREA = 15  # m^2
P_LENGTH_A = 16  # m
P_LENGTH_B = 17
P_PRESTRAIN_A = 18
P_PRESTRAIN_B = 19
P_LEVER = 20  # stage displacement / wire-end displacement
P_SPRING = 21  # N/m at the stage
P_AMBIENT = 22  # K
P_MAX_CURRENT = 23  # A
P_MAX_SUBSTEP = 24  # s
P_AMBIENT_DRIFT = 25  # K/s
P_CREEP_AMPLITUDE = 26  # m
P_CREEP_TAU = 27  # s
P_CREEP_REFERENCE = 28  # m
P_LOAD_FORCE = 29  # N
P_LOAD_TIME = 30  # s
N_PARAMETERS = 31

# State vector layout.
S_TIME = 0  # s
S_WIRE_DISPLACEMENT = 1  # m, wire-end displacement u (stage x = lever * u, before creep)
S_CREEP = 2  # m
S_TEMP_A = 3  # K
S_TEMP_B = 4
S_DETWINNED_A = 5  # detwinned (strain-carrying) martensite fraction
S_TWINNED_A = 6
S_DETWINNED_B = 7
S_TWINNED_B = 8
S_STRESS_A = 9  # Pa
S_STRESS_B = 10
N_STATE = 11

_STRESS_TOL_PA = 0.05
_DISPLACEMENT_TOL_M = 1e-13
_TINY = 1e-12


@njit(cache=True)
def _cosine_step(s: float, lower: float, upper: float) -> float:
    """0 below lower, 1 above upper, a half cosine in between."""
    if s <= lower:
        return 0.0
    if s >= upper:
        return 1.0
    return 0.5 * (1.0 - math.cos(math.pi * (s - lower) / (upper - lower)))


@njit(cache=True)
def _phase_update(p, det0, twin0, temp0, stress0, temp1, stress1):
    """Martensite fractions (detwinned, twinned) after moving from (temp0, stress0) to (temp1, stress1).

    Cosine kinetics (Liang-Rogers) scaled from the current state (Brinson's turning-point rule),
    in incremental form; stress shifts the transformation temperatures by Clausius-Clapeyron.
    """
    det = det0
    twin = twin0
    s_a0 = temp0 - stress0 / p[P_SLOPE_AUSTENITE]
    s_a1 = temp1 - stress1 / p[P_SLOPE_AUSTENITE]
    if s_a1 > s_a0:
        g0 = 1.0 - _cosine_step(s_a0, p[P_AS], p[P_AF])
        g1 = 1.0 - _cosine_step(s_a1, p[P_AS], p[P_AF])
        xi = det + twin
        if g0 > _TINY:
            factor = g1 / g0
        elif xi > g1:
            factor = g1 / xi
        else:
            factor = 1.0
        det *= factor
        twin *= factor
    s_m0 = temp0 - stress0 / p[P_SLOPE_MARTENSITE]
    s_m1 = temp1 - stress1 / p[P_SLOPE_MARTENSITE]
    detwin_share = _cosine_step(stress1, p[P_DETWIN_START], p[P_DETWIN_FINISH])
    if s_m1 < s_m0:
        q0 = _cosine_step(s_m0, p[P_MF], p[P_MS])
        q1 = _cosine_step(s_m1, p[P_MF], p[P_MS])
        xi = det + twin
        if q0 > _TINY:
            xi_new = 1.0 - (1.0 - xi) * q1 / q0
        else:
            xi_new = max(xi, 1.0 - q1)
        grown = xi_new - xi
        det += detwin_share * grown
        twin += (1.0 - detwin_share) * grown
    xi = det + twin
    if det < detwin_share * xi:
        det = detwin_share * xi
        twin = xi - det
    return det, twin


@njit(cache=True)
def _wire_stress_for(p, strain, det, twin):
    """Wire stress [Pa] for a strain and phase: E(xi) (strain - eps_L xi_S), zero when slack."""
    modulus = p[P_E_AUSTENITE] + (det + twin) * (p[P_E_MARTENSITE] - p[P_E_AUSTENITE])
    return max(0.0, modulus * (strain - p[P_RECOVERY_STRAIN] * det))


@njit(cache=True)
def _solve_wire(p, strain, det0, twin0, temp0, stress0, temp1):
    """Stress [Pa] and fractions of one wire at a strain, consistent with its phase kinetics.

    Solves sigma = G(sigma), G non-increasing, by the Illinois method on [0, G(0)].
    """
    det, twin = _phase_update(p, det0, twin0, temp0, stress0, temp1, 0.0)
    upper = _wire_stress_for(p, strain, det, twin)
    if upper <= 0.0:
        return 0.0, det, twin
    lo, f_lo = 0.0, -upper
    det, twin = _phase_update(p, det0, twin0, temp0, stress0, temp1, upper)
    hi = upper
    f_hi = upper - _wire_stress_for(p, strain, det, twin)
    if f_hi <= 0.0:
        return upper, det, twin
    side = 0
    for _ in range(200):
        mid = (lo * f_hi - hi * f_lo) / (f_hi - f_lo)
        if not (lo < mid < hi):
            mid = 0.5 * (lo + hi)
        det, twin = _phase_update(p, det0, twin0, temp0, stress0, temp1, mid)
        f_mid = mid - _wire_stress_for(p, strain, det, twin)
        if f_mid == 0.0:
            return mid, det, twin
        if f_mid < 0.0:
            lo, f_lo = mid, f_mid
            if side == -1:
                f_hi *= 0.5
            side = -1
        else:
            hi, f_hi = mid, f_mid
            if side == 1:
                f_lo *= 0.5
            side = 1
        if hi - lo < _STRESS_TOL_PA:
            break
    stress = 0.5 * (lo + hi)
    det, twin = _phase_update(p, det0, twin0, temp0, stress0, temp1, stress)
    return stress, det, twin


@njit(cache=True)
def _net_force(p, u, s, temp_a, temp_b, external_n):
    """Net generalised force [N] on the wire-end coordinate u (positive pushes u up), and wire stresses."""
    strain_a = p[P_PRESTRAIN_A] - u / p[P_LENGTH_A]
    strain_b = p[P_PRESTRAIN_B] + u / p[P_LENGTH_B]
    stress_a, _, _ = _solve_wire(
        p, strain_a, s[S_DETWINNED_A], s[S_TWINNED_A], s[S_TEMP_A], s[S_STRESS_A], temp_a
    )
    stress_b, _, _ = _solve_wire(
        p, strain_b, s[S_DETWINNED_B], s[S_TWINNED_B], s[S_TEMP_B], s[S_STRESS_B], temp_b
    )
    lever = p[P_LEVER]
    return p[P_AREA] * (stress_a - stress_b) + lever * external_n - lever * lever * p[P_SPRING] * u


@njit(cache=True)
def _solve_balance(p, s, temp_a, temp_b, external_n):
    """Wire-end displacement [m] where the net force vanishes (bracket from the last one, Illinois)."""
    u0 = s[S_WIRE_DISPLACEMENT]
    f0 = _net_force(p, u0, s, temp_a, temp_b, external_n)
    if f0 == 0.0:
        return u0
    direction = 1.0 if f0 > 0.0 else -1.0
    step = 1e-6
    lo, f_lo = u0, f0
    hi = u0 + direction * step
    f_hi = _net_force(p, hi, s, temp_a, temp_b, external_n)
    for _ in range(60):
        if f_hi * f0 <= 0.0:
            break
        lo, f_lo = hi, f_hi
        step *= 4.0
        hi = u0 + direction * step
        f_hi = _net_force(p, hi, s, temp_a, temp_b, external_n)
    if hi < lo:
        lo, hi, f_lo, f_hi = hi, lo, f_hi, f_lo
    side = 0
    for _ in range(200):
        mid = (lo * f_hi - hi * f_lo) / (f_hi - f_lo)
        if not (lo < mid < hi):
            mid = 0.5 * (lo + hi)
        f_mid = _net_force(p, mid, s, temp_a, temp_b, external_n)
        if f_mid == 0.0:
            return mid
        if f_mid > 0.0:
            lo, f_lo = mid, f_mid
            if side == -1:
                f_hi *= 0.5
            side = -1
        else:
            hi, f_hi = mid, f_mid
            if side == 1:
                f_lo *= 0.5
            side = 1
        if hi - lo < _DISPLACEMENT_TOL_M:
            break
    return 0.5 * (lo + hi)


@njit(cache=True)
def _commit_balance(p, s, u, temp_a, temp_b):
    """Store the equilibrium u with the wires' stresses, fractions and temperatures in the state."""
    strain_a = p[P_PRESTRAIN_A] - u / p[P_LENGTH_A]
    strain_b = p[P_PRESTRAIN_B] + u / p[P_LENGTH_B]
    stress_a, det_a, twin_a = _solve_wire(
        p, strain_a, s[S_DETWINNED_A], s[S_TWINNED_A], s[S_TEMP_A], s[S_STRESS_A], temp_a
    )
    stress_b, det_b, twin_b = _solve_wire(
        p, strain_b, s[S_DETWINNED_B], s[S_TWINNED_B], s[S_TEMP_B], s[S_STRESS_B], temp_b
    )
    s[S_WIRE_DISPLACEMENT] = u
    s[S_TEMP_A] = temp_a
    s[S_TEMP_B] = temp_b
    s[S_DETWINNED_A] = det_a
    s[S_TWINNED_A] = twin_a
    s[S_DETWINNED_B] = det_b
    s[S_TWINNED_B] = twin_b
    s[S_STRESS_A] = stress_a
    s[S_STRESS_B] = stress_b


@njit(cache=True)
def _wire_temperature(p, temp, current, xi, ambient, dt):
    """Exact exponential update of m c dT/dt = i^2 R(xi) - h A (T - T_amb) over dt [s], R frozen."""
    resistance = p[P_RES_AUSTENITE] + xi * (p[P_RES_MARTENSITE] - p[P_RES_AUSTENITE])
    steady = ambient + current * current * resistance / p[P_HEAT_LOSS]
    return steady + (temp - steady) * math.exp(-dt * p[P_HEAT_LOSS] / p[P_HEAT_CAPACITY])


@njit(cache=True)
def external_force(p, time_s):
    """External force on the stage [N] at time_s (the load-change effect)."""
    return p[P_LOAD_FORCE] if time_s >= p[P_LOAD_TIME] else 0.0


@njit(cache=True)
def stage_position(p, s):
    """Stage position [m]: lever times the wire-end displacement, plus creep."""
    return p[P_LEVER] * s[S_WIRE_DISPLACEMENT] + s[S_CREEP]


@njit(cache=True)
def _advance(p, s, current, dt):
    """Advance the state s in place by dt [s] under a clamped current [A] routed by the relay."""
    n_sub = max(1, int(math.ceil(dt / p[P_MAX_SUBSTEP] - 1e-9)))
    h = dt / n_sub
    current_a = current if current > 0.0 else 0.0
    current_b = -current if current < 0.0 else 0.0
    for _ in range(n_sub):
        t_mid = s[S_TIME] + 0.5 * h
        ambient = p[P_AMBIENT] + p[P_AMBIENT_DRIFT] * t_mid
        xi_a = s[S_DETWINNED_A] + s[S_TWINNED_A]
        xi_b = s[S_DETWINNED_B] + s[S_TWINNED_B]
        temp_a = _wire_temperature(p, s[S_TEMP_A], current_a, xi_a, ambient, h)
        temp_b = _wire_temperature(p, s[S_TEMP_B], current_b, xi_b, ambient, h)
        s[S_TIME] += h
        load = external_force(p, s[S_TIME])
        u = _solve_balance(p, s, temp_a, temp_b, load)
        _commit_balance(p, s, u, temp_a, temp_b)
        if p[P_CREEP_AMPLITUDE] != 0.0:
            drive = min(1.0, max(-1.0, p[P_LEVER] * u / p[P_CREEP_REFERENCE]))
            target = p[P_CREEP_AMPLITUDE] * drive
            s[S_CREEP] = target + (s[S_CREEP] - target) * math.exp(-h / p[P_CREEP_TAU])


@njit(cache=True)
def settle(p, s):
    """Put the state at rest: both wires at ambient, twinned martensite, loaded to their pre-strain."""
    s[:] = 0.0
    s[S_TEMP_A] = p[P_AMBIENT]
    s[S_TEMP_B] = p[P_AMBIENT]
    s[S_TWINNED_A] = 1.0
    s[S_TWINNED_B] = 1.0
    u = _solve_balance(p, s, p[P_AMBIENT], p[P_AMBIENT], external_force(p, 0.0))
    _commit_balance(p, s, u, p[P_AMBIENT], p[P_AMBIENT])


@njit(cache=True)
def run(p, s, currents, dt, out_position, out_temps, out_fractions, out_time):
    """Apply each current [A] for dt [s] in turn; write the state after each step into the outputs."""
    limit = p[P_MAX_CURRENT]
    for k in range(currents.shape[0]):
        current = min(limit, max(-limit, currents[k]))
        _advance(p, s, current, dt)
        out_time[k] = s[S_TIME]
        out_position[k] = stage_position(p, s)
        out_temps[k, 0] = s[S_TEMP_A]
        out_temps[k, 1] = s[S_TEMP_B]
        out_fractions[k, 0] = s[S_DETWINNED_A] + s[S_TWINNED_A]
        out_fractions[k, 1] = s[S_DETWINNED_B] + s[S_TWINNED_B]


def new_state() -> np.ndarray:
    """An empty state vector (call settle to fill it)."""
    return np.zeros(N_STATE)
