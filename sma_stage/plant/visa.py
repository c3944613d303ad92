"""The stage on real instruments over SCPI (PyVISA with the pure-Python pyvisa-py backend): a programmable
supply for the heating current, a relay that routes it to wire A or wire B, and a multimeter or DAQ reading
the displacement sensor. Command templates, resources, limits and scaling come from a YAML file
(config/hardware_example.yaml; docs/hardware.md) read by `visa_config`.

Safety lives here, not in the node: the relay moves only at zero current (read back) and after a settle time
(break before make), each wire has a current cap and an I^2 t (heating) budget, every read has a finite
timeout, and each cycle polls the instruments' error queues and the supply's protection trip.
"""

from __future__ import annotations

import math
import socket
import time
from collections.abc import Callable, Mapping

from sma_stage.plant.hardware import (
    STAGE_POSITION,
    STAGE_VELOCITY,
    WIRE_A_CURRENT,
    WIRE_B_CURRENT,
    HardwareError,
    Reading,
    StageHardware,
    signed_current,
    wire_commands,
)
from sma_stage.plant.visa_config import WIRES, BridgeConfig, InstrumentConfig

MAX_ERRORS_DRAINED = 20  # SYST:ERR? is read until "0,..." or this many entries


def open_with_pyvisa(config: InstrumentConfig, timeout_ms: float) -> object:
    """A pyvisa resource for the instrument, through the pure-Python pyvisa-py backend ("@py")."""
    import pyvisa

    manager = pyvisa.ResourceManager("@py")
    resource = manager.open_resource(config.resource, read_termination=config.read_termination,
                                     write_termination=config.write_termination, timeout=timeout_ms,
                                     open_timeout=timeout_ms)
    _no_delay(resource)
    return resource


def _no_delay(resource: object) -> None:
    """TCP_NODELAY on a raw-socket resource: without it Nagle's algorithm holds a small command behind the
    previous one's acknowledgement, up to 40 ms. pyvisa-py 0.8.1 wires VI_ATTR_TCPIP_NODELAY's setter to a
    method that raises, so the option is set on its socket."""
    session = getattr(getattr(resource, "visalib", None), "sessions", {}).get(getattr(resource, "session", None))
    connection = getattr(session, "interface", None)
    if isinstance(connection, socket.socket):
        connection.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


def _visa_errors() -> tuple[type[BaseException], ...]:
    try:
        from pyvisa.errors import VisaIOError
    except ImportError:  # pragma: no cover -- pyvisa is a pinned requirement
        return (OSError,)
    return (VisaIOError, OSError, UnicodeDecodeError)


class ScpiInstrument:
    """One SCPI instrument: write, query with the resource's finite timeout, drain the error queue. Every
    failure is a HardwareError naming the instrument and the command."""

    def __init__(self, config: InstrumentConfig, resource: object) -> None:
        self.config = config
        self.name = config.name
        self._resource = resource
        self._errors = _visa_errors()
        # False while a command is under way, and after one that did not end cleanly (a timeout, a lost
        # connection, Ctrl-C in the middle of a send): a late reply or half a command may be on the line.
        self.in_sync = True

    def write(self, command: str) -> None:
        """Send a command."""
        self.in_sync = False
        try:
            self._resource.write(command)
        except self._errors as error:
            raise HardwareError(f"{self.name}: cannot send {command!r}: {_describe(error)}") from None
        self.in_sync = True

    def query(self, command: str) -> str:
        """Send a query and return the stripped reply."""
        self.in_sync = False
        try:
            reply = self._resource.query(command)
        except self._errors as error:
            raise HardwareError(f"{self.name}: no reply to {command!r}: {_describe(error)}") from None
        self.in_sync = True
        return str(reply).strip()

    def query_number(self, command: str) -> float:
        """A query whose reply is one finite number."""
        reply = self.query(command)
        try:
            value = float(reply.split(",")[0])
        except ValueError:
            value = math.nan
        if not math.isfinite(value):
            raise HardwareError(f"{self.name}: reply to {command!r} is not a number: {reply[:40]!r}")
        return value

    def query_flag(self, command: str) -> bool:
        """A query whose reply is ON/OFF, 1/0 or YES/NO."""
        reply = self.query(command)
        word = reply.upper().lstrip("+")
        if word in ("1", "ON", "YES", "TRUE"):
            return True
        if word in ("0", "OFF", "NO", "FALSE"):
            return False
        raise HardwareError(f"{self.name}: reply to {command!r} is not ON/OFF: {reply[:40]!r}")

    def errors(self) -> list[str]:
        """The entries in the instrument's error queue (it is left empty)."""
        found = []
        for _ in range(MAX_ERRORS_DRAINED):
            reply = self.query(self.config.error_query)
            code = reply.split(",", 1)[0].strip().lstrip("+")
            try:
                number = int(code)
            except ValueError:
                raise HardwareError(f"{self.name}: reply to {self.config.error_query!r} is not an error entry: "
                                    f"{reply[:40]!r}") from None
            if number == 0:
                return found
            found.append(reply)
        return found

    def close(self) -> None:
        """Close the connection (never raises)."""
        try:
            self._resource.close()
        except Exception:  # noqa: BLE001 -- closing a broken connection is best effort
            pass


def _describe(error: BaseException) -> str:
    text = " ".join(str(error).split()) or type(error).__name__
    return text[:120]


class I2tBudget:
    """A wire's heat as I^2 t [A^2 s] that decays with a time constant: heat <- heat e^(-dt/tau) + I^2 dt."""

    def __init__(self, budget_a2s: float, time_constant_s: float) -> None:
        self.budget_a2s = budget_a2s
        self.time_constant_s = time_constant_s
        self.heat_a2s = 0.0

    def add(self, current_a: float, dt_s: float) -> None:
        """Account for current_a [A] flowing for dt_s [s]."""
        self.heat_a2s = self.heat_a2s * math.exp(-dt_s / self.time_constant_s) + current_a * current_a * dt_s

    def allowed_a(self, cap_a: float) -> float:
        """The current [A] allowed now: the cap, or the continuous level once the budget is spent."""
        if self.heat_a2s < self.budget_a2s:
            return cap_a
        return min(cap_a, math.sqrt(self.budget_a2s / self.time_constant_s))


Opener = Callable[[InstrumentConfig, float], object]


class VisaStage(StageHardware):
    """The two-wire stage on SCPI instruments: supply, relay and displacement reading (see the module doc).

    time_scale: stage seconds per host second; 1 for a real stage (a loopback test server may run faster).
    """

    kind = "visa"

    def __init__(self, config: BridgeConfig, opener: Opener = open_with_pyvisa, time_scale: float = 1.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.config = config
        self._opener = opener
        self.time_scale = time_scale
        self._clock = clock
        self.instruments: dict[str, ScpiInstrument] = {}
        self.identity: dict[str, str] = {}
        self._budgets = {wire: I2tBudget(config.limits.i2t_budget_a2s, config.limits.i2t_time_constant_s)
                         for wire in WIRES}
        self._reset_state()

    def _reset_state(self) -> None:
        self.relay = "open"
        self.output_on = False
        self.set_current_a = None  # the value last sent to the supply [A]; None: unknown
        self.readback_a = 0.0
        self.readback_v = 0.0
        self._zero_since: float | None = None
        self._relay_moved_at = -math.inf
        self._t0 = self._clock()
        self._last_read: tuple[float, float] | None = None
        self.trips = 0
        self.errors_seen: list[str] = []
        self.limited = {wire: False for wire in WIRES}

    # -- connection ---------------------------------------------------------------------------------
    def connect(self) -> dict[str, str]:
        self.close()
        self._reset_state()
        try:
            for name, config in self.config.instruments.items():
                self.instruments[name] = ScpiInstrument(config, self._open(config))
            for instrument in self.instruments.values():
                instrument.write("*RST")
                instrument.write("*CLS")
                self.identity[instrument.name] = instrument.query("*IDN?")
                for command in instrument.config.setup:
                    instrument.write(self._fill(command, 0.0))
            self._switch_off()
            self._check_error_queues()
        except HardwareError:
            self.close()
            raise
        return dict(self.identity)

    def _open(self, config: InstrumentConfig) -> object:
        try:
            return self._opener(config, self.config.timeout_ms)
        except Exception as error:  # noqa: BLE001 -- pyvisa raises many kinds for a resource it cannot open
            raise HardwareError(f"{config.name}: cannot connect to {config.resource}: {_describe(error)}") from None

    def close(self) -> None:
        for instrument in self.instruments.values():
            instrument.close()
        self.instruments = {}
        self.output_on = False

    @property
    def connected(self) -> bool:
        """True between a successful connect() and close()."""
        return bool(self.instruments)

    # -- commands -------------------------------------------------------------------------------------
    def _fill(self, template: str, current_a: float) -> str:
        supply = self.config.supply
        return template.format(current_a=current_a, voltage_v=supply.voltage_compliance_v,
                               protection_a=supply.protection_a)

    def _supply(self) -> ScpiInstrument:
        return self._instrument(self.config.supply.instrument)

    def _instrument(self, name: str) -> ScpiInstrument:
        try:
            return self.instruments[name]
        except KeyError:
            raise HardwareError(f"{name}: not connected") from None

    def _send_current(self, current_a: float) -> None:
        if current_a == self.set_current_a:
            return
        self._supply().write(self._fill(self.config.supply.commands["set_current"], current_a))
        self.set_current_a = current_a
        if current_a == 0.0:
            self._zero_since = self._clock()
        else:
            self._zero_since = None

    def _move_relay(self, position: str) -> None:
        relay = self._instrument(self.config.relay.instrument)
        for command in self.config.relay.commands[position]:
            relay.write(command)
        self.relay = position
        self._relay_moved_at = self._clock()

    def _switch_off(self) -> None:
        self._send_current(0.0)
        self._supply().write(self.config.supply.commands["output_off"])
        self.output_on = False
        self._move_relay("open")

    def enable(self) -> None:
        self._send_current(0.0)
        self._supply().write(self.config.supply.commands["output_on"])
        self.output_on = True

    def write(self, commands: Mapping[str, float]) -> None:
        current_a = signed_current(commands) if self.output_on else 0.0
        wanted = "wire_a" if current_a > 0.0 else "wire_b" if current_a < 0.0 else None
        if wanted is None:
            self._send_current(0.0)
        else:
            if wanted != self.relay:
                self._break_before_make(wanted)
            if wanted != self.relay or self._clock() - self._relay_moved_at < self.config.relay.settle_s:
                self._send_current(0.0)
            else:
                self._send_current(self._limited(wanted, abs(current_a)))

    def _break_before_make(self, wanted: str) -> None:
        """Toward moving the relay: zero the current; move only once it has been zero (commanded for
        zero_settle_s and read back below zero_current_a)."""
        self._send_current(0.0)
        limits = self.config.limits
        settled = self._zero_since is not None and self._clock() - self._zero_since >= limits.zero_settle_s
        if settled and abs(self.readback_a) <= limits.zero_current_a:
            self._move_relay(wanted)

    def _limited(self, wire: str, current_a: float) -> float:
        allowed = self._budgets[wire].allowed_a(self.config.limits.max_current_a[wire])
        self.limited[wire] = current_a > allowed
        return min(current_a, allowed)

    # -- state ------------------------------------------------------------------------------------------
    def read(self, period_s: float) -> Reading:
        now, read_ns = self._clock(), time.time_ns()
        supply, commands = self._supply(), self.config.supply.commands
        position = self.config.position
        raw = self._instrument(position.instrument).query_number(position.query)
        position_m = position.scale_m_per_unit * raw + position.offset_m
        self.readback_a = abs(supply.query_number(commands["measure_current"]))
        self.readback_v = supply.query_number(commands["measure_voltage"])
        self._check_error_queues()
        if supply.query_flag(commands["tripped"]):
            self.trips += 1
            raise HardwareError(f"{supply.name}: over-current protection tripped "
                                f"(protection at {self.config.supply.protection_a:g} A)")
        time_s = (now - self._t0) * self.time_scale
        velocity = 0.0
        if self._last_read is not None and time_s > self._last_read[0]:
            velocity = (position_m - self._last_read[1]) / (time_s - self._last_read[0])
            for wire in WIRES:
                flowing = self.readback_a if wire == self.relay else 0.0
                self._budgets[wire].add(flowing, (time_s - self._last_read[0]) / self.time_scale)
        self._last_read = (time_s, position_m)
        applied = self.readback_a if self.relay == "wire_a" else -self.readback_a if self.relay == "wire_b" else 0.0
        return Reading(time_s, {**wire_commands(applied), STAGE_POSITION: position_m, STAGE_VELOCITY: velocity},
                       read_ns)

    def _check_error_queues(self) -> None:
        for instrument in self.instruments.values():
            errors = instrument.errors()
            if errors:
                self.errors_seen.extend(f"{instrument.name}: {entry}" for entry in errors)
                del self.errors_seen[:-10]
                raise HardwareError(f"{instrument.name} reports an error: {errors[0]}"
                                    + (f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""))

    # -- stopping -------------------------------------------------------------------------------------
    def stop(self) -> None:
        """Zero current, output off, relay open (each tried even if one fails; a connection that is lost or
        out of step is opened again first), then confirm all three by reading back; HardwareError naming what
        is not."""
        problems = self._reopen_out_of_step()
        if not problems:
            problems = self._try_switch_off()
            if problems and any("cannot send" in p or "not connected" in p for p in problems):
                problems = self._reopen_all() or self._try_switch_off()
        if not problems:
            problems = self._unconfirmed()
        if problems:
            raise HardwareError("could not confirm the output off: " + "; ".join(problems))

    def _reopen_out_of_step(self) -> list[str]:
        """Open again the supply and the relay's instrument if their last command did not end cleanly (all, when
        none is open); an out-of-step position reader is left for the next connect, so the output goes off
        without waiting for it."""
        if not self.instruments:
            return self._reopen_all()
        needed = {self.config.supply.instrument, self.config.relay.instrument}
        for name, instrument in list(self.instruments.items()):
            if name in needed and not instrument.in_sync:
                instrument.close()
                try:
                    self.instruments[name] = ScpiInstrument(instrument.config, self._open(instrument.config))
                except HardwareError as error:
                    return [str(error)]
        return []

    def _reopen_all(self) -> list[str]:
        self.close()
        try:
            for name, config in self.config.instruments.items():
                self.instruments[name] = ScpiInstrument(config, self._open(config))
        except HardwareError as error:
            self.close()
            return [str(error)]
        return []

    def _try_switch_off(self) -> list[str]:
        problems = []
        supply_commands = self.config.supply.commands
        self.set_current_a = None  # send the zero whatever was sent before
        steps = (lambda: self._send_current(0.0),
                 lambda: self._supply().write(supply_commands["output_off"]),
                 lambda: self._move_relay("open"))
        for step in steps:
            try:
                step()
            except HardwareError as error:
                problems.append(str(error))
        self.output_on = False
        return problems

    def _unconfirmed(self) -> list[str]:
        supply, commands = self._supply(), self.config.supply.commands
        problems = []
        try:
            if supply.query_flag(commands["output_state"]):
                problems.append(f"{supply.name}: output still on")
            current = abs(supply.query_number(commands["measure_current"]))
            if current > self.config.limits.zero_current_a:
                problems.append(f"{supply.name}: {current:g} A still flowing")
            relay = self._instrument(self.config.relay.instrument)
            closed = [wire for wire, query in self.config.relay.state_queries.items() if relay.query_flag(query)]
            if closed:
                problems.append(f"{relay.name}: relay still on {', '.join(closed)}")
        except HardwareError as error:
            problems.append(str(error))
        return problems

    def status(self) -> dict[str, object]:
        values: dict[str, object] = {f"{name}_identity": identity for name, identity in self.identity.items()}
        values.update({
            "connected": self.connected,
            "output_on": self.output_on,
            "relay": self.relay,
            "set_current_a": self.set_current_a if self.set_current_a is not None else "unknown",
            "readback_current_a": self.readback_a,
            "readback_voltage_v": self.readback_v,
            # the heated wire's resistance with its leads: a broken wire reads the compliance voltage and no current
            "wire_resistance_ohm": round(self.readback_v / self.readback_a, 4) if self.readback_a > 0.05 else "n/a",
            "protection_trips": self.trips,
            "instrument_errors": " | ".join(self.errors_seen) or "none",
        })
        for wire in WIRES:
            values[f"{wire}_i2t_a2s"] = round(self._budgets[wire].heat_a2s, 6)
            values[f"{wire}_i2t_limited"] = self.limited[wire]
        return values


__all__ = ["HardwareError", "I2tBudget", "ScpiInstrument", "VisaStage", "WIRE_A_CURRENT", "WIRE_B_CURRENT",
           "open_with_pyvisa"]
