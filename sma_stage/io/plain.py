"""Plain Python values for JSON and YAML writers: numpy scalars as Python numbers, tuples as lists."""

from __future__ import annotations

import math

import numpy as np


def plain_values(value: object, non_finite_as_none: bool = False) -> object:
    """The value with numpy scalars as Python numbers and tuples as lists, nested; with non_finite_as_none,
    NaN and inf floats become None (strict JSON has neither)."""
    if isinstance(value, dict):
        return {key: plain_values(item, non_finite_as_none) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain_values(item, non_finite_as_none) for item in value]
    if isinstance(value, np.generic):
        value = value.item()
    if non_finite_as_none and isinstance(value, float) and not math.isfinite(value):
        return None
    return value
