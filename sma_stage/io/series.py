"""A measured input/output record (time, actuator input, measured output) and its validation."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sma_stage.errors import InputError

DEFAULT_MIN_SAMPLES = 20
_FLAT_RELATIVE_SPAN = 1e-9
MAX_RECORD_S = 1e7  # about 116 days: a longer t column is not in seconds
MIN_STEP_S = 1e-10  # a 10 GHz record: a smaller median step is not in seconds


def _frozen_vector(values: object) -> np.ndarray:
    vector = np.array(values, dtype=np.float64).reshape(-1)
    vector.setflags(write=False)
    return vector


@dataclass(frozen=True, eq=False)
class Series:
    """Samples of time t [s] (or a sample index), actuator input [A] and measured output [m or file unit].

    Build it with `make_series`, which checks the data; the arrays are read-only.
    """

    t: np.ndarray
    input: np.ndarray
    output: np.ndarray
    source: str = ""
    time_is_index: bool = False

    def __post_init__(self) -> None:
        for name in ("t", "input", "output"):
            object.__setattr__(self, name, _frozen_vector(getattr(self, name)))
        if not len(self.t) == len(self.input) == len(self.output):
            raise InputError(
                f"{self._prefix()}columns differ in length: t {len(self.t)}, "
                f"input {len(self.input)}, output {len(self.output)}"
            )

    def __len__(self) -> int:
        return len(self.t)

    def _prefix(self) -> str:
        return f"{self.source}: " if self.source else ""

    @property
    def duration(self) -> float:
        """Time from the first to the last sample [s, or samples when time is an index]."""
        return float(self.t[-1] - self.t[0]) if len(self) else 0.0

    @property
    def sample_period(self) -> float:
        """Median spacing of the time stamps [s, or 1 for an index]."""
        return float(np.median(np.diff(self.t))) if len(self) > 1 else 0.0

    @property
    def output_span(self) -> float:
        """Peak-to-peak span of the measured output (the reference for per-cent errors)."""
        return float(np.ptp(self.output)) if len(self) else 0.0

    def slice(self, start: int | None = None, stop: int | None = None) -> Series:
        """Samples start..stop-1 (Python slice semantics); time keeps its original origin."""
        part = slice(start, stop)
        return Series(self.t[part], self.input[part], self.output[part], self.source, self.time_is_index)

    def window(self, t_start: float, t_stop: float) -> Series:
        """Samples with t_start <= t < t_stop (same unit as t)."""
        first, last = np.searchsorted(self.t, [t_start, t_stop], side="left")
        return self.slice(int(first), int(last))

    def thinned(self, block: int) -> Series:
        """Every block samples as one: the input averaged over the block (the heat it brought to first order), the
        time and the output at the block's last sample; the first len % block samples are dropped, so the last
        sample stays."""
        if block <= 1:
            return self
        start = len(self) % block
        inputs = self.input[start:].reshape(-1, block).mean(axis=1)
        ends = slice(start + block - 1, None, block)
        return Series(self.t[ends], inputs, self.output[ends], self.source, self.time_is_index)

    def split(self, fraction: float) -> tuple[Series, Series]:
        """(first, rest): the first `fraction` of the samples and the remainder, e.g. for held-out validation."""
        if not 0.0 < fraction < 1.0:
            raise InputError(f"split fraction must lie strictly between 0 and 1, got {fraction}")
        cut = round(fraction * len(self))
        if cut < 1 or cut > len(self) - 1:
            raise InputError(f"{self._prefix()}{len(self)} samples cannot be split at fraction {fraction}")
        return self.slice(None, cut), self.slice(cut, None)


def _check_finite(name: str, values: np.ndarray, prefix: str) -> None:
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        raise InputError(
            f"{prefix}column '{name}' has {values[bad[0]]} at sample {bad[0]} ({bad.size} non-finite values)"
        )


def _check_increasing(t: np.ndarray, prefix: str) -> None:
    steps = np.diff(t)
    bad = np.flatnonzero(steps <= 0)
    if bad.size:
        k = int(bad[0])
        raise InputError(
            f"{prefix}time must increase: sample {k + 1} has t = {float(t[k + 1])!r} after t = {float(t[k])!r}"
        )


def _check_time_in_seconds(t: np.ndarray, prefix: str) -> None:
    """Refuse a time column whose span or typical step cannot be seconds of a stage record (ns stamps give
    a span of about 1e12: a lag of 1e10 s would be reported without a word)."""
    span = float(t[-1] - t[0])
    step = float(np.median(np.diff(t)))
    if span > MAX_RECORD_S:
        raise InputError(f"{prefix}t spans {span:.3g} s ({span / 86400:.3g} days): is it in ms, us or ns? "
                         "give it in seconds")
    if step < MIN_STEP_S:
        raise InputError(f"{prefix}t steps by {step:.3g} s (median): is it in seconds?")


def _check_excited(name: str, values: np.ndarray, prefix: str) -> None:
    span = float(np.ptp(values))
    if span <= _FLAT_RELATIVE_SPAN * float(np.max(np.abs(values))):
        raise InputError(
            f"{prefix}no excitation: '{name}' is constant ({float(values[0])!r}) over all {len(values)} samples"
        )


def make_series(
    t: object,
    input: object,
    output: object,
    source: str = "",
    time_is_index: bool = False,
    min_samples: int = DEFAULT_MIN_SAMPLES,
) -> Series:
    """A checked Series; InputError for too few samples, NaN/inf, unequal lengths,
    non-increasing time, or a constant input or output."""
    series = Series(t, input, output, source, time_is_index)
    prefix = series._prefix()
    if len(series) < max(min_samples, 1):
        raise InputError(f"{prefix}only {len(series)} samples, at least {max(min_samples, 1)} needed")
    for name in ("t", "input", "output"):
        _check_finite(name, getattr(series, name), prefix)
    _check_increasing(series.t, prefix)
    if not time_is_index:
        _check_time_in_seconds(series.t, prefix)
    _check_excited("input", series.input, prefix)
    _check_excited("output", series.output, prefix)
    return series
