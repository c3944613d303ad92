"""Numerical core of the stage simulator: wire thermal model, phase kinetics, force balance (numba).

Everything here works on flat float64 arrays so that one compiled loop serves both the
per-sample `StageSimulator.step` and the batched `simulate`. Indices are named below. Each wire
is cut into nodes along its length (half a wire: the two clamped ends are symmetric), each node
with its own temperature and martensite fractions; the nodes of a wire carry the same stress.
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
P_CONDUCTANCE = 31  # W m/K: thermal conductivity * cross-section
P_NODES = 32  # nodes per half wire
P_AMBIENT_DRIFT_START = 33  # s
P_CREEP_START = 34  # s
N_PARAMETERS = 35

# State vector layout: scalars, then per wire (A = 0, B = 1) three blocks of P_NODES values:
# node temperatures [K], detwinned (strain-carrying) and twinned martensite fractions, from the
# clamp to the middle of the wire.
S_TIME = 0  # s
MIN_THERMAL_STEP_S = 1e-12  # shorter steps leave the temperatures as they are (C/dt would overflow)
S_WIRE_DISPLACEMENT = 1  # m, wire-end displacement u (stage x = lever * u, before creep)
S_CREEP = 2  # m
S_STRESS_A = 3  # Pa (wire B: S_STRESS_A + 1)
S_STRESS_B = 4
S_NODES = 5
K_TEMPERATURE = 0
K_DETWINNED = 1
K_TWINNED = 2

_STRESS_TOL_PA = 1.0  # bracket width at which the Illinois search for a stress stops
_STRESS_PROBE_PA = 1e3  # step from the last stress that gives the local slope
_DISPLACEMENT_TOL_M = 1e-12  # the same for the wire-end displacement
_STRAIN_TOL = 1e-12  # |mean strain - strain| at which a wire's stress is taken (< 0.1 Pa)
_FORCE_TOL_N = 1e-7  # |net force| at which the balance is taken (< 1e-12 m)
_TINY = 1e-12


def state_size(nodes: int) -> int:
    """Length of the state vector for a number of nodes per half wire."""
    return S_NODES + 6 * nodes


@njit(cache=True)
def block(p, wire, kind):
    """Index of the first node of a block (kind K_*) of a wire (0 = A, 1 = B) in the state."""
    return S_NODES + (3 * wire + kind) * int(p[P_NODES])


@njit(cache=True)
def _cosine_step(s: float, lower: float, upper: float) -> float:
    """0 below lower, 1 above upper, a half cosine in between."""
    if s <= lower:
        return 0.0
    if s >= upper:
        return 1.0
    return 0.5 * (1.0 - math.cos(math.pi * (s - lower) / (upper - lower)))


# Rows of a wire's node table (shape (N_ROWS, nodes)), filled once per sub-step: the nodes' new
# temperatures and what the phase kinetics need from the start of the sub-step.
R_TEMPERATURE = 0  # K, at the end of the sub-step
R_HEATING_START = 1  # stress-corrected temperature T - sigma / C_A at the start [K]
R_HEATING_FRACTION = 2  # 1 - cosine step of it over [A_s, A_f]
R_COOLING_START = 3  # T - sigma / C_M at the start [K]
R_COOLING_FRACTION = 4  # cosine step of it over [M_f, M_s]
R_LAST_STRAIN = 5  # [R_LAST_STRAIN, 0]: the strain last solved for in this sub-step
R_LAST_STRESS = 6  # [R_LAST_STRESS, 0]: its stress [Pa]
N_ROWS = 7


@njit(cache=True)
def _prepare(p, s, wire, table):
    """Fill the start-of-sub-step rows of a wire's node table from the state (row R_TEMPERATURE is set)."""
    n = int(p[P_NODES])
    t0 = block(p, wire, K_TEMPERATURE)
    stress0 = s[S_STRESS_A + wire]
    table[R_LAST_STRAIN, 0] = math.nan
    for j in range(n):
        heating = s[t0 + j] - stress0 / p[P_SLOPE_AUSTENITE]
        cooling = s[t0 + j] - stress0 / p[P_SLOPE_MARTENSITE]
        table[R_HEATING_START, j] = heating
        table[R_HEATING_FRACTION, j] = 1.0 - _cosine_step(heating, p[P_AS], p[P_AF])
        table[R_COOLING_START, j] = cooling
        table[R_COOLING_FRACTION, j] = _cosine_step(cooling, p[P_MF], p[P_MS])


@njit(cache=True)
def _phase_update(p, det, twin, table, j, shift_a, shift_m, detwin_share):
    """Martensite fractions (detwinned, twinned) of node j after moving to its new temperature and stress1.

    Cosine kinetics (Liang-Rogers) scaled from the current state (Brinson's turning-point rule),
    in incremental form; stress shifts the transformation temperatures by Clausius-Clapeyron.
    shift_a and shift_m are stress1 / C_A and stress1 / C_M [K]; detwin_share is the cosine step of
    stress1 over [sigma_s, sigma_f].
    """
    temp1 = table[R_TEMPERATURE, j]
    s_a1 = temp1 - shift_a
    if s_a1 > table[R_HEATING_START, j] and s_a1 > p[P_AS]:
        g0 = table[R_HEATING_FRACTION, j]
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
    s_m1 = temp1 - shift_m
    if s_m1 < table[R_COOLING_START, j] and s_m1 < p[P_MS]:
        q0 = table[R_COOLING_FRACTION, j]
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
def _wire_strain(p, s, wire, table, stress):
    """Mean strain of a wire at a stress [Pa], each node's phase moved from the state to its new temperature.

    Brinson's law without thermal expansion per node, stress / E(xi) + eps_L xi_S, averaged over
    the nodes (equal lengths in series).
    """
    n = int(p[P_NODES])
    d0, w0 = block(p, wire, K_DETWINNED), block(p, wire, K_TWINNED)
    share = _cosine_step(stress, p[P_DETWIN_START], p[P_DETWIN_FINISH])
    shift_a, shift_m = stress / p[P_SLOPE_AUSTENITE], stress / p[P_SLOPE_MARTENSITE]
    e_a, e_drop = p[P_E_AUSTENITE], p[P_E_MARTENSITE] - p[P_E_AUSTENITE]
    compliance = 0.0
    recovered = 0.0
    for j in range(n):
        det, twin = _phase_update(p, s[d0 + j], s[w0 + j], table, j, shift_a, shift_m, share)
        compliance += 1.0 / (e_a + (det + twin) * e_drop)
        recovered += det
    return (stress * compliance + p[P_RECOVERY_STRAIN] * recovered) / n


@njit(cache=True)
def _illinois(lo, f_lo, hi, f_hi, p, s, wire, table, strain):
    """Root in [lo, hi] of the increasing f(stress) = mean strain - strain, f_lo < 0 < f_hi (Illinois)."""
    side = 0
    for _ in range(200):
        mid = (lo * f_hi - hi * f_lo) / (f_hi - f_lo)
        if not (lo < mid < hi):
            mid = 0.5 * (lo + hi)
        f_mid = _wire_strain(p, s, wire, table, mid) - strain
        if abs(f_mid) < _STRAIN_TOL:
            return mid
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
    return 0.5 * (lo + hi)


@njit(cache=True)
def _solve_from_zero(p, s, wire, table, strain):
    """_solve_stress on the bracket [0, -E_A f(0)], which holds the root (f rises at least as 1 / E_A)."""
    f_lo = _wire_strain(p, s, wire, table, 0.0) - strain
    if f_lo >= 0.0:
        return 0.0
    hi = -p[P_E_AUSTENITE] * f_lo
    f_hi = _wire_strain(p, s, wire, table, hi) - strain
    if f_hi <= 0.0:
        return hi
    return _illinois(0.0, f_lo, hi, f_hi, p, s, wire, table, strain)


@njit(cache=True)
def _solve_stress(p, s, wire, table, strain):
    """Stress [Pa] of a wire held at a strain, consistent with its nodes' phase kinetics; 0 when slack.

    f(stress) = mean strain - strain is increasing (more stress: less reverse transformation, more
    forward transformation and detwinning, more elastic strain) with a slope of at least 1 / E_A,
    so its root is unique. From the last stress: secant steps lengthened by half, so that they tend to
    pass the root (a step of -E_A f, which reaches or passes it, where the secant would creep), until
    the sign changes; then the Illinois method.
    """
    stiff = p[P_E_AUSTENITE]
    guess = s[S_STRESS_A + wire]
    if guess <= 0.0:
        return _solve_from_zero(p, s, wire, table, strain)
    f_guess = _wire_strain(p, s, wire, table, guess) - strain
    if f_guess == 0.0:
        return guess
    direction = 1.0 if f_guess < 0.0 else -1.0
    probe = max(0.0, guess + direction * _STRESS_PROBE_PA)
    f_probe = _wire_strain(p, s, wire, table, probe) - strain
    x0, f0, x1, f1 = guess, f_guess, probe, f_probe
    for _ in range(60):
        if f1 * f0 <= 0.0 or (x1 == 0.0 and f1 >= 0.0):
            break
        slope = (f1 - f0) / (x1 - x0)
        step = -f1 / slope if slope > 0.0 else -stiff * f1
        if abs(step) < abs(stiff * f1) * 1e-3:
            step = -stiff * f1
        x0, f0 = x1, f1
        x1 = max(0.0, x1 + 1.5 * step)
        f1 = _wire_strain(p, s, wire, table, x1) - strain
    if x1 == 0.0 and f1 >= 0.0:
        return 0.0
    if f1 == 0.0:
        return x1
    if f1 * f0 > 0.0:
        return _solve_from_zero(p, s, wire, table, strain)
    if x1 < x0:
        x0, f0, x1, f1 = x1, f1, x0, f0
    return _illinois(x0, f0, x1, f1, p, s, wire, table, strain)


@njit(cache=True)
def _solve_wire(p, s, wire, table, strain):
    """_solve_stress, remembering the last strain and stress of the sub-step (the commit repeats it)."""
    if table[R_LAST_STRAIN, 0] == strain:
        return table[R_LAST_STRESS, 0]
    stress = _solve_stress(p, s, wire, table, strain)
    table[R_LAST_STRAIN, 0] = strain
    table[R_LAST_STRESS, 0] = stress
    return stress


@njit(cache=True)
def _strains(p, u):
    """Strains of wires A and B at the wire-end displacement u [m]."""
    return p[P_PRESTRAIN_A] - u / p[P_LENGTH_A], p[P_PRESTRAIN_B] + u / p[P_LENGTH_B]


@njit(cache=True)
def _net_force(p, u, s, table_a, table_b, external_n):
    """Net generalised force [N] on the wire-end coordinate u (positive pushes u up)."""
    strain_a, strain_b = _strains(p, u)
    stress_a = _solve_wire(p, s, 0, table_a, strain_a)
    stress_b = _solve_wire(p, s, 1, table_b, strain_b)
    lever = p[P_LEVER]
    return p[P_AREA] * (stress_a - stress_b) + lever * external_n - lever * lever * p[P_SPRING] * u


@njit(cache=True)
def _solve_balance(p, s, table_a, table_b, external_n):
    """Wire-end displacement [m] where the net force vanishes (Illinois).

    The net force falls with u at least as fast as the spring's G^2 k (the wires only add to it),
    so the step f / (G^2 k) from the last displacement reaches or passes the root: a bracket.
    """
    u0 = s[S_WIRE_DISPLACEMENT]
    f0 = _net_force(p, u0, s, table_a, table_b, external_n)
    if f0 == 0.0:
        return u0
    lo, f_lo = u0, f0
    step = f0 / (p[P_LEVER] * p[P_LEVER] * p[P_SPRING])
    hi = u0 + step
    f_hi = _net_force(p, hi, s, table_a, table_b, external_n)
    for _ in range(60):
        if f_hi * f0 <= 0.0:
            break
        lo, f_lo = hi, f_hi
        step *= 2.0
        hi = u0 + step
        f_hi = _net_force(p, hi, s, table_a, table_b, external_n)
    if f_hi == 0.0:
        return hi
    if hi < lo:
        lo, hi, f_lo, f_hi = hi, lo, f_hi, f_lo
    side = 0
    for _ in range(200):
        mid = (lo * f_hi - hi * f_lo) / (f_hi - f_lo)
        if not (lo < mid < hi):
            mid = 0.5 * (lo + hi)
        f_mid = _net_force(p, mid, s, table_a, table_b, external_n)
        if abs(f_mid) < _FORCE_TOL_N:
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
def _commit_wire(p, s, wire, table, strain):
    """Store a wire's stress, node fractions and node temperatures at a strain in the state."""
    stress = _solve_wire(p, s, wire, table, strain)
    n = int(p[P_NODES])
    t0, d0, w0 = block(p, wire, K_TEMPERATURE), block(p, wire, K_DETWINNED), block(p, wire, K_TWINNED)
    share = _cosine_step(stress, p[P_DETWIN_START], p[P_DETWIN_FINISH])
    shift_a, shift_m = stress / p[P_SLOPE_AUSTENITE], stress / p[P_SLOPE_MARTENSITE]
    for j in range(n):
        s[d0 + j], s[w0 + j] = _phase_update(p, s[d0 + j], s[w0 + j], table, j, shift_a, shift_m, share)
        s[t0 + j] = table[R_TEMPERATURE, j]
    s[S_STRESS_A + wire] = stress


@njit(cache=True)
def _commit_balance(p, s, u, table_a, table_b):
    """Store the equilibrium u with the wires' stresses, fractions and temperatures in the state."""
    strain_a, strain_b = _strains(p, u)
    _commit_wire(p, s, 0, table_a, strain_a)
    _commit_wire(p, s, 1, table_b, strain_b)
    s[S_WIRE_DISPLACEMENT] = u


@njit(cache=True)
def _wire_temperatures(p, s, wire, current, ambient, dt, out, work):
    """Node temperatures [K] of a wire after dt [s] (Crank-Nicolson, resistances frozen) into out.

    Per unit length: m c dT/dt = i^2 R(xi) - h pi d (T - T_amb) + k A d2T/dx2, with the clamp at
    T_amb and no heat flow across the middle of the wire (symmetry).
    """
    n = int(p[P_NODES])
    length = p[P_LENGTH_A] if wire == 0 else p[P_LENGTH_B]
    dx = 0.5 * length / n
    link = p[P_CONDUCTANCE] / (dx * dx)
    t0, d0, w0 = block(p, wire, K_TEMPERATURE), block(p, wire, K_DETWINNED), block(p, wire, K_TWINNED)
    if dt < MIN_THERMAL_STEP_S:
        for j in range(n):
            out[j] = s[t0 + j]
        return
    rate = p[P_HEAT_CAPACITY] / dt
    diag = work[:n]
    rhs = out
    for j in range(n):
        xi = s[d0 + j] + s[w0 + j]
        heat = current * current * (p[P_RES_AUSTENITE] + xi * (p[P_RES_MARTENSITE] - p[P_RES_AUSTENITE]))
        links = 0.0
        neighbours = 0.0
        source = heat + p[P_HEAT_LOSS] * ambient
        if j == 0:
            links += 2.0
            source += 2.0 * link * ambient
        else:
            links += 1.0
            neighbours += s[t0 + j - 1]
        if j < n - 1:
            links += 1.0
            neighbours += s[t0 + j + 1]
        loss = p[P_HEAT_LOSS] + links * link
        diag[j] = rate + 0.5 * loss
        rhs[j] = (rate - 0.5 * loss) * s[t0 + j] + 0.5 * link * neighbours + source
    off = -0.5 * link
    for j in range(1, n):
        factor = off / diag[j - 1]
        diag[j] -= factor * off
        rhs[j] -= factor * rhs[j - 1]
    rhs[n - 1] /= diag[n - 1]
    for j in range(n - 2, -1, -1):
        rhs[j] = (rhs[j] - off * rhs[j + 1]) / diag[j]


@njit(cache=True)
def external_force(p, time_s):
    """External force on the stage [N] at time_s (the load-change effect)."""
    return p[P_LOAD_FORCE] if time_s >= p[P_LOAD_TIME] else 0.0


@njit(cache=True)
def stage_position(p, s):
    """Stage position [m]: lever times the wire-end displacement, plus creep."""
    return p[P_LEVER] * s[S_WIRE_DISPLACEMENT] + s[S_CREEP]


@njit(cache=True)
def wire_mean(p, s, wire, kind):
    """Mean over a wire's length of a node quantity (K_TEMPERATURE, or the martensite fraction for K_DETWINNED)."""
    n = int(p[P_NODES])
    start = block(p, wire, kind)
    total = 0.0
    for j in range(n):
        total += s[start + j]
        if kind == K_DETWINNED:
            total += s[start + n + j]
    mean = total / n
    return min(1.0, mean) if kind == K_DETWINNED else mean


@njit(cache=True)
def _advance(p, s, current, dt, table_a, table_b, scratch):
    """Advance the state s in place by dt [s] under a clamped current [A] routed by the relay."""
    n_sub = max(1, int(math.ceil(dt / p[P_MAX_SUBSTEP] - 1e-9)))
    h = dt / n_sub
    current_a = current if current > 0.0 else 0.0
    current_b = -current if current < 0.0 else 0.0
    for _ in range(n_sub):
        t_mid = s[S_TIME] + 0.5 * h
        ambient = p[P_AMBIENT] + p[P_AMBIENT_DRIFT] * max(0.0, t_mid - p[P_AMBIENT_DRIFT_START])
        _wire_temperatures(p, s, 0, current_a, ambient, h, table_a[R_TEMPERATURE], scratch)
        _wire_temperatures(p, s, 1, current_b, ambient, h, table_b[R_TEMPERATURE], scratch)
        _prepare(p, s, 0, table_a)
        _prepare(p, s, 1, table_b)
        s[S_TIME] += h
        load = external_force(p, s[S_TIME])
        u = _solve_balance(p, s, table_a, table_b, load)
        _commit_balance(p, s, u, table_a, table_b)
        if p[P_CREEP_AMPLITUDE] != 0.0 and s[S_TIME] > p[P_CREEP_START]:
            drive = min(1.0, max(-1.0, p[P_LEVER] * u / p[P_CREEP_REFERENCE]))
            target = p[P_CREEP_AMPLITUDE] * drive
            s[S_CREEP] = target + (s[S_CREEP] - target) * math.exp(-h / p[P_CREEP_TAU])


@njit(cache=True)
def settle(p, s):
    """Put the state at rest: both wires at ambient, twinned martensite, loaded to their pre-strain."""
    n = int(p[P_NODES])
    s[:] = 0.0
    table_a, table_b = np.empty((N_ROWS, n)), np.empty((N_ROWS, n))
    for wire in range(2):
        s[block(p, wire, K_TEMPERATURE) : block(p, wire, K_TEMPERATURE) + n] = p[P_AMBIENT]
        s[block(p, wire, K_TWINNED) : block(p, wire, K_TWINNED) + n] = 1.0
    table_a[R_TEMPERATURE, :] = p[P_AMBIENT]
    table_b[R_TEMPERATURE, :] = p[P_AMBIENT]
    _prepare(p, s, 0, table_a)
    _prepare(p, s, 1, table_b)
    u = _solve_balance(p, s, table_a, table_b, external_force(p, 0.0))
    _commit_balance(p, s, u, table_a, table_b)


@njit(cache=True)
def run(p, s, currents, dt, out_position, out_temps, out_fractions, out_time):
    """Apply each current [A] for dt [s] in turn; write the state after each step into the outputs.

    Temperatures and martensite fractions are written as means over each wire's length.
    """
    limit = p[P_MAX_CURRENT]
    n = int(p[P_NODES])
    table_a, table_b, scratch = np.empty((N_ROWS, n)), np.empty((N_ROWS, n)), np.empty(n)
    for k in range(currents.shape[0]):
        current = min(limit, max(-limit, currents[k]))
        _advance(p, s, current, dt, table_a, table_b, scratch)
        out_time[k] = s[S_TIME]
        out_position[k] = stage_position(p, s)
        for wire in range(2):
            out_temps[k, wire] = wire_mean(p, s, wire, K_TEMPERATURE)
            out_fractions[k, wire] = wire_mean(p, s, wire, K_DETWINNED)


def new_state(p: np.ndarray) -> np.ndarray:
    """An empty state vector for the parameters p (call settle to fill it)."""
    return np.zeros(state_size(int(p[P_NODES])))
