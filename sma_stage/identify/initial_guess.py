"""Starting points for the GPI fit derived from the data alone (input range, output span, loop width)."""

from __future__ import annotations

import numpy as np

from sma_stage.model.parameters import GPIParameters

SATURATION_ARGUMENT = 1.5  # tanh argument at the ends of the input range in the guess
DENSITY_DECAY = 2.0  # a11 * largest threshold in the guess: the last weight is exp(-2) of the first
WIDTH_BINS = 20
DEFAULT_WIDTH_FRACTION = 0.1
# (envelope gain, loop width, density decay, envelope asymmetry) factors of the further starts.
START_VARIATIONS = (
    (1.0, 1.0, 1.0, 1.0),
    (2.5, 1.0, 1.0, 1.0),
    (0.5, 0.5, 1.0, 1.0),
    (1.0, 2.0, 0.25, 1.0),
    (1.5, 0.5, 4.0, 0.7),
    (0.7, 1.5, 1.0, 1.4),
)


def loop_width(u: np.ndarray, y: np.ndarray) -> float:
    """Median vertical loop width [output unit]: falling-branch minus rising-branch output at equal input."""
    rising = np.diff(u, prepend=u[0]) > 0.0
    falling = np.diff(u, prepend=u[0]) < 0.0
    edges = np.quantile(u, np.linspace(0.1, 0.9, WIDTH_BINS + 1))
    bins = np.digitize(u, edges)
    widths = []
    for b in range(1, WIDTH_BINS + 1):
        inside = bins == b
        up, down = inside & rising, inside & falling
        if up.any() and down.any():
            widths.append(np.mean(y[down]) - np.mean(y[up]))
    widths = np.asarray(widths)
    positive = widths[widths > 0.0]
    span = float(np.ptp(y))
    if positive.size == 0:
        return DEFAULT_WIDTH_FRACTION * span
    return float(min(np.median(positive), 0.8 * span))


def initial_guess(u: np.ndarray, y: np.ndarray, operators: int, gain_factor: float = 1.0,
                  width_factor: float = 1.0, decay_factor: float = 1.0, asymmetry: float = 1.0,
                  output_unit: str = "m") -> GPIParameters:
    """A guess with densities summing to 1: envelopes from the input range and output span, thresholds
    from the loop width (rising branch ~ gl - mean r, falling ~ gr + mean r)."""
    u_low, u_high = float(np.min(u)), float(np.max(u))
    centre, half_range = 0.5 * (u_low + u_high), 0.5 * (u_high - u_low)
    gain = gain_factor * SATURATION_ARGUMENT / half_range
    decay_per_operator = decay_factor * DENSITY_DECAY / max(operators - 1, 1)
    indices = np.arange(operators)
    weights = np.exp(-decay_per_operator * indices)
    weights /= weights.sum()
    width = width_factor * loop_width(u, y)
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


def start_points(u: np.ndarray, y: np.ndarray, operators: int, count: int, seed: int = 0,
                 output_unit: str = "m") -> list[GPIParameters]:
    """count deterministic starts: the plain guess, then fixed variations, then seeded random ones."""
    rng = np.random.default_rng(seed)
    factors = list(START_VARIATIONS[:count])
    while len(factors) < count:
        factors.append(tuple(np.exp(rng.uniform(-1.0, 1.0, 4) * np.array([0.9, 0.9, 1.4, 0.4]))))
    return [initial_guess(u, y, operators, *f, output_unit=output_unit) for f in factors]
