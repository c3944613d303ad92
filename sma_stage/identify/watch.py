"""The model in force watched against the stage (no ROS): its prediction from the applied current compared with
the measured position, sample by sample, and two sequential tests for a change of the stage.

The residual of a hysteresis model is not white: it is the model's error along the stage's path, correlated
over seconds and, on the stage simulator, as large as the changes worth flagging (a 2 N load step moves the
stage 3-7 um where the model's error runs to 26 um). But it is repeatable: the same stage driven along the
same path gives the same residual, to the noise. So the watch has two tests, each a CUSUM over windows of
`window_s` of stage time, both calibrated over the `calibration_windows` after `warmup_windows` (the model,
started where the watch started it, settles onto the stage's state):

- the path test: while calibrating, the residual is remembered against where the stage's path was (the measured
  position and four low-passes of it, 2 to 120 s: a summary of its recent history; with the PI loop it follows
  the setpoint whatever the stage became, so a changed stage is still on remembered ground). Afterwards each
  sample whose path comes within `path_radius` (in the memory's standard deviations) of remembered ones on at
  least two passes (PASS_GAP_S apart) whose residuals agreed is compared with the residual remembered there:
  the innovation. Per window with at least `min_coverage` of the samples it looked at so judged,
  z = sqrt(max(0, e^2 - (EXPLAINED s)^2)) / r0 (e the innovations' RMS; s the largest of what the passes'
  variance and the sensor noise give, half the largest RMS of a calibration window's innovations, each
  remembered sample compared with the other passes only, and EXPECTED_FLOOR r0; r0 the reference below) and
  S = max(0, S + z - shift_allowance); drift while S > shift_threshold. It sees a change
  of a fraction of the model's own error where the stage revisits ground it covered twice while calibrating;
  elsewhere it does not judge (`coverage`). Beside the innovations' size it follows their mean: per judged window,
  b = |mean innovation| / sigma, sigma the largest of: what the passes' variance and the noise give a window's
  mean; the RMS of the calibration windows' mean innovations, each remembered sample compared with its nearest
  of the other passes only (how far a window's mean wanders with nothing changed, measured), widened by how
  windows in a row share it (in_a_row_factor) and widened to an upper confidence bound of that measurement
  (scale_confidence_factor: a few correlated windows can measure it low); BIAS_FLOOR r0. Then
  S_b = max(0, S_b + b - bias_allowance) (capped as the size's); drift while S_b > bias_threshold. It sees a
  change small against the model's error but steady (an ambient drift of a fraction of a kelvin) that the size,
  which counts anything under shift_allowance r0 as no change, does not.
- the level test: the residual's RMS r per window against the largest window RMS of the calibration (at least
  r0), S = max(0, S + ln(r / (allowance ceiling))), drift while S > threshold: the model's error grown beyond
  anything it showed, anywhere.

The reference r0 is the larger of the model's held-out RMS when it was identified (its file's metadata
`held_out_rms`, when there) and the residual's RMS over the calibration windows.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from sma_stage.errors import InputError
from sma_stage.identify.path_memory import (
    MIN_HELD_OUT_WINDOWS,
    MIN_JUDGED,
    PASS_AGREEMENT,
    PASS_GAP_S,
    PATH_NEIGHBOURS,
    PATH_TIME_CONSTANTS_S,
    PathMemory,
    in_a_row_factor,
    inliers,
    lag_one_correlation,
    rms_without_outliers,
    scale_confidence_factor,
    thinned_to_rate,
)

STATES = ("ok", "drift", "no_model", "no_data")
EXPECTED_FLOOR = 0.05  # ... and at least this fraction of r0
WINDOWS_TO_TRIP = 3  # judged windows the path test needs at least to trip (one odd revisit does not)
EXPLAINED = 2.0  # innovations up to this many times what the passes' differences and the noise give ...
BIAS_FLOOR = 0.005  # the bias test's scale of a window's mean innovation is at least this fraction of r0
JUDGE_RATE_HZ = 10.0  # the path test judges at most this many samples per second of stage time


@dataclass(frozen=True)
class DriftTest:
    """The tests' settings: the level test drifts when the sum of ln(r / (allowance r0)) over windows exceeds
    `threshold`; the path test when the sum of (z - shift_allowance) exceeds `shift_threshold`."""

    window_s: float = 10.0
    allowance: float = 1.5
    threshold: float = 1.5
    calibration_windows: int = 120
    warmup_windows: int = 30  # the first windows in force, not counted: the model and the stage settle
    shift_allowance: float = 0.1  # innovations up to this fraction of r0 count as no change
    shift_threshold: float = 0.3
    path_radius: float = 0.2  # a path this near remembered ones (in the memory's standard deviations) is judged
    min_coverage: float = 0.25  # the path test judges a window with at least this fraction of it covered
    bias_allowance: float = 1.5  # a window's mean innovation up to this many of its standard errors is no change
    bias_threshold: float = 3.0
    path_time_constants_s: tuple[float, ...] = PATH_TIME_CONSTANTS_S  # the path's low-passes of the position [s]

    def __post_init__(self) -> None:
        for name in ("window_s", "threshold", "shift_threshold", "path_radius", "bias_threshold"):
            if not 0.0 < getattr(self, name) < math.inf:
                raise InputError(f"{name} must be positive and finite, got {getattr(self, name)}")
        if not 1.0 <= self.allowance < math.inf:
            raise InputError(f"allowance must be at least 1, got {self.allowance}")
        for name in ("shift_allowance", "bias_allowance"):
            if not 0.0 <= getattr(self, name) < math.inf:
                raise InputError(f"{name} must be at least 0 and finite, got {getattr(self, name)}")
        taus = self.path_time_constants_s
        if not taus or not all(isinstance(tau, (int, float)) and not isinstance(tau, bool) and 0.0 < tau < math.inf
                               for tau in taus):
            raise InputError(f"path_time_constants_s must be one or more positive finite times [s], got {taus!r}")
        if not 0.0 < self.min_coverage <= 1.0:
            raise InputError(f"min_coverage must be in (0, 1], got {self.min_coverage}")
        if self.calibration_windows < 1:
            raise InputError(f"calibration_windows must be at least 1, got {self.calibration_windows}")
        if self.warmup_windows < 0:
            raise InputError(f"warmup_windows must be at least 0, got {self.warmup_windows}")


class CusumOfWindows:
    """The level test on window RMS values [m]; feed each completed window's RMS with `add`."""

    def __init__(self, test: DriftTest, held_out_rms: float | None = None) -> None:
        self.test = test
        self.held_out_rms = held_out_rms if held_out_rms is not None and held_out_rms > 0.0 else None
        self.calibration: list[float] = []
        self.statistic = 0.0
        self.windows = 0
        self.reference: float | None = None  # r0 [m]: the held-out RMS or the calibration's, the larger (None before)
        self.ceiling: float | None = None  # the largest window RMS [m] while calibrating, at least r0 (None before)

    @property
    def drift(self) -> bool:
        return self.statistic > self.test.threshold

    def add(self, window_rms: float) -> None:
        """One completed window's residual RMS [m]."""
        self.windows += 1
        if self.windows <= self.test.warmup_windows:
            return
        if self.reference is None:
            self.calibration.append(window_rms)
            if len(self.calibration) == self.test.calibration_windows:
                calibrated = float(np.sqrt(np.mean(np.square(self.calibration))))
                self.reference = max(calibrated, self.held_out_rms or 0.0)
                self.ceiling = max(self.reference, max(self.calibration))
            return
        ratio = max(window_rms, 1e-300) / self.ceiling
        self.statistic = max(0.0, self.statistic + math.log(ratio) - math.log(self.test.allowance))


def load_kernels(model: object) -> None:
    """Run the watch's compiled kernels and the model's forward once on a throwaway record, so that they load (or
    build: seconds on a cold numba cache) now and not in a node's first callback."""
    t_s = np.arange(2 * PATH_NEIGHBOURS, dtype=float)
    ModelWatch(model).step(t_s, np.zeros_like(t_s), np.zeros_like(t_s))
    memory = PathMemory()
    features = memory.features(t_s, np.sin(t_s))
    memory.remember(t_s, features, np.cos(t_s))
    memory.build()
    memory.innovations(features, np.cos(t_s), 1.0, PASS_GAP_S, 1.0)
    memory.held_out_windows(4.0, 1.0, 1.0, 1.0, 0.25)


class RecentRecord:
    """The last `seconds` of aligned samples (t [s], input [A], output [m]), kept in chunks."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds
        self._chunks: deque[tuple[np.ndarray, np.ndarray, np.ndarray]] = deque()

    def add(self, t_s: np.ndarray, current_a: np.ndarray, position_m: np.ndarray) -> None:
        if t_s.size == 0:
            return
        self._chunks.append((t_s.copy(), current_a.copy(), position_m.copy()))
        while len(self._chunks) > 1 and self._chunks[1][0][0] <= t_s[-1] - self.seconds:
            self._chunks.popleft()

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(t, input, output) of the last `seconds` (empty arrays when nothing came)."""
        if not self._chunks:
            return np.empty(0), np.empty(0), np.empty(0)
        t, u, y = (np.concatenate(column) for column in zip(*self._chunks, strict=True))
        keep = t > t[-1] - self.seconds
        return t[keep], u[keep], y[keep]

    @property
    def span_s(self) -> float:
        """Stage seconds from the first sample kept to the last."""
        if not self._chunks:
            return 0.0
        return float(self._chunks[-1][0][-1] - self._chunks[0][0][0])


@dataclass
class _Window:
    """The samples of the window being filled: residuals [m], and the path test's innovations [m] of the samples
    it looked at (NaN where the memory could not say)."""

    start_s: float
    residuals: list[np.ndarray]
    innovations: list[np.ndarray]
    spreads: list[np.ndarray]  # the variance of each innovation with nothing changed [m^2]


class ModelWatch:
    """A model (any family: `run(t, u, state)`) run on the applied current, its residual (measured - predicted
    [m]) per sample, and the two drift tests on windows of it.

    The model starts from rest, or from where `history` (t [s], u [A]: the applied current before the first
    sample) leaves it."""

    def __init__(self, model: object, test: DriftTest | None = None,
                 history: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        self.model = model.without_state()
        self.test = test or DriftTest()
        held_out = (getattr(model, "metadata", None) or {}).get("held_out_rms")
        self.cusum = CusumOfWindows(self.test, float(held_out) if held_out is not None else None)
        self._state = None
        if history is not None and len(history[0]):
            self._state = self.model.run(*history, None)[1]
        self.memory = PathMemory(self.test.path_time_constants_s)
        self.path_statistic = 0.0
        self.bias_statistic = 0.0
        self.judged_windows = 0
        self._last_judged_s = -math.inf
        self._level_onset_s = self._path_onset_s = self._bias_onset_s = 0.0
        self.coverage: float | None = None  # the judged fraction of the last window the path test looked at
        self._started_s: float | None = None
        self._window: _Window | None = None
        self.last_window_rms: float | None = None
        self.last_innovation_rms: float | None = None
        self.last_bias_z: float | None = None  # the last judged window's |mean innovation| in its standard errors
        self.held_out_bias_m: float | None = None  # a window's mean innovation with nothing changed, RMS [m]
        self.held_out_size_m: float | None = None  # a window's innovations' RMS with nothing changed, largest [m]
        self.bias_scale_widening = 1.0  # the bias test's scale over held_out_bias_m: the measurement's uncertainty
        self.samples = 0

    def step(self, t_s: np.ndarray, current_a: np.ndarray, position_m: np.ndarray) -> np.ndarray:
        """The residuals [m] of these samples (t [s of stage time, increasing], the current held at each [A],
        the measured position [m]), the model carried on from the samples before."""
        t_s, current_a, position_m = (np.asarray(a, dtype=float) for a in (t_s, current_a, position_m))
        if t_s.size == 0:
            return np.empty(0)
        predicted, self._state = self.model.run(t_s, current_a, self._state)
        residual = position_m - predicted
        if self._started_s is None:
            self._started_s = float(t_s[0])
        innovation, spread, looked_at = self._path(t_s, position_m, residual)
        self._add_to_windows(t_s, residual, innovation, spread, looked_at)
        self.samples += t_s.size
        return residual

    @property
    def memory_window_s(self) -> tuple[float, float]:
        """The stage times [s] the path memory remembers: the calibration windows after the warm-up."""
        start = (self._started_s or 0.0) + self.test.warmup_windows * self.test.window_s
        return start, start + self.test.calibration_windows * self.test.window_s

    def _path(self, t_s: np.ndarray, position_m: np.ndarray, residual: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(the path test's innovations of these samples [m] and their variances with nothing changed [m^2], NaN
        where the memory cannot say; which samples it looked at), remembering while it learns."""
        features = self.memory.features(t_s, position_m)
        innovation, spread = np.full(t_s.size, np.nan), np.full(t_s.size, np.nan)
        looked_at = np.zeros(t_s.size, dtype=bool)
        reference = self.cusum.reference
        if self.memory.built and reference is not None:
            judged = thinned_to_rate(t_s, JUDGE_RATE_HZ)
            judged = judged[t_s[judged] > self._last_judged_s]
            if judged.size:
                self._last_judged_s = float(t_s[judged[-1]])
                looked_at[judged] = True
                innovation[judged], spread[judged] = self.memory.innovations(
                    features[judged], residual[judged], self.test.path_radius, PASS_GAP_S, PASS_AGREEMENT * reference)
            return innovation, spread, looked_at
        start, end = self.memory_window_s
        learning = (t_s >= start) & (t_s < end)
        if learning.any():
            self.memory.remember(t_s[learning], features[learning], residual[learning])
        if t_s[-1] >= end and not self.memory.build():
            # too little came to remember: learn again from here
            self.memory = PathMemory(self.test.path_time_constants_s)
            self._started_s = float(t_s[-1]) - self.test.warmup_windows * self.test.window_s
        return innovation, spread, looked_at

    def _add_to_windows(self, t_s: np.ndarray, residual: np.ndarray, innovation: np.ndarray, spread: np.ndarray,
                        looked_at: np.ndarray) -> None:
        """Add samples to the window being filled, closing each window at the first sample window_s after its
        start."""
        first = 0
        while first < t_s.size:
            if self._window is None:
                self._window = _Window(float(t_s[first]), [], [], [])
            window = self._window
            end = first + int(np.searchsorted(t_s[first:], window.start_s + self.test.window_s, side="left"))
            if end == first:
                self._close_window(window)
                self._window = _Window(float(t_s[first]), [], [], [])
                continue
            window.residuals.append(residual[first:end])
            window.innovations.append(innovation[first:end][looked_at[first:end]])
            window.spreads.append(spread[first:end][looked_at[first:end]])
            first = end

    def _close_window(self, window: _Window) -> None:
        level_before, path_before, bias_before = self.cusum.statistic, self.path_statistic, self.bias_statistic
        self._test_window(window)
        if level_before == 0.0 < self.cusum.statistic:
            self._level_onset_s = window.start_s
        if path_before == 0.0 < self.path_statistic:
            self._path_onset_s = window.start_s
        if bias_before == 0.0 < self.bias_statistic:
            self._bias_onset_s = window.start_s

    def _test_window(self, window: _Window) -> None:
        residuals = np.concatenate(window.residuals)
        self.last_window_rms = float(np.sqrt(np.mean(np.square(residuals))))
        self.cusum.add(self.last_window_rms)
        innovations, spreads = np.concatenate(window.innovations), np.concatenate(window.spreads)
        judged = np.isfinite(innovations)
        reference = self.cusum.reference
        if not self.memory.built or reference is None:
            return
        if innovations.size == 0:
            return
        count = np.count_nonzero(judged)
        self.coverage = count / innovations.size
        if self.coverage < self.test.min_coverage or count < MIN_JUDGED:
            return
        self.judged_windows += 1
        held_out_bias, held_out_size = self._held_out(reference)
        innovations, mean_spread = innovations[judged], float(np.mean(spreads[judged]))
        self.last_innovation_rms = float(np.sqrt(np.mean(np.square(innovations))))
        expected = max(mean_spread + self.memory.noise_m**2, (held_out_size / EXPLAINED) ** 2,
                       (EXPECTED_FLOOR * reference) ** 2)
        excess = math.sqrt(max(0.0, self.last_innovation_rms**2 - EXPLAINED**2 * expected))
        step = min(excess / reference - self.test.shift_allowance, self.test.shift_threshold / (WINDOWS_TO_TRIP - 0.5))
        self.path_statistic = max(0.0, self.path_statistic + step)
        mean_variance = mean_spread + self.memory.noise_m**2 / count
        self.last_bias_z = abs(float(np.mean(innovations))) / math.sqrt(
            max(mean_variance, held_out_bias**2, (BIAS_FLOOR * reference) ** 2))
        step = min(self.last_bias_z - self.test.bias_allowance, self.test.bias_threshold / (WINDOWS_TO_TRIP - 0.5))
        self.bias_statistic = max(0.0, self.bias_statistic + step)

    def _held_out(self, reference: float) -> tuple[float, float]:
        """(the bias test's scale, the size test's level) [m], from the calibration's windows, each sample compared
        with its nearest of the other passes (0 where fewer than MIN_HELD_OUT_WINDOWS could be): how far a window's
        mean wanders with nothing changed (the means' RMS, widened by in_a_row_factor over WINDOWS_TO_TRIP: where
        each pass's residual differs, windows in a row share it and trip the test together; and by
        scale_confidence_factor, since few windows can measure it low), and how large its
        innovations are (the largest window RMS). Only inliers count: one window from a pass remembered while the
        stage still settled would set either alone."""
        if self.held_out_size_m is None:  # both are set together, once
            slots, means, sizes = self.memory.held_out_windows(self.test.window_s, self.test.path_radius,
                                                               PASS_GAP_S, PASS_AGREEMENT * reference,
                                                               self.test.min_coverage)
            kept = inliers(means)
            rho = lag_one_correlation(slots[kept], means[kept])
            self.held_out_bias_m = rms_without_outliers(means) * in_a_row_factor(rho, WINDOWS_TO_TRIP)
            self.bias_scale_widening = scale_confidence_factor(rho, int(np.count_nonzero(kept)))
            kept_sizes = sizes[inliers(sizes)]
            self.held_out_size_m = float(kept_sizes.max()) if kept_sizes.size >= MIN_HELD_OUT_WINDOWS else 0.0
        return self.held_out_bias_m * self.bias_scale_widening, self.held_out_size_m

    @property
    def path_drift(self) -> bool:
        """The path test tripped, by the innovations' size or by their mean."""
        return self.size_drift or self.bias_drift

    @property
    def size_drift(self) -> bool:
        return self.path_statistic > self.test.shift_threshold

    @property
    def bias_drift(self) -> bool:
        return self.bias_statistic > self.test.bias_threshold

    @property
    def onset_s(self) -> float | None:
        """Where the change began [s of stage time]: the start of the window from which a test that tripped rose
        from 0, the earliest of them (None without drift)."""
        onsets = [onset for tripped, onset in ((self.size_drift, self._path_onset_s),
                                               (self.bias_drift, self._bias_onset_s),
                                               (self.cusum.drift, self._level_onset_s)) if tripped]
        return min(onsets) if onsets else None

    @property
    def state(self) -> str:
        """ok or drift (no_model and no_data are the node's to say)."""
        return "drift" if self.cusum.drift or self.path_drift else "ok"

    @property
    def calibrating(self) -> bool:
        return self.cusum.reference is None

    def restart_tests(self) -> None:
        """Every statistic back to 0 (the model runs on, the reference and the memory are kept)."""
        self.cusum.statistic = 0.0
        self.path_statistic = 0.0
        self.bias_statistic = 0.0
