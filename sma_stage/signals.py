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
