"""The stage node's parameters (each with its descriptor's range and unit) and the backend they name: the
embedded simulator with its effects, or the SCPI bridge on its instruments' file."""

from __future__ import annotations

from dataclasses import fields

from sma_stage.errors import InputError
from sma_stage.nodes._common import Param, settings_type
from sma_stage.plant import Effects, StageConfig
from sma_stage.plant.hardware import SimulatedHardware, StageHardware

BACKENDS = ("sim", "visa")
AUTOSTART = ("auto", "active", "inactive", "unconfigured")
_EFFECT_UNITS = {"ambient_drift_k_per_s": "K/s", "ambient_drift_start_s": "s (simulated)", "sensor_delay_s": "s",
                 "creep_amplitude_m": "m", "creep_time_constant_s": "s", "creep_reference_m": "m",
                 "creep_start_s": "s (simulated)", "load_change_n": "N", "load_change_time_s": "s (simulated)"}


def effect_params() -> list[Param]:
    """One read-only parameter per simulator effect (Effects' fields, defaults and ranges)."""
    ranges = Effects._RANGES
    return [Param(item.name, float(item.default), f"simulator effect {item.name} [{_EFFECT_UNITS.get(item.name, '')}]",
                  *ranges[item.name], read_only=True) for item in fields(Effects)]


STAGE_PARAMS = [
    Param("backend", "sim", "stage backend: 'sim' (the embedded physics simulator) or 'visa' (SCPI instruments "
          "described by hardware_file)", read_only=True),
    Param("hardware_file", "", "the instruments' YAML file for backend 'visa' (config/hardware_example.yaml)",
          read_only=True),
    Param("autostart", "auto", "lifecycle state to reach at start: auto (active for sim, inactive for visa), "
          "active, inactive or unconfigured", read_only=True),
    Param("rate_hz", 50.0, "joint_states publication and control cycle rate [Hz, wall clock]", 1.0, 2000.0,
          read_only=True),
    Param("max_current", 5.0, "current limit [A]: commands are clamped to +-max_current", 0.0, 20.0),
    Param("command_timeout", 1.0, "no command within this time [s, steady clock]: current zeroed (sim) or "
          "node deactivated (visa)", 0.001, 3600.0),
    Param("reconnect_max_interval", 30.0, "after a hardware fault, reconnect attempts back off from 1 s up to "
          "this interval [s]; 0 disables reconnecting", 0.0, 3600.0, read_only=True),
    Param("seed", 0, "random seed of the simulated sensor noise", 0, 2**31 - 1, read_only=True),
    Param("time_scale", 1.0, "stage seconds per wall second (simulator; 1 on a real stage)", 0.001, 10000.0,
          read_only=True),
    Param("lockstep_timeout", 0.0, "simulator on use_sim_time: after publishing a state, wait up to this long "
          "[s, steady clock] for a current_cmd before the next step, while commands are coming (a controller "
          "answering each state: the compensator's control_trigger joint_states); 0: off", 0.0, 60.0,
          read_only=True),
    *effect_params(),
]
StageSettings = settings_type("StageSettings", STAGE_PARAMS)


def check_choice(name: str, value: str, known: tuple[str, ...]) -> str:
    """value, refused unless it is one of known."""
    if value not in known:
        raise InputError(f"parameter '{name}': unknown value {value!r} (known: {', '.join(known)})")
    return value


def make_hardware(values: StageSettings) -> StageHardware:
    """The backend the parameters name (InputError for a bad or missing hardware file)."""
    if check_choice("backend", values.backend, BACKENDS) == "sim":
        effects = Effects(**{item.name: getattr(values, item.name) for item in fields(Effects)})
        return SimulatedHardware(StageConfig(), effects, values.seed)
    from sma_stage.plant.visa import VisaStage
    from sma_stage.plant.visa_config import load_bridge_config

    if not values.hardware_file:
        raise InputError("parameter 'hardware_file': backend 'visa' needs the instruments' YAML file "
                         "(see config/hardware_example.yaml)")
    return VisaStage(load_bridge_config(values.hardware_file), time_scale=values.time_scale)
