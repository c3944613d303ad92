"""Excitation signals of the source paper, as functions of time [s] returning current [A]."""

import numpy as np

IDENTIFICATION_PERIOD_S = 250.0
IDENTIFICATION_DURATION_S = 1000.0


def paper_identification_signal(
    t: np.ndarray,
    amplitude_start: float = 5.0,
    amplitude_end: float = 3.6,
    period_s: float = IDENTIFICATION_PERIOD_S,
    duration_s: float = IDENTIFICATION_DURATION_S,
) -> np.ndarray:
    """The paper's decaying sine A(t) sin(2 pi t / period) [A]; A falls linearly over duration_s."""
    t = np.asarray(t, dtype=float)
    fraction = np.clip(t / duration_s, 0.0, 1.0)
    amplitude = amplitude_start + (amplitude_end - amplitude_start) * fraction
    return amplitude * np.sin(2.0 * np.pi * t / period_s)


def paper_validation_signal(t: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """The paper's validation input u(t) = 2.5 cos(0.01 pi t) + 2.5 cos(0.02 t) [A], times scale."""
    t = np.asarray(t, dtype=float)
    return scale * (2.5 * np.cos(0.01 * np.pi * t) + 2.5 * np.cos(0.02 * t))


LEVELS_HOLD_S = 60.0


def held_levels_signal(t: np.ndarray, max_current_a: float = 5.0, hold_s: float = LEVELS_HOLD_S,
                       seed: int = 0) -> np.ndarray:
    """Held random levels [A]: a current drawn uniformly from -max_current_a to max_current_a, held hold_s [s]
    each (steps, deterministic by seed): its steps hand the current from one wire to the other at full scale,
    the hand-overs a slow sine does not show."""
    t = np.asarray(t, dtype=float)
    index = np.floor(np.maximum(t, 0.0) / hold_s).astype(int)
    levels = np.random.default_rng(seed).uniform(-max_current_a, max_current_a, int(index.max(initial=0)) + 1)
    return levels[index]


DESIGNED_LEVELS = (0.45, 0.55, 0.65, 0.75, 0.85, 1.0)  # excursion peaks, fractions of the current limit


def designed_schedule(max_current_a: float = 5.0, duration_s: float = IDENTIFICATION_DURATION_S,
                      seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Breakpoints (times [s], currents [A]) of the designed identification signal: excursions that heat one
    wire each (the first two wire a then wire b, later the wire chosen at random, sometimes the same one twice),
    each rising to a peak from DESIGNED_LEVELS (each level in turn, shuffled), held, returned part way to a
    reversal level and held, in half of them raised again to a lower second peak (an inner loop), then brought
    to zero and held while the wire cools."""
    rng = np.random.default_rng(seed)
    times, levels = [0.0], [0.0]
    peaks: list[float] = []
    sign = 1.0

    def go(level: float, ramp_s: float, hold_s: float) -> None:
        times.extend([times[-1] + ramp_s, times[-1] + ramp_s + hold_s])
        levels.extend([level, level])

    count = 0
    while times[-1] < duration_s:
        if not peaks:
            peaks = list(rng.permutation(DESIGNED_LEVELS))
        peak = sign * max_current_a * peaks.pop()
        go(peak, rng.uniform(15.0, 30.0), rng.uniform(10.0, 25.0))
        reversal = peak * rng.uniform(0.3, 0.7)
        go(reversal, rng.uniform(10.0, 20.0), rng.uniform(10.0, 20.0))
        if rng.random() < 0.5:
            go(reversal + (peak - reversal) * rng.uniform(0.4, 0.8), rng.uniform(8.0, 15.0), rng.uniform(5.0, 15.0))
        go(0.0, rng.uniform(10.0, 20.0), rng.uniform(15.0, 35.0))
        count += 1
        sign = -sign if count < 2 or rng.random() < 0.65 else sign
    return np.array(times), np.array(levels)


def joined_by_raised_cosines(t: np.ndarray, times: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """The current [A] at times t [s] through breakpoints (times [s], levels [A]) joined by raised-cosine ramps
    (smooth, so a lag sees no steps); zero before the first breakpoint and after the last."""
    t = np.asarray(t, dtype=float)
    index = np.clip(np.searchsorted(times, t, side="right") - 1, 0, times.size - 2)
    start, end = times[index], times[index + 1]
    fraction = np.clip((t - start) / np.maximum(end - start, 1e-12), 0.0, 1.0)
    value = levels[index] + (levels[index + 1] - levels[index]) * 0.5 * (1.0 - np.cos(np.pi * fraction))
    return np.where((t >= times[0]) & (t <= times[-1]), value, 0.0)


def designed_identification_signal(t: np.ndarray, max_current_a: float = 5.0,
                                   duration_s: float = IDENTIFICATION_DURATION_S, seed: int = 0) -> np.ndarray:
    """The designed identification signal [A] at times t [s]: designed_schedule's breakpoints joined by
    raised-cosine ramps; zero after duration_s."""
    times, levels = designed_schedule(max_current_a, duration_s, seed)
    t = np.asarray(t, dtype=float)
    return np.where(t <= duration_s, joined_by_raised_cosines(t, times, levels), 0.0)
