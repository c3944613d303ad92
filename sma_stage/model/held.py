"""What a record leaves a model in whose input is a held current (the two-wire and the Bouc-Wen families; no
ROS): the last sample's time [s], the current applied from then [A] and the model's state vector."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sma_stage.errors import InputError
from sma_stage.model.parameters import float_or_inf, shown_number

STATE_KEYS = ("time_s", "current_a", "values")


@dataclass(frozen=True)
class HeldState:
    """Where a record left a held-current model: its last sample's time [s], the current applied from then [A]
    and the state vector (the family says what it holds)."""

    time_s: float
    current_a: float
    values: tuple[float, ...]

    def to_dict(self) -> dict[str, object]:
        """Plain values for YAML."""
        return {"time_s": self.time_s, "current_a": self.current_a, "values": [float(v) for v in self.values]}


def finite_value(value: object, name: str, family: str) -> float:
    """value as a float; one InputError line naming the family's parameter unless it is a finite number."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not math.isfinite(float_or_inf(value)):
        raise InputError(f"{family} {name} must be a finite number, got {shown_number(value)}")
    return float(value)


def held_state_from_dict(entry: object, family: str) -> HeldState:
    """A HeldState from a model file's `state` mapping; InputError naming the first bad key."""
    if not isinstance(entry, dict):
        raise InputError(f"{family} state must be a mapping")
    unknown = [str(key) for key in entry if key not in STATE_KEYS]
    if unknown:
        raise InputError(f"unknown key {unknown[0]!r} in the {family} state (known: {', '.join(STATE_KEYS)})")
    values = entry.get("values")
    if not isinstance(values, list):
        raise InputError(f"{family} state.values must be a list")
    return HeldState(finite_value(entry.get("time_s"), "state.time_s", family),
                     finite_value(entry.get("current_a"), "state.current_a", family),
                     tuple(finite_value(value, "state.values", family) for value in values))
