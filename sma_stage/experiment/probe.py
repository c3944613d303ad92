"""The probe: a short experiment that measures, from the stage itself, each wire's working band (the currents
where heating starts and stops moving the stage) and the wires' thermal time constant. Wire a is heated by a
positive current, wire b by a negative one.

The schedule: each wire in turn climbs a staircase of held currents (STAIRS, fractions of the current limit),
then both rest at zero (REST_SHARE of the duration). A held current relaxes the wire's temperature towards its
steady value along one exponential, and the position follows it: each hold's position is fitted with
c + a exp(-t / tau), which gives the time constant tau (the median over the holds that moved the stage) and the
position the hold was heading for (c: the static position at that current, even when a hold is shorter than the
lag). The band is where that static position crosses EDGE and 1 - EDGE of the wire's travel."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from sma_stage.errors import InputError
from sma_stage.model.checks import as_signal, checked_record

PROBE_SHARE = 0.10  # of an excitation's duration, by default
MIN_PROBE_S = 40.0
STAIRS = (0.4, 0.55, 0.7, 0.85, 1.0)  # held currents, fractions of the current limit
REST_SHARE = 0.10  # of the probe's duration, after each wire's staircase
TIME_CONSTANTS_S = np.geomspace(0.2, 200.0, 151)
EDGE = 0.05  # of a wire's travel: where its band starts and ends
MIN_TRAVEL_SHARE = 0.05  # of the probe's output span: a wire that moves the stage less does not move it
MIN_HOLD_MOTION = 0.05  # of the wire's travel: a hold that moves the stage less says nothing of the lag
NOISE_MULTIPLE = 10.0  # a motion smaller than this many times the sensor's noise is no motion
MIN_HOLD_SAMPLES = 4
LEVEL_TOLERANCE = 0.02  # of the current limit: a recorded current this close to a held one is that hold
WIRES = ("a", "b")


@dataclass(frozen=True)
class WireBand:
    """What one wire does: heating moves the stage from start_a to end_a [A] (the static currents where its
    position crosses EDGE and 1 - EDGE of its travel); travel [output units], the static motion from rest to the
    current limit, signed; the held currents [A] and the static positions they were heading for. resolved: False
    when the lowest held current already moved the stage past EDGE, so that start_a, interpolated from rest, only
    says the start lies below that current."""

    wire: str
    moves: bool
    travel: float
    start_a: float
    end_a: float
    held_a: tuple[float, ...]
    static: tuple[float, ...]
    resolved: bool = True


@dataclass(frozen=True)
class ProbeResult:
    """What a probe found: the current limit [A], the thermal time constant [s] and each wire's band."""

    max_current_a: float
    time_constant_s: float
    wires: tuple[WireBand, WireBand]

    def as_dict(self) -> dict:
        """The result as a dict for a report (a wire that does not move has NaN edges: strict_json writes null)."""
        return asdict(self)

    def summary(self) -> str:
        """One line for a log."""
        parts = [f"time constant {self.time_constant_s:.1f} s"]
        for band in self.wires:
            if band.moves and not band.resolved:
                parts.append(f"wire {band.wire} moves the stage from below {band.held_a[0]:.2f} A (its lowest held "
                             f"current already moved it; a probe to a lower current limit finds where) to "
                             f"{band.end_a:.2f} A")
            elif band.moves:
                parts.append(f"wire {band.wire} moves the stage from {band.start_a:.2f} A to {band.end_a:.2f} A")
            else:
                parts.append(f"wire {band.wire} does not move the stage up to {self.max_current_a:g} A")
        return "; ".join(parts)


def _hold_s(duration_s: float) -> float:
    return duration_s * (1.0 - 2 * REST_SHARE) / (2 * len(STAIRS))


def probe_schedule(max_current_a: float, duration_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Breakpoints (times [s], currents [A]) of the probe: held currents, each a step (two breakpoints at one
    time)."""
    hold, rest = _hold_s(duration_s), REST_SHARE * duration_s
    times, levels, start = [], [], 0.0
    for sign in (1.0, -1.0):
        for fraction in STAIRS:
            times.extend([start, start + hold])
            levels.extend([sign * fraction * max_current_a] * 2)
            start += hold
        times.extend([start, start + rest])
        levels.extend([0.0, 0.0])
        start += rest
    return np.array(times), np.array(levels)


def probe_signal(t: np.ndarray, max_current_a: float, duration_s: float) -> np.ndarray:
    """The probe's current [A] at times t [s] from its start; zero outside [0, duration_s)."""
    t = np.asarray(t, dtype=float)
    times, levels = probe_schedule(max_current_a, duration_s)
    index = np.clip(np.searchsorted(times, t, side="right") - 1, 0, times.size - 1)
    return np.where((t >= 0.0) & (t < duration_s), levels[index], 0.0)


def probe_duration_s(excitation_s: float) -> float:
    """The probe's default duration [s] for an excitation of excitation_s [s]: PROBE_SHARE of it, at least
    MIN_PROBE_S but never more than half of it."""
    return max(PROBE_SHARE * excitation_s, min(MIN_PROBE_S, 0.5 * excitation_s))


def _exponential_fit(elapsed: np.ndarray, y: np.ndarray, time_constant_s: float) -> tuple[float, float]:
    """(squared error, final value c) of the least-squares fit y = c + a exp(-elapsed / time_constant_s)."""
    basis = np.c_[np.ones_like(elapsed), np.exp(-elapsed / time_constant_s)]
    coefficients, *_ = np.linalg.lstsq(basis, y, rcond=None)
    return float(np.sum((basis @ coefficients - y) ** 2)), float(coefficients[0])


def fit_relaxation(t: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """(time constant [s], RMS residual) of the y(t) = c + a exp(-(t - t[0]) / tau) that fits best, over
    TIME_CONSTANTS_S."""
    costs = [_exponential_fit(t - t[0], y, tau)[0] for tau in TIME_CONSTANTS_S]
    best = int(np.argmin(costs))
    return float(TIME_CONSTANTS_S[best]), float(np.sqrt(costs[best] / y.size))


def _longest_run(mask: np.ndarray, after: int = 0) -> slice | None:
    """The longest run of True in mask starting at or after index `after` (None: none)."""
    padded = np.r_[False, mask[after:], False].astype(np.int8)
    edges = np.flatnonzero(np.diff(padded))
    if edges.size == 0:
        return None
    starts, ends = edges[::2], edges[1::2]
    longest = int(np.argmax(ends - starts))
    return slice(after + int(starts[longest]), after + int(ends[longest]))


def _segments(u: np.ndarray, limit: float) -> list[tuple[int, float, slice]]:
    """(wire, held current as a fraction of the limit, samples) of every hold, wire a's then wire b's, then the
    rest between them (wire -1), found from the recorded current (the longest run at each held current, so that a
    stage clock that ran slow or fast moves nothing); each slice leaves out the run's first sample (the position
    before the step). InputError naming a held current the record does not hold for MIN_HOLD_SAMPLES samples."""
    found, after = [], 0
    for wire, sign in ((0, 1.0), (1, -1.0)):
        for fraction in STAIRS:
            run = _longest_run(np.abs(u - sign * fraction * limit) <= LEVEL_TOLERANCE * limit, after)
            if run is None or run.stop - run.start < MIN_HOLD_SAMPLES:
                raise InputError(f"not a probe record: no hold of {MIN_HOLD_SAMPLES} samples at "
                                 f"{sign * fraction * limit:g} A "
                                 "(write one with gpi_tool excitation probe)")
            found.append((wire, fraction, slice(run.start + 1, run.stop)))
            after = run.stop
        if wire == 0:  # the rest at 0 A right after wire a's last hold
            resting = np.abs(u[after:]) <= LEVEL_TOLERANCE * limit
            length = resting.size if resting.all() else int(np.argmax(~resting))
            found.append((-1, 0.0, slice(after + 1, after + length)))
    return found


def _crossing(currents: np.ndarray, travelled: np.ndarray, fraction: float) -> float:
    """The current [A] where the static travel (fractions, from 0 at rest) first reaches fraction, linear
    between the held currents."""
    above = np.flatnonzero(travelled >= fraction)
    k = int(above[0]) if above.size else travelled.size - 1
    if k == 0:
        return float(currents[0])
    share = np.clip((fraction - travelled[k - 1]) / max(travelled[k] - travelled[k - 1], 1e-12), 0.0, 1.0)
    return float(currents[k - 1] + share * (currents[k] - currents[k - 1]))


def _band(name: str, currents: np.ndarray, static: np.ndarray, least: float) -> WireBand:
    """A wire's band from its static positions at rest (first) and at each held current [A] (then); it moves
    the stage when it travels at least `least`."""
    travel = float(static[-1] - static[0])
    moves = least > 0.0 and abs(travel) >= least
    held = tuple(float(value) for value in currents[1:])
    if not moves:
        return WireBand(name, False, travel, np.nan, np.nan, held, tuple(float(value) for value in static[1:]))
    travelled = np.maximum.accumulate((static - static[0]) / travel)
    return WireBand(name, True, travel, _crossing(currents, travelled, EDGE), _crossing(currents, travelled, 1 - EDGE),
                    held, tuple(float(value) for value in static[1:]), bool(travelled[1] < EDGE))


def analyse_probe(t: np.ndarray, u: np.ndarray, y: np.ndarray) -> ProbeResult:
    """What a recorded probe (time [s], current [A], output) found; InputError in one line when the record is not
    a probe (no hold of MIN_HOLD_SAMPLES samples at one of its held currents, STAIRS of the record's largest current) or neither
    wire moved the stage."""
    t, u = checked_record(t, u)
    y = as_signal(y, "output")
    if y.size != t.size:
        raise InputError(f"time and output differ in length ({t.size} and {y.size} samples)")
    t = t - t[0]
    limit = float(np.max(np.abs(u)))
    if limit <= 0.0:
        raise InputError("the probe record's current is zero throughout")
    segments = _segments(u, limit)
    holds = [(wire, fraction, part) for wire, fraction, part in segments if wire >= 0]
    relaxations = [fit_relaxation(t[part], y[part]) for _, _, part in holds]
    span = float(np.ptp(y))
    noise = NOISE_MULTIPLE * float(np.median([residual for _, residual in relaxations]))  # the sensor's, per sample
    moving = [number for number, (_, _, part) in enumerate(holds)
              if float(np.ptp(y[part])) >= max(MIN_HOLD_MOTION * span, noise)]
    if not moving:
        raise InputError(f"the probe did not move the stage: no held current up to {limit:g} A moved it over "
                         f"{100 * MIN_HOLD_MOTION:g} % of the record's span (is the stage powered, the sensor read?)")
    time_constant_s = float(np.median([relaxations[number][0] for number in moving]))

    def final(part: slice) -> float:
        """Where the position was heading over these samples (the last one's value when there are too few)."""
        if part.stop - part.start < 3:
            return float(y[part.stop - 1])
        return _exponential_fit(t[part] - t[part][0], y[part], time_constant_s)[1]

    rest = next(part for wire, _, part in segments if wire < 0)
    at_rest = (float(y[holds[0][2].start - 1]), final(rest))  # before wire a's first hold; where the rest went
    wires = []
    for wire, name in enumerate(WIRES):
        chosen = [(fraction, part) for owner, fraction, part in holds if owner == wire]
        currents = np.array([0.0] + [fraction * limit for fraction, _ in chosen])
        static = np.array([at_rest[wire]] + [final(part) for _, part in chosen])
        wires.append(_band(name, currents, static, max(MIN_TRAVEL_SHARE * span, noise)))
    if not any(band.moves for band in wires):
        raise InputError(f"the probe did not move the stage: neither wire moved it over {100 * MIN_TRAVEL_SHARE:g} % "
                         f"of the record's span up to {limit:g} A (is the stage powered, the sensor read?)")
    return ProbeResult(limit, time_constant_s, (wires[0], wires[1]))
