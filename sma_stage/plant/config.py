"""Physical parameters of the simulated stage (StageConfig) and the switchable effects (Effects).

SI units throughout: m, s, A, K, Pa, N. Sources of the defaults are in docs/simulator.md.
"""

import math
import numbers
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields

import numpy as np

from sma_stage.errors import InputError
from sma_stage.plant import physics as ph


def _check_range(owner: object, name: str, low: float, high: float) -> None:
    value = getattr(owner, name)
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise InputError(f"{type(owner).__name__}.{name} must be a number, got {value!r}")
    if not (math.isfinite(value) and low <= value <= high):
        raise InputError(f"{type(owner).__name__}.{name}={value!r} is outside [{low:g}, {high:g}]")


def _from_mapping(cls, values: Mapping[str, object]):
    known = {item.name for item in fields(cls)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise InputError(f"unknown {cls.__name__} parameter(s): {', '.join(unknown)}")
    return cls(**values)


@dataclass(frozen=True)
class StageConfig:
    """All physical parameters of the antagonistic two-wire NiTi stage, with documented defaults."""

    wire_diameter_m: float = 1.0e-3
    wire_length_a_m: float = 0.060
    wire_length_b_m: float = 0.056
    prestrain_a: float = 0.022
    prestrain_b: float = 0.021
    density_kg_m3: float = 6450.0
    specific_heat_j_kg_k: float = 450.0
    resistivity_martensite_ohm_m: float = 76e-8
    resistivity_austenite_ohm_m: float = 82e-8
    convection_w_m2_k: float = 50.0
    thermal_conductivity_w_m_k: float = 18.0
    ambient_temperature_k: float = 293.15
    youngs_modulus_austenite_pa: float = 70e9
    youngs_modulus_martensite_pa: float = 30e9
    recovery_strain: float = 0.045
    detwin_start_stress_pa: float = 70e6
    detwin_finish_stress_pa: float = 140e6
    stress_slope_austenite_pa_k: float = 8e6
    stress_slope_martensite_pa_k: float = 8e6
    martensite_finish_k: float = 278.15
    martensite_start_k: float = 291.15
    austenite_start_k: float = 293.15
    austenite_finish_k: float = 313.15
    lever_ratio: float = 1.8
    flexure_stiffness_n_m: float = 2.7e5
    max_current_a: float = 5.0
    sensor_noise_m: float = 0.2e-6
    sensor_resolution_m: float = 0.1e-6
    max_substep_s: float = 0.25
    wire_nodes: int = 16

    _RANGES = {
        "wire_diameter_m": (1e-5, 5e-3),
        "wire_length_a_m": (1e-3, 2.0),
        "wire_length_b_m": (1e-3, 2.0),
        "prestrain_a": (0.0, 0.08),
        "prestrain_b": (0.0, 0.08),
        "density_kg_m3": (1000.0, 20000.0),
        "specific_heat_j_kg_k": (100.0, 2000.0),
        "resistivity_martensite_ohm_m": (1e-8, 1e-5),
        "resistivity_austenite_ohm_m": (1e-8, 1e-5),
        "convection_w_m2_k": (1.0, 5000.0),
        "thermal_conductivity_w_m_k": (0.0, 500.0),
        "ambient_temperature_k": (200.0, 400.0),
        "youngs_modulus_austenite_pa": (1e9, 500e9),
        "youngs_modulus_martensite_pa": (1e9, 500e9),
        "recovery_strain": (0.001, 0.1),
        "detwin_start_stress_pa": (1e6, 1e9),
        "detwin_finish_stress_pa": (1e6, 2e9),
        "stress_slope_austenite_pa_k": (1e5, 1e8),
        "stress_slope_martensite_pa_k": (1e5, 1e8),
        "martensite_finish_k": (100.0, 600.0),
        "martensite_start_k": (100.0, 600.0),
        "austenite_start_k": (100.0, 600.0),
        "austenite_finish_k": (100.0, 600.0),
        "lever_ratio": (1e-3, 1e3),
        "flexure_stiffness_n_m": (1.0, 1e9),
        "max_current_a": (1e-3, 100.0),
        "sensor_noise_m": (0.0, 1e-2),
        "sensor_resolution_m": (0.0, 1e-2),
        "max_substep_s": (1e-5, 1.0),
        "wire_nodes": (1, 100),
    }

    def __post_init__(self) -> None:
        for item in fields(self):
            _check_range(self, item.name, *self._RANGES[item.name])
        if not float(self.wire_nodes).is_integer():
            raise InputError(f"StageConfig.wire_nodes must be a whole number, got {self.wire_nodes!r}")
        self._check_orderings()

    @classmethod
    def from_mapping(cls, values: Mapping[str, object]) -> "StageConfig":
        """Build from a dict (e.g. parsed YAML); unknown names or bad values raise InputError."""
        return _from_mapping(cls, values)

    def as_dict(self) -> dict[str, float]:
        """All fields by name (SI units)."""
        return asdict(self)

    def _check_orderings(self) -> None:
        pairs = [
            ("martensite_finish_k", "martensite_start_k"),
            ("austenite_start_k", "austenite_finish_k"),
            ("martensite_finish_k", "austenite_start_k"),
            ("martensite_start_k", "austenite_finish_k"),
            ("detwin_start_stress_pa", "detwin_finish_stress_pa"),
        ]
        for lower, upper in pairs:
            if not getattr(self, lower) < getattr(self, upper):
                raise InputError(f"StageConfig.{lower} must be below StageConfig.{upper}")

    @property
    def wire_area_m2(self) -> float:
        """Wire cross-section [m^2]."""
        return math.pi * self.wire_diameter_m**2 / 4.0

    @property
    def thermal_time_constant_s(self) -> float:
        """Slowest thermal mode [s] of wire A: convection, 4 h / (rho c d), plus conduction into the clamps."""
        heat_capacity = self.density_kg_m3 * self.specific_heat_j_kg_k
        convection = 4.0 * self.convection_w_m2_k / (heat_capacity * self.wire_diameter_m)
        conduction = self.thermal_conductivity_w_m_k / heat_capacity * (math.pi / self.wire_length_a_m) ** 2
        return 1.0 / (convection + conduction)

    def steady_temperature_rise_k(self, current_a: float) -> float:
        """Steady-state rise above ambient [K] of a fully austenitic wire carrying current_a [A], far from the clamps."""
        per_metre = current_a**2 * self.resistivity_austenite_ohm_m / self.wire_area_m2
        return per_metre / (self.convection_w_m2_k * math.pi * self.wire_diameter_m)


@dataclass(frozen=True)
class Effects:
    """Effects a user or a test can switch on (all off by default); nothing tells the identification."""

    ambient_drift_k_per_s: float = 0.0
    ambient_drift_start_s: float = 0.0
    sensor_delay_s: float = 0.0
    creep_amplitude_m: float = 0.0
    creep_time_constant_s: float = 200.0
    creep_reference_m: float = 0.5e-3
    creep_start_s: float = 0.0
    load_change_n: float = 0.0
    load_change_time_s: float = 0.0

    _RANGES = {
        "ambient_drift_k_per_s": (-1.0, 1.0),
        "ambient_drift_start_s": (0.0, 1e9),
        "sensor_delay_s": (0.0, 60.0),
        "creep_amplitude_m": (-1e-2, 1e-2),
        "creep_time_constant_s": (1e-3, 1e6),
        "creep_reference_m": (1e-7, 1.0),
        "creep_start_s": (0.0, 1e9),
        "load_change_n": (-1e4, 1e4),
        "load_change_time_s": (0.0, 1e9),
    }

    def __post_init__(self) -> None:
        for item in fields(self):
            _check_range(self, item.name, *self._RANGES[item.name])

    @classmethod
    def from_mapping(cls, values: Mapping[str, object]) -> "Effects":
        """Build from a dict (e.g. parsed YAML); unknown names or bad values raise InputError."""
        return _from_mapping(cls, values)

    def as_dict(self) -> dict[str, float]:
        """All fields by name (SI units)."""
        return asdict(self)


def pack_parameters(config: StageConfig, effects: Effects) -> np.ndarray:
    """The flat parameter vector the numba core reads (layout in physics.P_*)."""
    p = np.zeros(ph.N_PARAMETERS)
    area = config.wire_area_m2
    p[ph.P_HEAT_CAPACITY] = config.density_kg_m3 * config.specific_heat_j_kg_k * area
    p[ph.P_HEAT_LOSS] = config.convection_w_m2_k * math.pi * config.wire_diameter_m
    p[ph.P_RES_MARTENSITE] = config.resistivity_martensite_ohm_m / area
    p[ph.P_RES_AUSTENITE] = config.resistivity_austenite_ohm_m / area
    p[ph.P_E_AUSTENITE] = config.youngs_modulus_austenite_pa
    p[ph.P_E_MARTENSITE] = config.youngs_modulus_martensite_pa
    p[ph.P_RECOVERY_STRAIN] = config.recovery_strain
    p[ph.P_DETWIN_START] = config.detwin_start_stress_pa
    p[ph.P_DETWIN_FINISH] = config.detwin_finish_stress_pa
    p[ph.P_SLOPE_AUSTENITE] = config.stress_slope_austenite_pa_k
    p[ph.P_SLOPE_MARTENSITE] = config.stress_slope_martensite_pa_k
    p[ph.P_MF] = config.martensite_finish_k
    p[ph.P_MS] = config.martensite_start_k
    p[ph.P_AS] = config.austenite_start_k
    p[ph.P_AF] = config.austenite_finish_k
    p[ph.P_AREA] = area
    p[ph.P_LENGTH_A] = config.wire_length_a_m
    p[ph.P_LENGTH_B] = config.wire_length_b_m
    p[ph.P_PRESTRAIN_A] = config.prestrain_a
    p[ph.P_PRESTRAIN_B] = config.prestrain_b
    p[ph.P_LEVER] = config.lever_ratio
    p[ph.P_SPRING] = config.flexure_stiffness_n_m
    p[ph.P_AMBIENT] = config.ambient_temperature_k
    p[ph.P_MAX_CURRENT] = config.max_current_a
    p[ph.P_MAX_SUBSTEP] = config.max_substep_s
    p[ph.P_AMBIENT_DRIFT] = effects.ambient_drift_k_per_s
    p[ph.P_CREEP_AMPLITUDE] = effects.creep_amplitude_m
    p[ph.P_CREEP_TAU] = effects.creep_time_constant_s
    p[ph.P_CREEP_REFERENCE] = effects.creep_reference_m
    p[ph.P_LOAD_FORCE] = effects.load_change_n
    p[ph.P_LOAD_TIME] = effects.load_change_time_s
    p[ph.P_CONDUCTANCE] = config.thermal_conductivity_w_m_k * area
    p[ph.P_NODES] = int(config.wire_nodes)
    p[ph.P_AMBIENT_DRIFT_START] = effects.ambient_drift_start_s
    p[ph.P_CREEP_START] = effects.creep_start_s
    return p
