"""Starting points for the GPI fit derived from the data alone (input range, output span, loop width)."""

from __future__ import annotations

import itertools

import numpy as np

from sma_stage.model.parameters import GPIParameters

SATURATION_ARGUMENT = 1.5  # tanh argument at the ends of the input range in the guess
DENSITY_DECAY = 2.0  # a11 * largest threshold in the guess: the last weight is exp(-2) of the first
WIDTH_BINS = 20
DEFAULT_WIDTH_FRACTION = 0.1
# Factors on the plain guess spanned by the starts: envelope gain, loop width (threshold scale), density decay.
GAIN_FACTORS = (1.0, 0.5, 2.0)
WIDTH_FACTORS = (1.0, 2.0, 0.5, 4.0)
DECAY_FACTORS = (1.0, 0.25, 4.0)


def start_factors() -> list[tuple[float, float, float]]:
    """The grid of (gain, width, decay) factors, nearest the plain guess (1, 1, 1) first."""
    grid = list(itertools.product(GAIN_FACTORS, WIDTH_FACTORS, DECAY_FACTORS))
    return sorted(grid, key=lambda factors: float(np.sum(np.abs(np.log(factors)))))


DEFAULT_START_COUNT = len(GAIN_FACTORS) * len(WIDTH_FACTORS) * len(DECAY_FACTORS)


def loop_width(u: np.ndarray, y: np.ndarray) -> float:
    """Largest vertical loop width [output unit]: falling- minus rising-branch mean output in bins of
    equal input (the loop closes where the envelopes saturate, so the widest bin is the telling one)."""
    slope = np.diff(u, prepend=u[0])
    edges = np.linspace(np.min(u), np.max(u), WIDTH_BINS + 1)
    bins = np.clip(np.digitize(u, edges), 1, WIDTH_BINS)
    widths = [0.0]
    for b in range(1, WIDTH_BINS + 1):
        inside = bins == b
        up, down = inside & (slope > 0.0), inside & (slope < 0.0)
        if up.any() and down.any():
            widths.append(np.mean(y[down]) - np.mean(y[up]))
    span = float(np.ptp(y))
    width = max(widths)
    return float(min(width, 0.8 * span)) if width > 0.0 else DEFAULT_WIDTH_FRACTION * span


def initial_guess(u: np.ndarray, y: np.ndarray, operators: int, gain_factor: float = 1.0,
                  width_factor: float = 1.0, decay_factor: float = 1.0, asymmetry: float = 1.0,
                  output_unit: str = "m", width: float | None = None) -> GPIParameters:
    """A guess with densities summing to 1: envelopes from the input range and output span, thresholds
    from the loop width (rising branch ~ gl - mean r, falling ~ gr + mean r; width: loop_width(u, y))."""
    u_low, u_high = float(np.min(u)), float(np.max(u))
    centre, half_range = 0.5 * (u_low + u_high), 0.5 * (u_high - u_low)
    gain = gain_factor * SATURATION_ARGUMENT / half_range
    decay_per_operator = decay_factor * DENSITY_DECAY / max(operators - 1, 1)
    indices = np.arange(operators)
    weights = np.exp(-decay_per_operator * indices)
    weights /= weights.sum()
    width = width_factor * (loop_width(u, y) if width is None else width)
    if operators > 1:
        a9 = 0.5 * width / float(weights @ indices)
        mean_threshold, envelope_gap = 0.5 * width, 0.0
    else:
        a9, mean_threshold, envelope_gap = 0.5 * width, 0.0, width
    y_low, y_high = float(np.min(y)), float(np.max(y))
    reach = np.tanh(gain * half_range)
    scale = (y_high - y_low + 2.0 * mean_threshold + envelope_gap) / (2.0 * reach)
    offset = 0.5 * (y_low + y_high)
    return GPIParameters(
        a1=scale * asymmetry, a2=gain, a3=-gain * centre, a4=offset - 0.5 * envelope_gap,
        a5=scale / asymmetry, a6=gain, a7=-gain * centre, a8=offset + 0.5 * envelope_gap,
        a9=a9, a10=1.0 / np.exp(-decay_per_operator * indices).sum(), a11=decay_per_operator / a9,
        output_unit=output_unit,
    )


def start_points(u: np.ndarray, y: np.ndarray, operators: int, count: int = DEFAULT_START_COUNT, seed: int = 0,
                 output_unit: str = "m") -> list[GPIParameters]:
    """count deterministic starts: the plain guess, then the grid of factors, then seeded random ones."""
    rng = np.random.default_rng(seed)
    factors = [(*f, 1.0) for f in start_factors()[:count]]
    while len(factors) < count:
        factors.append(tuple(np.exp(rng.uniform(-1.0, 1.0, 4) * np.array([0.9, 1.4, 1.4, 0.3]))))
    width = loop_width(u, y)
    return [initial_guess(u, y, operators, *f, output_unit=output_unit, width=width) for f in factors]
