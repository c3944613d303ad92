"""The hardware bridge without ROS: the YAML, the exact SCPI it sends, and the loopback rig reached through
pyvisa-py over TCP (break before make, limits, every fault ending with the output off)."""

import math
import re
import time
from pathlib import Path

import pytest
import yaml
from scpi_server import LoopbackRig

from sma_stage.errors import InputError
from sma_stage.plant import Effects, StageConfig
from sma_stage.plant.hardware import HardwareError, SimulatedHardware, wire_commands
from sma_stage.plant.visa import I2tBudget, VisaStage
from sma_stage.plant.visa_config import bridge_config, load_bridge_config

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "config" / "hardware_example.yaml"
TIMEOUT_MS = 200.0


def example() -> dict:
    return yaml.safe_load(EXAMPLE.read_text())


def rig_config(rig: LoopbackRig, **limits) -> dict:
    """The shipped example with the rig's resource strings (and any limits changed)."""
    data = example()
    for name in ("supply", "meter"):
        data["instruments"][name]["resource"] = rig.resource(name)
    data["timeout_ms"] = TIMEOUT_MS
    data["limits"].update(limits)
    return data


# --- the YAML ---------------------------------------------------------------------------------------


def test_the_shipped_example_loads_with_its_limits():
    config = load_bridge_config(EXAMPLE)
    assert config.supply.commands["set_current"].format(current_a=1.5) == ":SOUR1:CURR 1.5000"
    assert config.relay.commands["open"] == (":OUTP CH2,OFF", ":OUTP CH3,OFF")
    assert config.limits.max_current_a == {"wire_a": 2.5, "wire_b": 2.5}
    assert config.limits.continuous_current_a() == pytest.approx(math.sqrt(40.0 / 11.0))
    assert config.timeout_ms == 200.0


@pytest.mark.parametrize(("change", "message"), [
    (lambda d: d["instruments"]["meter"].pop("resource"), r"instruments\.meter\.resource must be a VISA resource"),
    (lambda d: d["supply"].update(set_current=":SOUR1:CURR {amps}"), r"unknown field 'amps'"),
    (lambda d: d["supply"].update(set_current=":SOUR1:CURR {current_a"), r"bad command template"),
    (lambda d: d["supply"].update(protection_a=2.0), r"protection_a \(2 A\) must be above the wires' current caps"),
    (lambda d: d["limits"]["max_current_a"].update(wire_b=float("nan")), r"wire_b must be a finite number"),
    (lambda d: d["relay"].update(instrument="dmm"), r"relay\.instrument must name one of the instruments"),
    (lambda d: d["position"].update(scale_m_per_unit=0), r"scale_m_per_unit must be a finite non-zero number"),
    (lambda d: d["relay"]["commands"].pop("open"), r"relay\.commands\.open must be an SCPI command"),
    (lambda d: d.pop("limits"), r"limits must be a mapping"),
])
def test_a_bad_hardware_file_is_refused_in_one_line_naming_the_entry(tmp_path, change, message):
    data = example()
    change(data)
    path = tmp_path / "hw.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(InputError, match=message) as excinfo:
        load_bridge_config(path)
    assert str(excinfo.value).startswith(str(path)) and "\n" not in str(excinfo.value)


def test_a_missing_or_malformed_file_is_one_line(tmp_path):
    with pytest.raises(InputError, match="hardware file not found"):
        load_bridge_config(tmp_path / "none.yaml")
    (tmp_path / "bad.yaml").write_text("supply: [unclosed\n")
    with pytest.raises(InputError, match="not valid YAML") as excinfo:
        load_bridge_config(tmp_path / "bad.yaml")
    assert "\n" not in str(excinfo.value)


# --- the exact commands ------------------------------------------------------------------------------------


class ScriptedResource:
    """A pyvisa resource stand-in: records every command and answers queries from a table (shared log)."""

    def __init__(self, name: str, log: list, replies: dict) -> None:
        self.name, self.log, self.replies = name, log, replies

    def write(self, command: str) -> None:
        self.log.append((self.name, command))

    def query(self, command: str) -> str:
        self.log.append((self.name, command))
        return self.replies.get(command, "0")

    def close(self) -> None:
        self.log.append((self.name, "<close>"))


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def scripted_stage(replies=None):
    log: list = []
    table = {"*IDN?": "RIGOL,DP832,1,1", "SYST:ERR?": '0,"No error"', ":OUTP:OCP:QUES? CH1": "NO",
             ":OUTP? CH1": "OFF", ":OUTP? CH2": "OFF", ":OUTP? CH3": "OFF", ":MEAS:CURR? CH1": "0.0000",
             "READ?": "+5.000000000E+00"}
    table.update(replies or {})
    clock = FakeClock()
    stage = VisaStage(bridge_config(example()), opener=lambda config, timeout: ScriptedResource(config.name, log, table),
                      clock=clock)
    return stage, log, table, clock


def test_configure_resets_identifies_sets_up_and_leaves_everything_off():
    stage, log, _, _ = scripted_stage()
    identity = stage.connect()
    assert identity == {"supply": "RIGOL,DP832,1,1", "meter": "RIGOL,DP832,1,1"}
    assert log == [
        ("supply", "*RST"), ("supply", "*CLS"), ("supply", "*IDN?"),
        ("supply", ":SOUR1:VOLT 12.000"), ("supply", ":SOUR1:CURR 0"), ("supply", ":OUTP:OCP:VAL CH1,2.800"),
        ("supply", ":OUTP:OCP CH1,ON"), ("supply", ":SOUR2:VOLT 5"), ("supply", ":SOUR2:CURR 0.2"),
        ("supply", ":SOUR3:VOLT 5"), ("supply", ":SOUR3:CURR 0.2"),
        ("meter", "*RST"), ("meter", "*CLS"), ("meter", "*IDN?"),
        ("meter", "CONF:VOLT:DC 10"), ("meter", "VOLT:DC:NPLC 0.2"), ("meter", "TRIG:SOUR IMM"),
        ("supply", ":SOUR1:CURR 0.0000"), ("supply", ":OUTP CH1,OFF"),
        ("supply", ":OUTP CH2,OFF"), ("supply", ":OUTP CH3,OFF"),
        ("supply", "SYST:ERR?"), ("meter", "SYST:ERR?"),
    ]


def test_a_cycle_reads_position_current_error_queues_and_the_trip_and_scales_the_position():
    stage, log, _, _ = scripted_stage({"READ?": "+7.500000000E+00"})
    stage.connect()
    log.clear()
    before_ns = time.time_ns()
    reading = stage.read(0.01)
    assert before_ns <= reading.read_ns <= time.time_ns(), "stamped on the host's clock when it was read"
    assert log == [("meter", "READ?"), ("supply", ":MEAS:CURR? CH1"), ("supply", ":MEAS:VOLT? CH1"), ("supply", "SYST:ERR?"),
                   ("meter", "SYST:ERR?"), ("supply", ":OUTP:OCP:QUES? CH1")]
    assert reading.position_m == pytest.approx(2e-4 * 7.5 - 1e-3)


def test_a_sign_change_zeroes_the_current_then_moves_the_relay_then_waits_before_current_flows():
    stage, log, table, clock = scripted_stage()
    stage.connect()
    stage.enable()
    log.clear()
    stage.write(wire_commands(1.0))
    assert log == [], "the current was set to zero on configure, under zero_settle_s ago: the relay waits"
    clock.now += 0.01
    stage.write(wire_commands(1.0))
    assert log == [("supply", ":OUTP CH3,OFF"), ("supply", ":OUTP CH2,ON")]
    log.clear()
    stage.write(wire_commands(1.0))
    assert log == [], "no current during the relay's settle time"
    clock.now += 0.025
    stage.write(wire_commands(1.0))
    assert log == [("supply", ":SOUR1:CURR 1.0000")]
    table[":MEAS:CURR? CH1"] = "1.0000"
    stage.read(0.01)
    log.clear()
    stage.write(wire_commands(-1.0))
    assert log == [("supply", ":SOUR1:CURR 0.0000")], "break: the current goes to zero, the relay stays"
    clock.now += 0.05
    log.clear()
    stage.write(wire_commands(-1.0))
    assert log == [], "the relay waits for the read-back current to be zero"
    table[":MEAS:CURR? CH1"] = "0.0010"
    stage.read(0.01)
    log.clear()
    stage.write(wire_commands(-1.0))
    assert log == [("supply", ":OUTP CH2,OFF"), ("supply", ":OUTP CH3,ON")], "then make on wire B"
    clock.now += 0.025
    log.clear()
    stage.write(wire_commands(-1.0))
    assert log == [("supply", ":SOUR1:CURR 1.0000")]


def test_the_per_wire_cap_and_the_i2t_budget_limit_the_current():
    stage, log, table, clock = scripted_stage()
    stage.connect()
    stage.enable()
    clock.now += 0.01
    stage.write(wire_commands(4.0))
    clock.now += 0.025
    log.clear()
    stage.write(wire_commands(4.0))
    assert log == [("supply", ":SOUR1:CURR 2.5000")], "capped at wire A's 2.5 A"
    table[":MEAS:CURR? CH1"] = "2.5000"
    for _ in range(12):  # 2.5 A for 12 s heats past the 40 A^2 s budget
        clock.now += 1.0
        stage.read(1.0)
    log.clear()
    stage.write(wire_commands(4.0))
    assert log == [("supply", f":SOUR1:CURR {math.sqrt(40.0 / 11.0):.4f}")], "held to the continuous level"
    assert stage.status()["wire_a_i2t_limited"] is True


def test_the_i2t_heat_decays_with_its_time_constant():
    budget = I2tBudget(40.0, 10.0)
    budget.add(2.0, 5.0)
    assert budget.heat_a2s == pytest.approx(20.0)
    budget.add(0.0, 10.0)
    assert budget.heat_a2s == pytest.approx(20.0 * math.exp(-1.0))
    assert budget.allowed_a(2.5) == 2.5


def test_stop_confirms_by_reading_back_and_names_what_is_still_on():
    stage, log, table, _ = scripted_stage()
    stage.connect()
    stage.stop()
    table[":OUTP? CH1"] = "ON"
    table[":OUTP? CH3"] = "ON"
    with pytest.raises(HardwareError, match=r"supply: output still on; supply: relay still on wire_b"):
        stage.stop()


def test_an_error_in_a_queue_after_set_up_fails_the_configure_and_closes():
    stage, log, _, _ = scripted_stage({"SYST:ERR?": '-113,"Undefined header"'})
    with pytest.raises(HardwareError, match=r'^supply reports an error: -113,"Undefined header" \(and 19 more\)$'):
        stage.connect()
    assert not stage.connected and ("supply", "<close>") in log


def test_the_simulator_backend_applies_nothing_until_enabled():
    hardware = SimulatedHardware(StageConfig(), Effects(), 0)
    hardware.connect()
    hardware.write(wire_commands(2.0))
    assert hardware.read(0.1).current_a == 0.0
    hardware.enable()
    hardware.write(wire_commands(-2.0))
    assert hardware.read(0.1).current_a == -2.0
    hardware.stop()
    hardware.write(wire_commands(2.0))
    assert hardware.read(0.1).current_a == 0.0


# --- through pyvisa-py and the loopback rig -------------------------------------------------------------------


@pytest.fixture
def rig():
    with LoopbackRig(time_scale=20.0) as loopback:
        yield loopback


def run_cycles(stage: VisaStage, current_a: float, cycles: int, period_s: float = 0.01) -> None:
    for _ in range(cycles):
        stage.write(wire_commands(current_a))
        stage.read(period_s)
        time.sleep(period_s)


def test_the_bridge_runs_the_rig_and_never_closes_both_relays_under_current(rig):
    stage = VisaStage(bridge_config(rig_config(rig)), time_scale=rig.time_scale)
    identity = stage.connect()
    assert identity["supply"].startswith("RIGOL TECHNOLOGIES,DP832") and "34461A" in identity["meter"]
    stage.enable()
    for current in (2.0, -2.0, 1.0, -1.5, 2.0):
        run_cycles(stage, current, 15)
        assert rig.stage_current_a() == pytest.approx(current)
    relay_moves = [event for event in rig.events if event.kind == "relay" and event.detail.endswith("ON")]
    assert len(relay_moves) == 5
    assert all(event.current_a == 0.0 for event in relay_moves), "a relay closed while current flowed"
    assert rig.conflicts == 0
    stage.stop()
    assert not rig.output[1] and not rig.output[2] and not rig.output[3]
    stage.close()


FAULTS = [("meter", "drop", "no reply to 'READ?'"),
          ("meter", "garbage", "reply to 'READ?' is not a number"),
          ("meter", "late", "no reply to 'READ?'"),
          ("supply", "refuse", 'supply reports an error: -222,"Data out of range"'),
          ("supply", "trip", "over-current protection tripped")]


@pytest.mark.parametrize(("instrument", "kind", "message"), FAULTS)
def test_every_fault_ends_with_the_output_off_within_a_cycle_and_the_timeout(rig, instrument, kind, message):
    stage = VisaStage(bridge_config(rig_config(rig)), time_scale=rig.time_scale)
    stage.connect()
    stage.enable()
    run_cycles(stage, 1.5 if kind != "refuse" else 1.0, 10)
    assert rig.output[1] and rig.heating_current_a() > 0.0
    rig.inject(instrument, kind, delay_s=2 * TIMEOUT_MS / 1e3)
    started = time.monotonic()
    with pytest.raises(HardwareError, match=re.escape(message)):
        run_cycles(stage, 1.5, 5)
    stage.stop()
    elapsed_s = time.monotonic() - started
    assert not rig.output[1] and rig.heating_current_a() == 0.0 and not (rig.output[2] or rig.output[3])
    # one cycle (10 ms) plus the timeout, and the stop's own round trips; generous for a loaded machine
    assert elapsed_s < 0.01 + TIMEOUT_MS / 1e3 + 0.5, elapsed_s
    stage.close()


def test_a_rig_that_is_gone_fails_in_one_line_within_the_timeout(rig):
    stage = VisaStage(bridge_config(rig_config(rig)), time_scale=rig.time_scale)
    stage.connect()
    rig.stop()
    started = time.monotonic()
    with pytest.raises(HardwareError) as excinfo:
        stage.read(0.01)
    with pytest.raises(HardwareError, match="could not confirm the output off"):
        stage.stop()
    assert time.monotonic() - started < 4 * TIMEOUT_MS / 1e3 + 1.0
    assert "\n" not in str(excinfo.value)
