"""The input checks every model family shares (no import from the rest of the package but its errors): each
refuses bad input with one InputError line."""

from __future__ import annotations

import math

import numpy as np

from sma_stage.errors import InputError


def as_signal(values: np.ndarray, name: str) -> np.ndarray:
    """A 1-D float64 copy of values, refused with one line if empty, not 1-D or not finite."""
    try:
        array = np.array(values, dtype=float, copy=True)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be numeric") from None
    if array.ndim == 0:
        array = array.reshape(1)
    if array.ndim != 1:
        raise InputError(f"{name} must be one-dimensional, got shape {array.shape}")
    if array.size == 0:
        raise InputError(f"{name} is empty")
    bad = np.flatnonzero(~np.isfinite(array))
    if bad.size:
        raise InputError(f"{name} has a non-finite value ({array[bad[0]]}) at index {bad[0]}")
    return array


def checked_record(t: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Time [s] and input [A] of a record as signals of one length, time increasing from sample to sample."""
    t, u = as_signal(t, "time"), as_signal(u, "input")
    if t.size != u.size:
        raise InputError(f"time and input differ in length ({t.size} and {u.size} samples)")
    if t.size > 1 and np.any(np.diff(t) <= 0.0):
        raise InputError("time must increase from sample to sample")
    return t, u


def float_or_inf(value: float | int) -> float:
    """float(value), or +-inf for an integer too large for a float (float() raises OverflowError)."""
    try:
        return float(value)
    except OverflowError:
        return math.inf if value > 0 else -math.inf


def shown_number(value: object, limit: int = 40) -> str:
    """repr(value) for a message, cut to `limit` characters (a 400-digit integer stays one short line)."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text):,} characters)"


def finite_value(value: object, name: str, family: str) -> float:
    """value as a float; one InputError line naming the family's parameter unless it is a finite number."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not math.isfinite(float_or_inf(value)):
        raise InputError(f"{family} {name} must be a finite number, got {shown_number(value)}")
    return float(value)
