"""The models whose input is a held current (the two-wire and the Bouc-Wen families; no ROS): what a record
leaves them in (the last sample's time [s], the current applied from then [A], the state vector), running a
record, and their model files."""

from __future__ import annotations

import os
from dataclasses import dataclass, replace

import numpy as np
import yaml

from sma_stage.errors import InputError
from sma_stage.io.atomic import atomic_write_text
from sma_stage.io.plain import plain_values
from sma_stage.model.checks import checked_record, finite_value

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


TOP_KEYS = ("schema_version", "kind", "output_unit", "parameters", "state", "metadata")
SCHEMA_VERSION = 1


class HeldCurrentModel:
    """What the held-current families share (a frozen dataclass with `parameters`, `output_unit`, `state` and
    `metadata`, defining KIND, FAMILY (its name in messages), HEADER, `state_size`, `rest_state()`,
    `_advance_record(t, u, state_vector, held, first_step_s, out)` and `_parameters_from_dict(mapping)`):
    running a record from rest or a carried state, and the model file."""

    KIND = ""
    FAMILY = ""
    HEADER = ""

    def _check_common(self) -> None:
        if not isinstance(self.output_unit, str) or not self.output_unit.strip():
            raise InputError(f"output_unit must be a non-empty string, got {self.output_unit!r}")
        if self.state is not None and len(self.state.values) != self.state_size:
            raise InputError(f"{self.FAMILY} state holds {len(self.state.values)} values; the model has "
                             f"{self.state_size}")

    @property
    def kind(self) -> str:
        return self.KIND

    def without_state(self):  # noqa: ANN201 -- the subclass's own type
        """The same model with no carried state."""
        return replace(self, state=None)

    def run(self, t: np.ndarray, u: np.ndarray, state: HeldState | None = None) -> tuple[np.ndarray, HeldState]:
        """(output at each sample [output unit], the state at the last sample): from a stage long at rest (zero
        current up to the first sample), or from `state` (what an earlier record left: its current held until
        this record's first sample)."""
        t, u = checked_record(t, u)
        if state is None:
            values, held, first = self.rest_state(), 0.0, 0.0
        else:
            values, held = np.array(state.values, dtype=float), state.current_a
            first = float(t[0] - state.time_s)
            if first < 0.0:
                raise InputError(f"the record starts at {t[0]:g} s, before the carried state ({state.time_s:g} s)")
        out = np.empty(t.size)
        self._advance_record(t, u, values, held, first, out)
        return out, HeldState(float(t[-1]), float(u[-1]), tuple(values.tolist()))

    def predict(self, t: np.ndarray, u: np.ndarray, state: HeldState | None = None) -> np.ndarray:
        """Output [output unit] for a record (t [s] increasing, u [A]); see run."""
        return self.run(t, u, state)[0]

    def to_dict(self) -> dict[str, object]:
        """The YAML document as plain values."""
        document: dict[str, object] = {"schema_version": SCHEMA_VERSION, "kind": self.KIND,
                                       "output_unit": self.output_unit, "parameters": self.parameters.to_dict()}
        if self.state is not None:
            document["state"] = self.state.to_dict()
        if self.metadata:
            document["metadata"] = dict(self.metadata)
        return document

    def to_yaml_text(self) -> str:
        """The model file's text."""
        return self.HEADER + yaml.safe_dump(plain_values(self.to_dict()), sort_keys=False)

    def save(self, path: str | os.PathLike) -> None:
        """Write the model file atomically."""
        atomic_write_text(path, self.to_yaml_text())

    @classmethod
    def from_dict(cls, document: object):  # noqa: ANN206 -- the subclass's own type
        """The model from a parsed YAML document of this kind; InputError naming the first bad key."""
        if not isinstance(document, dict):
            raise InputError("the model: expected a mapping")
        unknown = [str(key) for key in document if key not in TOP_KEYS]
        if unknown:
            raise InputError(f"unknown key {unknown[0]!r} in the model (known: {', '.join(TOP_KEYS)})")
        if document.get("schema_version", SCHEMA_VERSION) != SCHEMA_VERSION:
            raise InputError(f"{cls.FAMILY} schema_version {document.get('schema_version')!r} is not supported")
        if document.get("kind") != cls.KIND:
            raise InputError(f"model kind {document.get('kind')!r} is not {cls.KIND!r}")
        metadata = document.get("metadata") or {}
        if not isinstance(metadata, dict):
            raise InputError("metadata must be a mapping")
        state = held_state_from_dict(document["state"], cls.FAMILY) if document.get("state") is not None else None
        return cls(cls._parameters_from_dict(document.get("parameters")), document.get("output_unit", "m"), state,
                   metadata)
