"""The SCPI bridge's YAML file (config/hardware_example.yaml; docs/hardware.md) read and checked into frozen
settings: the instruments and their resources, the supply's, relay's and position reader's command templates,
the sensor's scaling and the per-wire safety limits."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from string import Formatter

from sma_stage.errors import InputError
from sma_stage.io.safe_yaml import load_yaml_file

WIRES = ("wire_a", "wire_b")
RELAY_POSITIONS = ("wire_a", "wire_b", "open")
SUPPLY_COMMANDS = ("set_current", "output_on", "output_off", "output_state", "measure_current", "measure_voltage",
                   "tripped")
TEMPLATE_FIELDS = {"current_a", "voltage_v", "protection_a"}


@dataclass(frozen=True)
class InstrumentConfig:
    """One instrument: its VISA resource string and the commands sent after *RST/*CLS on configure."""

    name: str
    resource: str
    setup: tuple[str, ...] = ()
    read_termination: str = "\n"
    write_termination: str = "\n"
    error_query: str = "SYST:ERR?"


@dataclass(frozen=True)
class SupplyConfig:
    """The heating supply: which instrument, its command templates, the voltage compliance [V] and the
    instrument's own over-current protection level [A]."""

    instrument: str
    commands: Mapping[str, str]
    voltage_compliance_v: float
    protection_a: float


@dataclass(frozen=True)
class RelayConfig:
    """The relay: the commands that put it on wire A, wire B or open, the queries that say which coil is on,
    and the settle time [s] after it moves."""

    instrument: str
    commands: Mapping[str, tuple[str, ...]]
    state_queries: Mapping[str, str]
    settle_s: float


@dataclass(frozen=True)
class PositionConfig:
    """The displacement reading: query, and position [m] = scale_m_per_unit * reading + offset_m."""

    instrument: str
    query: str
    scale_m_per_unit: float
    offset_m: float


@dataclass(frozen=True)
class Limits:
    """Per-wire current cap [A]; the I^2 t budget [A^2 s] of a wire's heat, which decays with
    i2t_time_constant_s [s]; the read-back current [A] that counts as zero; the time [s] the current must
    have been commanded to zero before the relay may move."""

    max_current_a: Mapping[str, float]
    i2t_budget_a2s: float
    i2t_time_constant_s: float
    zero_current_a: float
    zero_settle_s: float

    def continuous_current_a(self) -> float:
        """The current [A] a wire may carry for ever under its I^2 t budget."""
        return math.sqrt(self.i2t_budget_a2s / self.i2t_time_constant_s)


@dataclass(frozen=True)
class BridgeConfig:
    """The whole instrument set-up of config/hardware_*.yaml."""

    instruments: Mapping[str, InstrumentConfig]
    supply: SupplyConfig
    relay: RelayConfig
    position: PositionConfig
    limits: Limits
    timeout_ms: float = 500.0
    source: str = ""


def load_bridge_config(path: str | Path) -> BridgeConfig:
    """Read and check a hardware YAML file; InputError naming the file and the first bad entry."""
    path = Path(path)
    data = load_yaml_file(path, "hardware file")
    try:
        return bridge_config(data, str(path))
    except InputError as error:
        raise InputError(f"{path}: {error}") from None


def bridge_config(data: object, source: str = "") -> BridgeConfig:
    """A BridgeConfig from the parsed YAML mapping; InputError for the first missing or bad entry."""
    top = _mapping(data, "the file")
    instruments = {name: _instrument(name, entry) for name, entry in _mapping(top.get("instruments"),
                                                                              "instruments").items()}
    if not instruments:
        raise InputError("instruments: at least one instrument is needed")
    supply_data, relay_data = _mapping(top.get("supply"), "supply"), _mapping(top.get("relay"), "relay")
    position_data, limits_data = _mapping(top.get("position"), "position"), _mapping(top.get("limits"), "limits")
    supply = SupplyConfig(
        instrument=_instrument_name(supply_data, "supply", instruments),
        commands={name: _template(supply_data, name, "supply") for name in SUPPLY_COMMANDS},
        voltage_compliance_v=_positive(supply_data, "voltage_compliance_v", "supply"),
        protection_a=_positive(supply_data, "protection_a", "supply"),
    )
    relay_commands = _mapping(relay_data.get("commands"), "relay.commands")
    relay_states = _mapping(relay_data.get("state"), "relay.state")
    relay = RelayConfig(
        instrument=_instrument_name(relay_data, "relay", instruments),
        commands={position: _command_list(relay_commands, position, "relay.commands") for position in RELAY_POSITIONS},
        state_queries={wire: _template(relay_states, wire, "relay.state") for wire in WIRES},
        settle_s=_non_negative(relay_data, "settle_s", "relay"),
    )
    position = PositionConfig(
        instrument=_instrument_name(position_data, "position", instruments),
        query=_template(position_data, "query", "position"),
        scale_m_per_unit=_finite(position_data, "scale_m_per_unit", "position", nonzero=True),
        offset_m=_finite(position_data, "offset_m", "position"),
    )
    caps = _mapping(limits_data.get("max_current_a"), "limits.max_current_a")
    limits = Limits(
        max_current_a={wire: _positive(caps, wire, "limits.max_current_a") for wire in WIRES},
        i2t_budget_a2s=_positive(limits_data, "i2t_budget_a2s", "limits"),
        i2t_time_constant_s=_positive(limits_data, "i2t_time_constant_s", "limits"),
        zero_current_a=_positive(limits_data, "zero_current_a", "limits"),
        zero_settle_s=_non_negative(limits_data, "zero_settle_s", "limits"),
    )
    if supply.protection_a <= max(limits.max_current_a.values()):
        raise InputError(f"supply.protection_a ({supply.protection_a:g} A) must be above the wires' current caps "
                         f"({max(limits.max_current_a.values()):g} A): the instrument's protection is the last resort")
    timeout_ms = _positive(top, "timeout_ms", "the file") if "timeout_ms" in top else 500.0
    return BridgeConfig(instruments, supply, relay, position, limits, timeout_ms, source)


def _mapping(value: object, where: str) -> dict:
    if not isinstance(value, dict):
        raise InputError(f"{where} must be a mapping (key: value entries), got {type(value).__name__}")
    return value


def _instrument(name: object, entry: object) -> InstrumentConfig:
    entry = _mapping(entry, f"instruments.{name}")
    resource = entry.get("resource")
    if not isinstance(resource, str) or not resource.strip():
        raise InputError(f"instruments.{name}.resource must be a VISA resource string, e.g. "
                         "TCPIP0::192.168.1.20::5025::SOCKET")
    setup = entry.get("setup", [])
    if not isinstance(setup, list) or not all(isinstance(line, str) for line in setup):
        raise InputError(f"instruments.{name}.setup must be a list of SCPI commands")
    for line in setup:
        _check_template(line, f"instruments.{name}.setup")
    options = {key: entry[key] for key in ("read_termination", "write_termination", "error_query") if key in entry}
    for key, value in options.items():
        if not isinstance(value, str) or not value:
            raise InputError(f"instruments.{name}.{key} must be a non-empty string")
    return InstrumentConfig(str(name), resource.strip(), tuple(setup), **options)


def _instrument_name(data: dict, where: str, instruments: Mapping[str, InstrumentConfig]) -> str:
    name = data.get("instrument")
    if name not in instruments:
        raise InputError(f"{where}.instrument must name one of the instruments ({', '.join(instruments)}), "
                         f"got {name!r}")
    return name


def _template(data: dict, key: str, where: str) -> str:
    value = data.get(key)
    if not isinstance(value, str) or not value.strip():
        raise InputError(f"{where}.{key} must be an SCPI command string")
    _check_template(value, f"{where}.{key}")
    return value


def _command_list(data: dict, key: str, where: str) -> tuple[str, ...]:
    value = data.get(key)
    commands = [value] if isinstance(value, str) else value
    if not isinstance(commands, list) or not commands or not all(isinstance(c, str) and c.strip() for c in commands):
        raise InputError(f"{where}.{key} must be an SCPI command or a list of them")
    for command in commands:
        _check_template(command, f"{where}.{key}")
    return tuple(commands)


def _check_template(text: str, where: str) -> None:
    try:
        names = {name for _, name, _, _ in Formatter().parse(text) if name is not None}
        unknown = names - TEMPLATE_FIELDS
        if unknown:
            raise InputError(f"{where}: unknown field {sorted(unknown)[0]!r} in {text!r} "
                             f"(known: {', '.join(sorted(TEMPLATE_FIELDS))})")
        text.format(current_a=0.0, voltage_v=0.0, protection_a=0.0)
    except (ValueError, IndexError, KeyError) as error:
        raise InputError(f"{where}: bad command template {text!r}: {error}") from None


def _finite(data: dict, key: str, where: str, nonzero: bool = False) -> float:
    value = data.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or (nonzero and value == 0):
        raise InputError(f"{where}.{key} must be a finite{' non-zero' if nonzero else ''} number, got {value!r}")
    return float(value)


def _positive(data: dict, key: str, where: str) -> float:
    value = _finite(data, key, where)
    if value <= 0:
        raise InputError(f"{where}.{key} must be positive, got {value:g}")
    return value


def _non_negative(data: dict, key: str, where: str) -> float:
    value = _finite(data, key, where)
    if value < 0:
        raise InputError(f"{where}.{key} must be zero or positive, got {value:g}")
    return value
