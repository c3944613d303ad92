"""Model errors in per cent of the measured output's peak-to-peak span (the report's unit)."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from sma_stage.errors import InputError


@dataclass(frozen=True)
class ErrorMetrics:
    """RMS and maximum absolute error [% of the measured span] over `samples` samples."""

    rms_pct: float
    max_pct: float
    samples: int

    def to_dict(self) -> dict[str, float | int]:
        """The JSON report's form."""
        return {"rms_pct": self.rms_pct, "max_pct": self.max_pct, "samples": self.samples}


def error_metrics(measured: np.ndarray, predicted: np.ndarray) -> ErrorMetrics:
    """Errors of predicted against measured, in % of measured's peak-to-peak span."""
    measured = np.asarray(measured, dtype=float)
    predicted = np.asarray(predicted, dtype=float)
    if measured.shape != predicted.shape or measured.ndim != 1 or measured.size == 0:
        raise InputError(f"measured {measured.shape} and predicted {predicted.shape} must be equal, 1-D, non-empty")
    span = float(np.ptp(measured))
    if span <= 0.0:
        raise InputError("measured output has no span: errors in % of span are undefined")
    error = predicted - measured
    return ErrorMetrics(
        rms_pct=float(100.0 * np.sqrt(np.mean(error**2)) / span),
        max_pct=float(100.0 * np.max(np.abs(error)) / span),
        samples=int(measured.size),
    )


def worst(errors: Iterable[ErrorMetrics]) -> ErrorMetrics:
    """Of several records' errors, those of the record predicted worst (the largest RMS % of its span): what a
    choice made on several validation records is judged by."""
    return max(errors, key=lambda metrics: metrics.rms_pct)
