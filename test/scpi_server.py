"""A loopback instrument rig for the hardware bridge's tests: a supply like the Rigol DP832 (CH1 the heating
current, CH2/CH3 the coils of the relays K_A and K_B) and a multimeter like the Keysight 34461A reading a
displacement sensor, each speaking SCPI over TCP on 127.0.0.1 (an ephemeral port), coupled through the
project's stage simulator. Written from the instruments' command sets, not from the bridge's code.

Faults are injected with `LoopbackRig.inject(instrument, kind)`: "drop" (close the connection at the next
command), "garbage" (the next reply is not a number), "late" (the next reply comes after `delay_s`),
"refuse" (the next command is refused: an error in the queue), "trip" (an external short: the supply's
over-current protection trips). `events` is the time line of output, relay and current changes.

Run alone for a first check of a real set-up's YAML against it: `python test/scpi_server.py --time-scale 1`.
"""

from __future__ import annotations

import argparse
import copy
import re
import socket
import socketserver
import threading
import time
from collections import deque
from dataclasses import dataclass

from sma_stage.plant import Effects, StageConfig, StageSimulator

SENSOR_M_PER_V = 2.0e-4
SENSOR_OFFSET_M = -1.0e-3
NO_ERROR = '0,"No error"'
_LONG_FORMS = {"SOURCE": "SOUR", "CURRENT": "CURR", "VOLTAGE": "VOLT", "OUTPUT": "OUTP", "MEASURE": "MEAS",
               "SYSTEM": "SYST", "ERROR": "ERR", "QUESTION": "QUES", "VALUE": "VAL", "CONFIGURE": "CONF",
               "TRIGGER": "TRIG"}


def _short(command: str) -> str:
    """The command upper-cased, without a leading colon, long mnemonics shortened (SCPI accepts both)."""
    text = command.strip().upper().lstrip(":")
    return re.sub(r"[A-Z]+", lambda m: _LONG_FORMS.get(m.group(0), m.group(0)), text)


@dataclass
class Event:
    """One change on the rig: wall time [s], what changed, and the current flowing in CH1 then [A]."""

    time_s: float
    kind: str
    detail: str
    current_a: float


class LoopbackRig:
    """The supply, relays and meter around one simulated stage; its simulated time runs time_scale times the
    wall clock."""

    def __init__(self, time_scale: float = 1.0, seed: int = 0, effects: Effects | None = None) -> None:
        self.time_scale = time_scale
        self.simulator = StageSimulator(StageConfig(), effects or Effects(), seed)
        self.lock = threading.RLock()
        self.events: list[Event] = []
        self.faults: dict[str, deque] = {"supply": deque(), "meter": deque()}
        self.conflicts = 0  # both relays closed at once while current flowed
        self.commands: dict[str, list[str]] = {"supply": [], "meter": []}
        self._servers: dict[str, socketserver.ThreadingTCPServer] = {}
        self._connections: dict[str, list[socket.socket]] = {"supply": [], "meter": []}
        self._last_wall = time.monotonic()
        self._reset_supply()
        self._errors = {"supply": deque(), "meter": deque()}

    # -- the supply -------------------------------------------------------------------------------------
    def _reset_supply(self) -> None:
        self.voltage_v = {1: 0.0, 2: 0.0, 3: 0.0}
        self.current_set_a = {1: 0.0, 2: 0.0, 3: 0.0}
        self.output = {1: False, 2: False, 3: False}
        self.ocp_value_a, self.ocp_on, self.tripped = 3.3, False, False

    def heating_current_a(self) -> float:
        """The current CH1 delivers [A] (zero when off or tripped)."""
        return self.current_set_a[1] if self.output[1] and not self.tripped else 0.0

    def stage_current_a(self) -> float:
        """The signed current in the wires [A]: through K_A positive, through K_B negative, none when open."""
        relay_a, relay_b = self.output[2], self.output[3]
        current = self.heating_current_a()
        if relay_a and relay_b:
            return 0.0
        return current if relay_a else -current if relay_b else 0.0

    def _advance(self) -> None:
        now = time.monotonic()
        step_s = (now - self._last_wall) * self.time_scale
        self._last_wall = now
        if step_s > 0.0:
            self.simulator.step(self.stage_current_a(), step_s)

    def _note(self, kind: str, detail: str) -> None:
        self.events.append(Event(time.monotonic(), kind, detail, self.heating_current_a()))
        if self.output[2] and self.output[3] and self.heating_current_a() > 0.0:
            self.conflicts += 1

    def _supply(self, command: str) -> str | None:
        short = _short(command)
        channel_arg = re.fullmatch(r"(OUTP(?::OCP(?::QUES|:VAL|:CLE|:CLEAR)?)?)(\?)? ?(?:CH([123]))?(?:,(.+))?", short)
        source = re.fullmatch(r"(?:SOUR([123]):)?(CURR|VOLT) ([-+0-9.E]+)", short)
        if short == "*IDN?":
            return "RIGOL TECHNOLOGIES,DP832,DP8LOOPBACK,00.01.16"
        if short == "*RST":
            self._reset_supply()
            self._note("output", "reset")
            return None
        if short == "*CLS":
            self._errors["supply"].clear()
            return None
        if short == "SYST:ERR?":
            return self._errors["supply"].popleft() if self._errors["supply"] else NO_ERROR
        if source:
            channel, what, value = int(source.group(1) or 1), source.group(2), float(source.group(3))
            (self.current_set_a if what == "CURR" else self.voltage_v)[channel] = value
            if what == "CURR" and channel == 1:
                self._note("current", f"{value:g}")
            return None
        measure = re.fullmatch(r"MEAS:(CURR|VOLT)\? ?(?:CH([123]))?", short)
        if measure:
            channel = int(measure.group(2) or 1)
            if measure.group(1) == "CURR":
                flowing = self.heating_current_a() if channel == 1 else (0.05 if self.output[channel] else 0.0)
                return f"{flowing:.4f}"
            return f"{self.voltage_v[channel] if self.output[channel] else 0.0:.3f}"
        if channel_arg:
            return self._output_command(channel_arg.group(1), bool(channel_arg.group(2)),
                                        int(channel_arg.group(3) or 1), channel_arg.group(4))
        self._errors["supply"].append('-113,"Undefined header"')
        return None

    def _output_command(self, header: str, query: bool, channel: int, argument: str | None) -> str | None:
        if header == "OUTP" and query:
            return "ON" if self.output[channel] else "OFF"
        if header == "OUTP" and argument in ("ON", "OFF", "1", "0"):
            self.output[channel] = argument in ("ON", "1")
            if channel == 1 and self.output[1]:
                self.tripped = False
            self._note("output" if channel == 1 else "relay", f"CH{channel} {'ON' if self.output[channel] else 'OFF'}")
            self._check_protection()
            return None
        if header == "OUTP:OCP:VAL" and argument is not None:
            self.ocp_value_a = float(argument)
            return None
        if header == "OUTP:OCP" and argument in ("ON", "OFF", "1", "0"):
            self.ocp_on = argument in ("ON", "1")
            return None
        if header == "OUTP:OCP:QUES" and query:
            return "YES" if self.tripped else "NO"
        if header in ("OUTP:OCP:CLE", "OUTP:OCP:CLEAR"):
            self.tripped = False
            return None
        self._errors["supply"].append('-113,"Undefined header"')
        return None

    def _check_protection(self) -> None:
        if self.ocp_on and self.output[1] and self.current_set_a[1] > self.ocp_value_a:
            self._trip()

    def _trip(self) -> None:
        self.tripped = True
        self.output[1] = False
        self._note("output", "CH1 OFF (over-current protection)")

    # -- the meter ----------------------------------------------------------------------------------------
    def _meter(self, command: str) -> str | None:
        short = _short(command)
        if short == "*IDN?":
            return "Keysight Technologies,34461A,MY-LOOPBACK,A.03.01"
        if short in ("*RST", "TRIG:SOUR IMM") or short.startswith(("CONF:VOLT:DC", "VOLT:DC:NPLC")):
            return None
        if short == "*CLS":
            self._errors["meter"].clear()
            return None
        if short == "SYST:ERR?":
            return self._errors["meter"].popleft() if self._errors["meter"] else '+0,"No error"'
        if short in ("READ?", "MEAS:VOLT:DC?"):
            volts = (self.simulator.state.measured_position_m - SENSOR_OFFSET_M) / SENSOR_M_PER_V
            return f"{volts:+.9E}"
        self._errors["meter"].append('-113,"Undefined header"')
        return None

    # -- faults and serving -------------------------------------------------------------------------------
    def inject(self, instrument: str, kind: str, delay_s: float = 0.0) -> None:
        """Queue a fault for the instrument's next command (see the module doc)."""
        with self.lock:
            if kind == "trip":
                self._advance()
                self._trip()
                return
            self.faults[instrument].append((kind, delay_s))

    def handle(self, instrument: str, command: str) -> tuple[str | None, float, bool]:
        """Process one command line: (reply or None, delay before replying [s], drop the connection)."""
        with self.lock:
            self.commands[instrument].append(command)
            fault, delay_s = self.faults[instrument].popleft() if self.faults[instrument] else (None, 0.0)
            if fault == "drop":
                return None, 0.0, True
            self._advance()
            is_query = "?" in (command.split() or [""])[0]
            if fault == "refuse" and not is_query:
                self._errors[instrument].append('-222,"Data out of range"')
                return None, 0.0, False
            if fault == "refuse":
                self.faults[instrument].appendleft((fault, delay_s))
            reply = (self._supply if instrument == "supply" else self._meter)(command)
            if fault == "garbage" and reply is not None:
                reply = "#\x15?garbage"
            elif fault == "garbage":
                self.faults[instrument].appendleft((fault, delay_s))
            return reply, (delay_s if fault == "late" else 0.0), False

    def start(self) -> dict[str, int]:
        """Listen on 127.0.0.1 (ephemeral ports); the port of each instrument."""
        for instrument in ("supply", "meter"):
            self._servers[instrument] = _serve(self, instrument)
        return self.ports

    @property
    def ports(self) -> dict[str, int]:
        """The TCP port each instrument listens on."""
        return {name: server.server_address[1] for name, server in self._servers.items()}

    def resource(self, instrument: str) -> str:
        """The VISA resource string of an instrument (pyvisa-py raw socket)."""
        return f"TCPIP0::127.0.0.1::{self.ports[instrument]}::SOCKET"

    def simulator_equivalent(self, hardware: dict) -> dict:
        """A hardware YAML mapping pointed at this rig, allowing the simulated stage's 5 A range, with its relay
        and zero-current settle times divided by time_scale (the stage then sees a real relay's dead times)."""
        data = copy.deepcopy(hardware)
        for name in ("supply", "meter"):
            data["instruments"][name]["resource"] = self.resource(name)
        data["supply"]["protection_a"] = 5.5
        data["limits"].update(max_current_a={"wire_a": 5.0, "wire_b": 5.0}, i2t_budget_a2s=1e6,
                              zero_settle_s=data["limits"]["zero_settle_s"] / self.time_scale)
        data["relay"]["settle_s"] /= self.time_scale
        return data

    def stop(self) -> None:
        """Stop listening and close every connection."""
        for server in self._servers.values():
            server.shutdown()
            server.server_close()
        for sockets in self._connections.values():
            for connection in sockets:
                _close(connection)
        self._servers = {}

    def __enter__(self) -> LoopbackRig:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _close(connection: socket.socket) -> None:
    try:
        connection.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    connection.close()


def _serve(rig: LoopbackRig, instrument: str) -> socketserver.ThreadingTCPServer:
    class Handler(socketserver.StreamRequestHandler):
        def handle(self) -> None:
            rig._connections[instrument].append(self.connection)
            self.connection.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            for raw in self.rfile:
                reply, delay_s, drop = rig.handle(instrument, raw.decode("ascii", "replace").strip())
                if drop:
                    _close(self.connection)
                    return
                if delay_s:
                    time.sleep(delay_s)
                if reply is not None:
                    try:
                        self.wfile.write(reply.encode("ascii", "replace") + b"\n")
                    except OSError:
                        return

    server = socketserver.ThreadingTCPServer(("127.0.0.1", 0), Handler)
    server.daemon_threads = True
    threading.Thread(target=server.serve_forever, name=f"loopback-{instrument}", daemon=True).start()
    return server


def main() -> None:
    """Serve the rig until Ctrl-C, printing the resource strings to put in a hardware YAML."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--time-scale", type=float, default=1.0, help="simulated seconds per wall second")
    args = parser.parse_args()
    with LoopbackRig(time_scale=args.time_scale) as rig:
        for instrument in ("supply", "meter"):
            print(f"{instrument}: {rig.resource(instrument)}", flush=True)
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass


if __name__ == "__main__":
    main()
