"""The identification excitation designed from a probe: first-order reversal curves of each wire over the band
the probe found (peaks spread over the band and a little beyond, reversals at many depths, half of them with an
inner loop), holds sized to the measured time constant, ramps at rates from steps to slow ramps so that the
rate effect shows, runs of held levels reached by steps on either wire (as a positioning loop commands), and
passes from one wire to the other either through a cooling rest or directly. Deterministic by
seed; the peaks and the reversal depths are stratified, so that every draw covers the band."""

from __future__ import annotations

import numpy as np

from sma_stage.errors import InputError
from sma_stage.experiment.probe import ProbeResult, WireBand
from sma_stage.signals import joined_by_raised_cosines

PEAK_STRATA = 5  # each wire's peaks: one per stratum of its band, in a shuffled order, round after round
DEPTH_STRATA = 4  # reversal depths (fractions of the peak) likewise
DEPTHS = (0.1, 0.9)  # reversals this far down from the peak to where the return ends (return_end_a)
BEYOND_BAND = 0.2  # peaks reach this share of the band's width above its end (within the limit)
BELOW_BAND = 0.8  # the current jumps quickly to this fraction of the band's start: below it nothing moves
HOLD_TAUS = (1.0, 2.5)  # a hold at a peak or a reversal: this many time constants (uniform)
INNER_HOLD_TAUS = (0.7, 1.5)
COOL_TAUS = (2.0, 3.5)  # a rest at zero current between wires
RAMP_TAUS = (0.05, 5.0)  # a ramp over the band takes this many time constants (log-uniform): steps to slow ramps
INNER_LOOP_SHARE = 0.5
DIRECT_SHARE = 0.4  # of the passes to the other wire: directly, without a cooling rest
STEP_RUN_SHARE = 0.35  # of the reversal curves: followed by a run of held levels reached by steps, either wire
STEP_RUN_LEVELS = (2, 4)  # levels in a run (uniform, the upper bound excluded)
MIN_STEP_S = 0.5


class _Draw:
    """Stratified draws of one quantity: each stratum once per round, in a shuffled order."""

    def __init__(self, rng: np.random.Generator, strata: int) -> None:
        self.rng, self.strata, self.left = rng, strata, []

    def next(self) -> float:
        """A fraction in [0, 1)."""
        if not self.left:
            self.left = list(self.rng.permutation(self.strata))
        return (self.left.pop() + self.rng.uniform()) / self.strata


def _width(band: WireBand, limit: float) -> float:
    return max(band.end_a - band.start_a, 0.05 * limit)


def peak_range(band: WireBand, limit: float) -> tuple[float, float]:
    """The currents [A] a reversal curve's peak is drawn between: from a fifth into the wire's band to
    BEYOND_BAND of its width above the band's end, within the limit [A]."""
    width = _width(band, limit)
    return min(band.start_a + 0.2 * width, limit), min(band.end_a + BEYOND_BAND * width, limit)


def return_end_a(band: WireBand, limit: float) -> float:
    """Where a cooling wire has returned [A]: the cooling branch lies below the heating one by about the band's
    width (the probe climbs only; on the physical plants the return ends 0.8-2 A below the band's start), so
    reversals below this say little more."""
    return max(band.start_a - _width(band, limit), 0.0)


def design_schedule(probe: ProbeResult, duration_s: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Breakpoints (times [s], currents [A]) of the designed excitation over duration_s [s] for the stage the
    probe measured; InputError when the probe found no wire that moves the stage."""
    wires = [(1.0 if band.wire == "a" else -1.0, band) for band in probe.wires if band.moves]
    if not wires:
        raise InputError("the probe found no wire that moves the stage: nothing to design an excitation on")
    if not 0.0 < duration_s < np.inf:
        raise InputError(f"the excitation's duration must be positive and finite, got {duration_s:g} s")
    tau = probe.time_constant_s if np.isfinite(probe.time_constant_s) else 5.0
    limit = probe.max_current_a
    rng = np.random.default_rng(seed)
    peaks = [_Draw(rng, PEAK_STRATA) for _ in wires]
    depths = [_Draw(rng, DEPTH_STRATA) for _ in wires]
    times, levels = [0.0], [0.0]

    def go(level: float, move_s: float, hold_s: float) -> None:
        times.extend([times[-1] + max(move_s, MIN_STEP_S), times[-1] + max(move_s, MIN_STEP_S) + hold_s])
        levels.extend([level, level])

    def ramp_s(span_a: float, band: WireBand) -> float:
        width = _width(band, limit)
        return tau * float(np.exp(rng.uniform(*np.log(RAMP_TAUS)))) * min(abs(span_a) / width, 2.0)

    turn = 0
    while times[-1] < duration_s:
        number = turn % len(wires)
        sign, band = wires[number]
        low, high = peak_range(band, limit)
        peak = low + (high - low) * peaks[number].next()
        below = BELOW_BAND * band.start_a
        if abs(levels[-1]) < below or np.sign(levels[-1]) != sign:
            go(sign * below, MIN_STEP_S + 0.2 * tau, 0.0)
        go(sign * peak, ramp_s(peak - below, band), tau * rng.uniform(*HOLD_TAUS))
        bottom = min(return_end_a(band, limit), peak)
        reversal = peak - (peak - bottom) * (DEPTHS[0] + (DEPTHS[1] - DEPTHS[0]) * depths[number].next())
        go(sign * reversal, ramp_s(peak - reversal, band), tau * rng.uniform(*HOLD_TAUS))
        if rng.uniform() < INNER_LOOP_SHARE:
            inner = reversal + (peak - reversal) * rng.uniform(0.3, 0.8)
            go(sign * inner, ramp_s(inner - reversal, band), tau * rng.uniform(*INNER_HOLD_TAUS))
        if rng.uniform() < STEP_RUN_SHARE:
            for _ in range(rng.integers(*STEP_RUN_LEVELS)):
                sign, band = wires[rng.integers(len(wires))]
                level = rng.uniform(return_end_a(band, limit), peak_range(band, limit)[1])
                go(sign * level, MIN_STEP_S, tau * rng.uniform(*HOLD_TAUS))
        if len(wires) == 1 or rng.uniform() >= DIRECT_SHARE:
            go(0.0, ramp_s(levels[-1], band), tau * rng.uniform(*COOL_TAUS))
        turn += 1
    times, levels = np.array(times), np.array(levels)
    keep = times < duration_s
    return np.r_[times[keep], duration_s], np.r_[levels[keep], 0.0]


def designed_signal(t: np.ndarray, probe: ProbeResult, duration_s: float, seed: int = 0) -> np.ndarray:
    """The designed excitation's current [A] at times t [s] from its start: design_schedule's breakpoints joined
    by raised-cosine ramps; zero after duration_s."""
    times, levels = design_schedule(probe, duration_s, seed)
    return joined_by_raised_cosines(t, times, levels)
