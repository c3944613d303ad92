"""The model in force watched against the stage (no ROS): its prediction from the applied current compared with
the measured position, sample by sample, and a sequential test for a change in how well it predicts.

The test (a CUSUM of log RMS ratios over windows): the residual of a hysteresis model is not white (it is the
model's error along the input's path, correlated over seconds), so a test per sample would count the same
error many times. Per window of `window_s` of stage time the residual's RMS r is compared with the reference
level r0 and

    S = max(0, S + ln(r / r0) - ln(allowance)),     drift while S > threshold.

A window at the reference level takes ln(allowance) off S, a window at e^threshold x allowance times it trips
it at once, a smaller lasting rise in a few windows. The reference level is the larger of the model's held-out
RMS when it was identified (its file's metadata `held_out_rms`, when there) and the RMS over its first
`calibration_windows` windows in force after `warmup_windows` (the model, started from rest, settles onto the
stage's state): tracking a signal other than its excitation, the residual may sit above the held-out level
with nothing wrong.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sma_stage.errors import InputError

STATES = ("ok", "drift", "no_model", "no_data")


@dataclass(frozen=True)
class DriftTest:
    """The CUSUM's settings: windows at up to `allowance` times the reference count as no change; drift when
    the sum of ln(r / (allowance r0)) exceeds `threshold`."""

    window_s: float = 20.0
    allowance: float = 1.5
    threshold: float = 1.5
    calibration_windows: int = 6
    warmup_windows: int = 3  # the first windows in force, not counted: the model started from rest settles

    def __post_init__(self) -> None:
        for name in ("window_s", "threshold"):
            if not 0.0 < getattr(self, name) < math.inf:
                raise InputError(f"{name} must be positive and finite, got {getattr(self, name)}")
        if not 1.0 <= self.allowance < math.inf:
            raise InputError(f"allowance must be at least 1, got {self.allowance}")
        if self.calibration_windows < 1:
            raise InputError(f"calibration_windows must be at least 1, got {self.calibration_windows}")
        if self.warmup_windows < 0:
            raise InputError(f"warmup_windows must be at least 0, got {self.warmup_windows}")


class CusumOfWindows:
    """The sequential test on window RMS values [m]; feed each completed window's RMS with `add`."""

    def __init__(self, test: DriftTest, held_out_rms: float | None = None) -> None:
        self.test = test
        self.held_out_rms = held_out_rms if held_out_rms is not None and held_out_rms > 0.0 else None
        self.calibration: list[float] = []
        self.statistic = 0.0
        self.windows = 0

    @property
    def reference(self) -> float | None:
        """The reference level r0 [m] (None while calibrating)."""
        if len(self.calibration) < self.test.calibration_windows:
            return None
        calibrated = float(np.sqrt(np.mean(np.square(self.calibration))))
        return max(calibrated, self.held_out_rms or 0.0)

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
            return
        ratio = max(window_rms, 1e-300) / self.reference
        self.statistic = max(0.0, self.statistic + math.log(ratio) - math.log(self.test.allowance))


class ModelWatch:
    """A model (any family: `run(t, u, state)`) run forward from rest on the applied current, its residual
    (measured - predicted [m]) per sample, its RMS per window of stage time and the drift test on them."""

    def __init__(self, model: object, test: DriftTest | None = None) -> None:
        self.model = model.without_state()
        self.test = test or DriftTest()
        held_out = (getattr(model, "metadata", None) or {}).get("held_out_rms")
        self.cusum = CusumOfWindows(self.test, float(held_out) if held_out is not None else None)
        self._state = None
        self._window_start: float | None = None
        self._window: list[float] = []
        self.last_window_rms: float | None = None
        self.samples = 0

    def step(self, t_s: np.ndarray, current_a: np.ndarray, position_m: np.ndarray) -> np.ndarray:
        """The residuals [m] of these samples (t [s of stage time, increasing], the current held at each [A],
        the measured position [m]), the model carried on from the samples before."""
        t_s, current_a, position_m = (np.asarray(a, dtype=float) for a in (t_s, current_a, position_m))
        if t_s.size == 0:
            return np.empty(0)
        predicted, self._state = self.model.run(t_s, current_a, self._state)
        residual = position_m - predicted
        for time_s, value in zip(t_s, residual, strict=True):
            self._add_to_window(float(time_s), float(value))
        self.samples += t_s.size
        return residual

    def _add_to_window(self, time_s: float, value: float) -> None:
        if self._window_start is None:
            self._window_start = time_s
        if time_s - self._window_start >= self.test.window_s and self._window:
            self.last_window_rms = float(np.sqrt(np.mean(np.square(self._window))))
            self.cusum.add(self.last_window_rms)
            self._window, self._window_start = [], time_s
        self._window.append(value)

    @property
    def state(self) -> str:
        """ok or drift (no_model and no_data are the node's to say)."""
        return "drift" if self.cusum.drift else "ok"

    @property
    def calibrating(self) -> bool:
        return self.cusum.reference is None
