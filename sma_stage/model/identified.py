"""The identified model: the GPI and the ordered chain of effects identification added to it, with where
the identification record left their states; one YAML form (`SCHEMA_VERSION`), read strictly.

Forward: the input effects (thermal_lag, delay) transform the current in the order found, the GPI (with
rate-dependent thresholds when `rate` is in) maps what they give to the output, and the output effects
(drift) add to it. A model file without effects is a plain GPI model (files written before the schema
had a version read as such).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import yaml

from sma_stage.errors import InputError
from sma_stage.io.atomic import atomic_write_text
from sma_stage.io.plain import plain_values
from sma_stage.io.safe_yaml import parse_yaml, read_text_file
from sma_stage.model.checks import checked_record, float_or_inf, shown_number
from sma_stage.model.effects import FREE_VALUES, START_KINDS, Effect, EffectState, rate_forward
from sma_stage.model.forward import forward_with_states
from sma_stage.model.parameters import (
    DEFAULT_OPERATORS,
    MODEL_KIND,
    GPIParameters,
    check_operators,
)

SCHEMA_VERSION = 1
TOP_KEYS = ("schema_version", "kind", "output_unit", "operators", "parameters", "effects", "state", "metadata")
EFFECT_KEYS = ("kind", "parameters")
STATE_KEYS = ("operators", "effects")
EFFECT_STATE_KEYS = ("time_s", "values")
HEADER = ("# sma_stage identified model: the GPI y = sum_i p(r_i) S_ri[v] (input in A, output in output_unit)\n"
          "# and the effects identification added to it, in order (see sma_stage.model.identified)\n")


@dataclass(frozen=True)
class ModelState:
    """Where a record left the model: the GPI's operator states [output unit] and each effect's state."""

    operators: tuple[float, ...]
    effects: tuple[EffectState, ...]

    def to_dict(self) -> dict[str, object]:
        """Plain values for YAML."""
        return {"operators": [float(value) for value in self.operators],
                "effects": [state.to_dict() for state in self.effects]}


@dataclass(frozen=True)
class Start:
    """How a record starts: `rest` (the current switched on one sample period before the first sample,
    every state at rest), `held` (held at the first current long enough to settle, reached from rest), or
    `free`: `values` are the last turning point of what the GPI sees [A] (its operators were brought
    from rest to it), then each effect's FREE_VALUES in the model's order."""

    kind: str = "rest"
    values: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if self.kind not in START_KINDS:
            raise InputError(f"unknown start {self.kind!r}; known: {', '.join(START_KINDS)}")
        object.__setattr__(self, "values", tuple(float(value) for value in self.values))


@dataclass(frozen=True)
class IdentifiedModel:
    """GPI parameters and operator count, the effects in the order found, the state at the end of the
    identification record (None: not known) and free-form metadata."""

    parameters: GPIParameters
    operators: int = DEFAULT_OPERATORS
    effects: tuple[Effect, ...] = ()
    state: ModelState | None = None
    metadata: Mapping[str, object] = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        if not isinstance(self.parameters, GPIParameters):
            raise InputError(f"parameters must be GPIParameters, got {type(self.parameters).__name__}")
        object.__setattr__(self, "operators", check_operators(self.operators))
        effects = tuple(self.effects)
        if not all(isinstance(effect, Effect) for effect in effects):
            raise InputError("effects must be Effect objects")
        kinds = [effect.kind for effect in effects]
        if len(set(kinds)) != len(kinds):
            raise InputError(f"an effect appears twice: {', '.join(kinds)}")
        object.__setattr__(self, "effects", effects)
        if self.parameters.weights is not None:
            if len(self.parameters.weights) != self.operators:
                raise InputError(f"the model has {len(self.parameters.weights)} free weights and {self.operators} "
                                 "operators")
            if "rate" in kinds:
                raise InputError("free GPI weights do not go with the rate effect (its thresholds take the density)")
        if self.state is not None:
            if len(self.state.operators) != self.operators or len(self.state.effects) != len(effects):
                raise InputError(f"state holds {len(self.state.operators)} operator states and "
                                 f"{len(self.state.effects)} effect states; the model has {self.operators} "
                                 f"and {len(effects)}")

    @property
    def output_unit(self) -> str:
        """The output's unit (the setpoint's, for a compensator)."""
        return self.parameters.output_unit

    @property
    def effect_names(self) -> list[str]:
        """The effects' kinds, in order."""
        return [effect.kind for effect in self.effects]

    def effect(self, kind: str) -> Effect | None:
        """The effect of this kind, or None."""
        return next((effect for effect in self.effects if effect.kind == kind), None)

    def without_state(self) -> IdentifiedModel:
        """The same model with no carried state."""
        return replace(self, state=None)

    # --- how a record starts ------------------------------------------------------------------

    @property
    def free_start_names(self) -> list[str]:
        """What a free start's values are, in order (units in the names)."""
        return ["gpi_turning_point_a"] + [f"{effect.kind}.{name}" for effect in self.effects
                                          for name in FREE_VALUES[effect.kind]]

    def start_state(self, t: np.ndarray, u: np.ndarray, start: Start) -> ModelState | None:
        """The state before a record (t [s], u [A]) that starts as `start` says (None: from rest)."""
        if start.kind == "rest":
            return None
        t, u = checked_record(t, u)
        if start.kind == "free" and len(start.values) != len(self.free_start_names):
            raise InputError(f"a free start of this model takes {len(self.free_start_names)} values "
                             f"({', '.join(self.free_start_names)}), got {len(start.values)}")
        free = list(start.values[1:])
        states, v, seen = [], u, float(u[0])
        for effect in self.effects:
            count = len(FREE_VALUES[effect.kind])
            values, free = tuple(free[:count]), free[count:]
            states.append(effect.start_state(t, v, start.kind, values))
            if effect.role == "input":
                seen = effect.settled(seen)
                v = effect.transform(t, v, states[-1])[0]
        turning = start.values[0] if start.kind == "free" else seen
        _, operators = forward_with_states(np.array([turning]), self.parameters, self.operators)
        return ModelState(tuple(float(z) for z in operators), tuple(states))

    def gpi_input(self, t: np.ndarray, u: np.ndarray, state: ModelState | None = None) -> np.ndarray:
        """What the GPI sees [A]: the current after every input effect, from rest or from state."""
        t, u = checked_record(t, u)
        v = u
        for index, effect in enumerate(self.effects):
            if effect.role == "input":
                v = effect.transform(t, v, None if state is None else state.effects[index])[0]
        return v

    def predict_from(self, t: np.ndarray, u: np.ndarray, start: Start) -> np.ndarray:
        """Output [output unit] for a record (t [s], u [A]) that starts as `start` says."""
        return self.predict(t, u, self.start_state(t, u, start))

    # --- forward -------------------------------------------------------------------------------

    def predict(self, t: np.ndarray, u: np.ndarray, state: ModelState | None = None) -> np.ndarray:
        """Output [output unit] for a record (t [s] increasing, u [A]): from an idle stage, or from state
        (e.g. self.state, to continue the identification record)."""
        return self.run(t, u, state)[0]

    def run(self, t: np.ndarray, u: np.ndarray, state: ModelState | None = None
            ) -> tuple[np.ndarray, ModelState]:
        """(output [output unit], the state at the record's last sample); see predict."""
        t, u = checked_record(t, u)
        effect_states = list(state.effects) if state is not None else [None] * len(self.effects)
        ends: list[EffectState | None] = [None] * len(self.effects)
        v = u
        for index, effect in enumerate(self.effects):
            if effect.role == "input":
                v, ends[index] = effect.transform(t, v, effect_states[index])
        operators = np.asarray(state.operators, dtype=float) if state is not None else None
        rate = self.effect("rate")
        if rate is None:
            output, operator_states = forward_with_states(v, self.parameters, self.operators, operators)
        else:
            index = self.effects.index(rate)
            currents, rates, ends[index] = rate.rate_input(t, v, effect_states[index])
            output, operator_states = rate_forward(currents, rates, self.parameters.as_array(), self.operators,
                                                   rate.parameters.get("rate_gain_s_per_A", 0.0), operators,
                                                   rate.parameters.get("rate_shift_m_s_per_A", 0.0))
            output = output[1:]
        for index, effect in enumerate(self.effects):
            if effect.role == "output":
                offset, ends[index] = effect.offset(t, effect_states[index])
                output = output + offset
        return output, ModelState(tuple(float(z) for z in operator_states), tuple(ends))

    # --- YAML ----------------------------------------------------------------------------------

    def to_dict(self) -> dict[str, object]:
        """The YAML document as plain values."""
        document: dict[str, object] = {
            "schema_version": SCHEMA_VERSION,
            "kind": MODEL_KIND,
            "output_unit": self.output_unit,
            "operators": self.operators,
            "parameters": self.parameters.to_dict(),
            "effects": [effect.to_dict() for effect in self.effects],
        }
        if self.state is not None:
            document["state"] = self.state.to_dict()
        if self.metadata:
            document["metadata"] = dict(self.metadata)
        return document

    def to_yaml_text(self) -> str:
        """The model file's text."""
        return HEADER + yaml.safe_dump(plain_values(self.to_dict()), sort_keys=False)

    def save(self, path: str | os.PathLike) -> None:
        """Write the model file atomically."""
        atomic_write_text(path, self.to_yaml_text())

    @classmethod
    def from_dict(cls, document: object) -> IdentifiedModel:
        """The model from a parsed YAML document; InputError naming the first unknown, misspelt or bad key."""
        mapping = _mapping(document, "the model", TOP_KEYS)
        version = mapping.get("schema_version", SCHEMA_VERSION)
        if version != SCHEMA_VERSION:
            raise InputError(f"schema_version {version!r} is not supported (this version reads {SCHEMA_VERSION})")
        kind = mapping.get("kind", MODEL_KIND)
        if kind != MODEL_KIND:
            raise InputError(f"model kind {kind!r} is not supported (expected {MODEL_KIND!r})")
        unit = mapping.get("output_unit", "m")
        params = GPIParameters.from_dict(mapping.get("parameters"), output_unit=unit)
        effects = tuple(_effect(entry, number) for number, entry in enumerate(_list(mapping.get("effects"), "effects")))
        metadata = mapping.get("metadata") or {}
        if not isinstance(metadata, dict):
            raise InputError("metadata must be a mapping")
        state = _state(mapping["state"]) if mapping.get("state") is not None else None
        return cls(params, mapping.get("operators", DEFAULT_OPERATORS), effects, state, metadata)

    @classmethod
    def from_yaml_text(cls, text: str) -> IdentifiedModel:
        """The model from YAML text (a model file's content, or the compensator's `model` parameter)."""
        return cls.from_dict(parse_yaml(text))


def load_model_file(path: str | os.PathLike) -> IdentifiedModel:
    """Read and check a model file (a regular file of YAML); any problem is one InputError line naming it."""
    text = read_text_file(path, "model file")
    try:
        return IdentifiedModel.from_yaml_text(text)
    except InputError as error:
        raise InputError(f"model file {Path(path)}: {error}") from None


def _mapping(value: object, what: str, keys: Sequence[str] | None = None) -> dict:
    if not isinstance(value, dict):
        raise InputError(f"{what}: expected a mapping" + (f" with keys {', '.join(keys)}" if keys else ""))
    if keys is not None:
        unknown = [key for key in value if key not in keys]
        if unknown:
            raise InputError(f"unknown key {unknown[0]!r} in {what} (known: {', '.join(keys)})")
    return value


def _list(value: object, what: str) -> list:
    if value is None:
        return []
    if not isinstance(value, list):
        raise InputError(f"{what} must be a list")
    return value


def _effect(entry: object, number: int) -> Effect:
    mapping = _mapping(entry, f"effects[{number}]", EFFECT_KEYS)
    if "kind" not in mapping:
        raise InputError(f"effects[{number}] has no kind")
    return Effect(str(mapping["kind"]), _mapping(mapping.get("parameters") or {}, f"effects[{number}].parameters"))


def _state(entry: object) -> ModelState:
    mapping = _mapping(entry, "state", STATE_KEYS)
    operators = tuple(_number(value, "state.operators") for value in _list(mapping.get("operators"), "state.operators"))
    effects = []
    for number, item in enumerate(_list(mapping.get("effects"), "state.effects")):
        what = f"state.effects[{number}]"
        fields = _mapping(item, what, EFFECT_STATE_KEYS)
        time_s = fields.get("time_s")
        effects.append(EffectState(None if time_s is None else _number(time_s, f"{what}.time_s"),
                                   tuple(_number(value, f"{what}.values") for value in _list(fields.get("values"),
                                                                                              f"{what}.values"))))
    return ModelState(operators, tuple(effects))


def _number(value: object, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(float_or_inf(value)):
        raise InputError(f"{what} must hold finite numbers, got {shown_number(value)}")
    return float(value)
