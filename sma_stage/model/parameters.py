"""GPI model parameters a1..a11 (the source paper's eqs 4-5) and their YAML model file."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from sma_stage.errors import InputError
from sma_stage.model.checks import float_or_inf, shown_number

PARAMETER_NAMES: tuple[str, ...] = tuple(f"a{k}" for k in range(1, 12))
MODEL_KIND = "gpi"
DEFAULT_OPERATORS = 10
MAX_OPERATORS = 1000


@dataclass(frozen=True)
class GPIParameters:
    """Envelopes gl = a1 tanh(a2 v + a3) + a4, gr = a5 tanh(a6 v + a7) + a8 [output unit];
    thresholds r_i = a9 i; density p(r) = a10 exp(-a11 r), or free non-negative `weights` p_i, one per
    operator (the first above 0), which then stand for the density (a10 and a11 are kept, unused). Input v in A."""

    a1: float
    a2: float
    a3: float
    a4: float
    a5: float
    a6: float
    a7: float
    a8: float
    a9: float
    a10: float
    a11: float
    output_unit: str = "m"
    weights: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        for name in PARAMETER_NAMES:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
                raise InputError(f"GPI parameter {name} must be a number, got {value!r}")
            if not math.isfinite(float_or_inf(value)):
                raise InputError(f"GPI parameter {name} must be finite, got {shown_number(value)}")
            object.__setattr__(self, name, float(value))
        if self.a9 <= 0.0:
            raise InputError(f"GPI parameter a9 (threshold step) must be > 0, got {self.a9!r}")
        if not isinstance(self.output_unit, str) or not self.output_unit.strip():
            raise InputError(f"output_unit must be a non-empty string, got {self.output_unit!r}")
        if self.weights is not None:
            object.__setattr__(self, "weights", _checked_weights(self.weights))

    def as_array(self) -> np.ndarray:
        """The eleven parameters a1..a11 as a float array."""
        return np.array([getattr(self, name) for name in PARAMETER_NAMES])

    @classmethod
    def from_array(cls, values: np.ndarray, output_unit: str = "m") -> GPIParameters:
        """Parameters from eleven values a1..a11."""
        values = np.asarray(values, dtype=float).ravel()
        if values.size != len(PARAMETER_NAMES):
            raise InputError(f"expected {len(PARAMETER_NAMES)} GPI parameters, got {values.size}")
        return cls(*values.tolist(), output_unit=output_unit)

    def to_dict(self) -> dict[str, float | list[float]]:
        """The eleven parameters as a name-to-value mapping, and `weights` when free (output_unit left out)."""
        values: dict[str, float | list[float]] = {name: getattr(self, name) for name in PARAMETER_NAMES}
        if self.weights is not None:
            values["weights"] = list(self.weights)
        return values

    @classmethod
    def from_dict(cls, values: dict, output_unit: str = "m") -> GPIParameters:
        """Parameters from a mapping holding a1..a11 (and `weights`, optionally); unknown or missing names are
        refused."""
        if not isinstance(values, dict):
            raise InputError(f"GPI parameters must be a mapping of a1..a11, got {type(values).__name__}")
        missing = [name for name in PARAMETER_NAMES if name not in values]
        unknown = [key for key in values if key not in (*PARAMETER_NAMES, "weights")]
        if missing:
            raise InputError(f"GPI parameters missing: {', '.join(missing)}")
        if unknown:
            raise InputError(f"unknown GPI parameters: {', '.join(map(str, unknown))}")
        weights = values.get("weights")
        if weights is not None and not isinstance(weights, (list, tuple)):
            raise InputError(f"GPI parameter weights must be a list of numbers, got {type(weights).__name__}")
        return cls(**{name: values[name] for name in PARAMETER_NAMES}, output_unit=output_unit,
                   weights=tuple(weights) if weights is not None else None)

    def replace(self, **changes: float | str) -> GPIParameters:
        """A copy with some fields changed (validated again)."""
        values = asdict(self)
        values.update(changes)
        return GPIParameters(**values)

    def envelope_left(self, v: np.ndarray | float) -> np.ndarray:
        """gl(v) = a1 tanh(a2 v + a3) + a4, the loading envelope [output unit]; v in A."""
        return self.a1 * np.tanh(self.a2 * np.asarray(v, dtype=float) + self.a3) + self.a4

    def envelope_right(self, v: np.ndarray | float) -> np.ndarray:
        """gr(v) = a5 tanh(a6 v + a7) + a8, the unloading envelope [output unit]; v in A."""
        return self.a5 * np.tanh(self.a6 * np.asarray(v, dtype=float) + self.a7) + self.a8

    def thresholds(self, operators: int) -> np.ndarray:
        """Thresholds r_i = a9 i for i = 0..operators-1 [output unit]."""
        return self.a9 * np.arange(check_operators(operators), dtype=float)

    def densities(self, operators: int) -> np.ndarray:
        """Weights p(r_i) = a10 exp(-a11 r_i) for each threshold, or the free weights [dimensionless]."""
        if self.weights is not None:
            if len(self.weights) != check_operators(operators):
                raise InputError(f"the model has {len(self.weights)} free weights and {operators} operators")
            return np.array(self.weights)
        return self.a10 * np.exp(-self.a11 * self.thresholds(operators))

    def invertibility_problems(self, operators: int = DEFAULT_OPERATORS) -> list[str]:
        """Why the model is not a monotone increasing map of the input (empty when it is)."""
        problems = []
        if self.a1 * self.a2 <= 0.0:
            problems.append("gl is not increasing (a1*a2 <= 0)")
        if self.a5 * self.a6 <= 0.0:
            problems.append("gr is not increasing (a5*a6 <= 0)")
        if self.weights is not None:
            if len(self.weights) != operators:
                problems.append(f"{len(self.weights)} free weights for {operators} operators")
        elif self.a10 <= 0.0:
            problems.append(f"density p(r) = a10 exp(-a11 r) is not positive (a10 = {self.a10:g})")
        elif not np.all(np.isfinite(self.densities(operators))):
            problems.append("density overflows at the largest threshold (a11 too negative)")
        return problems


def _checked_weights(weights: object) -> tuple[float, ...]:
    """Free density weights as floats: finite, not negative, the first above 0 (the inverse divides by it)."""
    values = []
    for index, value in enumerate(weights):
        if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
            raise InputError(f"GPI weight {index} must be a number, got {shown_number(value)}")
        number = float_or_inf(value)
        if not math.isfinite(number) or number < 0.0:
            raise InputError(f"GPI weight {index} must be finite and at least 0, got {shown_number(value)}")
        values.append(number)
    if not values or values[0] <= 0.0:
        raise InputError("free GPI weights need at least one value and a first weight above 0")
    return tuple(values)


def check_operators(operators: int) -> int:
    """The operator count as an int, refused unless 1 <= operators <= MAX_OPERATORS."""
    if isinstance(operators, bool) or not isinstance(operators, (int, np.integer)):
        raise InputError(f"operator count must be an integer, got {operators!r}")
    if not 1 <= operators <= MAX_OPERATORS:
        raise InputError(f"operator count must be between 1 and {MAX_OPERATORS}, got {operators}")
    return int(operators)
