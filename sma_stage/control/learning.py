"""Iterative learning for a setpoint that repeats (no ROS): a correction [m] added to the setpoint at each phase of
its period, learnt from the tracking error of the periods before.

For a setpoint r that repeats every period, the compensator is given r + c(phase). The period is cut into bins of
RESOLUTION_S; each bin keeps the mean error e = measured - r (the setpoint without its correction) of the samples
that fell in it, and at the end of each period

    c  <-  Q(c - gain * S(e) shifted lag_s earlier)

S and Q are centred moving averages (over smoothing_s and twice that), taken round the period: S keeps the
sensor's noise out of c, Q keeps c from learning what changes faster than the stage can follow (the learning's
robustness filter). The shift: a correction acts on the position only through the stage's heating lag, so the
correction at phase p is corrected by the error lag_s later (a third of the model's tau: `learning_lag_s`).
From the second period on (the first began from elsewhere: a hold, another setpoint), a period whose RMS error is
more than WORSE_TOLERANCE above the best so far takes back the correction of that best period and halves the gain
(down to MIN_GAIN_FRACTION of the first): the relay's switch at each hand-over makes the stage's answer to c
anything but smooth, and a correction can make the error grow (bench/bench_learning.py; bench/README.md,
learning). c stays within +-limit_m, and between bins it is interpolated linearly.
"""

from __future__ import annotations

import math

import numpy as np

from sma_stage.errors import InputError, finite_number, non_negative_number

DEFAULT_GAIN = 0.5
DEFAULT_SMOOTHING_S = 1.0
RESOLUTION_S = 0.2  # the correction's and the errors' bins [s]
LAG_FRACTION = 0.3  # the learning's lag, as a fraction of the model's thermal time constant
WORSE_TOLERANCE = 0.05  # a period more than 5 % worse (RMS) than the best so far takes the best's correction back
MIN_GAIN_FRACTION = 0.125
MIN_FILLED = 0.5  # a period learns only when at least this share of its bins got an error


def learning_lag_s(tau_s: float) -> float:
    """The lag [s] the learning corrects a phase by, for a model with thermal time constant tau_s [s]."""
    return LAG_FRACTION * max(finite_number("tau_s", tau_s), 0.0)


def checked_period_s(period_s: float, resolution_s: float = RESOLUTION_S, name: str = "period_s") -> float:
    """A learning period [s] as a float: 0 (no learning) or at least four bins of resolution_s; InputError (one
    line, naming `name`) otherwise."""
    period = finite_number(name, period_s)
    if period != 0.0 and period < 4.0 * resolution_s:
        raise InputError(f"{name} must be 0 (off) or at least {4.0 * resolution_s:g} s, got {period_s!r}")
    return period


def _centred_mean(values: np.ndarray, width: int) -> np.ndarray:
    """The moving average of `values` over `width` bins centred on each (odd width), round the period."""
    half = width // 2
    if half == 0:
        return values.copy()
    padded = np.concatenate([values[-half:], values, values[:half]])
    return np.convolve(padded, np.ones(2 * half + 1) / (2 * half + 1), mode="valid")


class PeriodicLearning:
    """The correction [m] for a setpoint that repeats every period_s [s] (see the module's docstring): `record`
    each measured error with the time [s] since the learning began, `correction_m` at any time."""

    def __init__(self, period_s: float, lag_s: float, limit_m: float, gain: float = DEFAULT_GAIN,
                 smoothing_s: float = DEFAULT_SMOOTHING_S, resolution_s: float = RESOLUTION_S) -> None:
        resolution = finite_number("resolution_s", resolution_s)
        if resolution <= 0.0:
            raise InputError(f"resolution_s must be above 0, got {resolution_s!r}")
        self.period_s = checked_period_s(period_s, resolution)
        if self.period_s == 0.0:
            raise InputError("period_s must be above 0")
        self.gain = finite_number("gain", gain)
        if not 0.0 < self.gain <= 1.0:
            raise InputError(f"gain must be above 0 and at most 1, got {gain!r}")
        self.limit_m = non_negative_number("limit_m", limit_m)
        bins = round(self.period_s / resolution)
        self.resolution_s = self.period_s / bins
        self.lag_bins = min(round(non_negative_number("lag_s", lag_s) / self.resolution_s), bins - 1)
        self.smoothing_bins = 2 * round(0.5 * non_negative_number("smoothing_s", smoothing_s) / self.resolution_s) + 1
        self.correction = np.zeros(bins)  # at each bin's start
        self._sums, self._counts = np.zeros(bins), np.zeros(bins, dtype=int)
        self._period = 0  # the period now, counted from 0
        self.periods = 0  # periods learnt from
        self.best_rms_m = math.inf
        self.last_rms_m = math.nan
        self._best_correction = self.correction
        self._first_gain = self.gain

    def correction_m(self, time_s: float) -> float:
        """The correction [m] at time_s [s] since the learning began (any time: round the period)."""
        position = (finite_number("time_s", time_s) / self.resolution_s) % self.correction.size
        first = int(position)
        share = position - first
        return float((1.0 - share) * self.correction[first] + share * self.correction[(first + 1) % self.correction.size])

    def record(self, time_s: float, error_m: float) -> None:
        """Take the tracking error [m] (measured position - setpoint, the setpoint without its correction) at time_s
        [s] since the learning began, not before the last one recorded; a period's end learns."""
        time, error = finite_number("time_s", time_s), finite_number("error_m", error_m)
        period = math.floor(time / self.period_s)
        if period < self._period:
            raise InputError(f"time_s went back to {time_s!r} s, before the period the learning is in")
        if period > self._period:
            self._learn()
            self._period = period
        index = min(int((time - period * self.period_s) / self.resolution_s + 1e-6), self.correction.size - 1)
        self._sums[index] += error
        self._counts[index] += 1

    def _learn(self) -> None:
        filled = self._counts > 0
        sums, counts = self._sums, self._counts
        self._sums, self._counts = np.zeros(sums.size), np.zeros(counts.size, dtype=int)
        if np.mean(filled) < MIN_FILLED:
            return
        bins = np.arange(sums.size)
        means = sums[filled] / counts[filled]
        errors = np.interp(bins, bins[filled], means, period=sums.size)
        rms = float(np.sqrt(np.mean(means**2)))
        self.last_rms_m = rms
        self.periods += 1
        if self.periods > 1:
            if rms > (1.0 + WORSE_TOLERANCE) * self.best_rms_m:
                self.correction = self._best_correction.copy()
                self.gain = max(0.5 * self.gain, MIN_GAIN_FRACTION * self._first_gain)
                return
            if rms < self.best_rms_m:
                self.best_rms_m, self._best_correction = rms, self.correction.copy()
        later = np.roll(_centred_mean(errors, self.smoothing_bins), -self.lag_bins)
        corrected = _centred_mean(self.correction - self.gain * later, 2 * self.smoothing_bins - 1)
        self.correction = np.clip(corrected, -self.limit_m, self.limit_m)
