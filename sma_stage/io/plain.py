"""Plain Python values for JSON and YAML writers: numpy scalars as Python numbers, tuples as lists."""

from __future__ import annotations

import json
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


def strict_json(value: object, indent: int | None = None) -> str:
    """The value as strict JSON text: numpy scalars as numbers, NaN and inf as null (never `Infinity`)."""
    return json.dumps(plain_values(value, non_finite_as_none=True), indent=indent, allow_nan=False)
