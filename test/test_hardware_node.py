"""The stage node as a managed node on the bridge, through the real stack: rclpy lifecycle services, the
bridge, pyvisa-py and the loopback SCPI rig on 127.0.0.1. In every case the output ends off and the node
says what happened."""

import os
import signal
import subprocess
import sys
import time

import pytest
import yaml

rclpy = pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from lifecycle_msgs.msg import Transition  # noqa: E402
from lifecycle_msgs.srv import ChangeState, GetState  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from scpi_server import LoopbackRig  # noqa: E402
from std_msgs.msg import Float64  # noqa: E402
from std_srvs.srv import SetBool  # noqa: E402
from test_hardware import rig_config  # noqa: E402
from test_nodes import REPO, Listener, Ros, read_until, unique_domain, wait_until  # noqa: E402

from sma_stage.errors import InputError  # noqa: E402
from sma_stage.nodes._common import COMMAND_QOS  # noqa: E402
from sma_stage.nodes.stage_node import StageNode  # noqa: E402

TIME_SCALE = 20.0


@pytest.fixture
def ros():
    harness = Ros()
    yield harness
    harness.close()


@pytest.fixture
def rig():
    with LoopbackRig(time_scale=TIME_SCALE) as loopback:
        yield loopback


def hardware_file(rig: LoopbackRig, tmp_path, timeout_ms: float | None = None, **limits) -> str:
    """The rig's hardware YAML (limits changed as given; timeout_ms: every read's, else the tests' 200 ms)."""
    config = rig_config(rig, **limits)
    if timeout_ms is not None:
        config["timeout_ms"] = timeout_ms
    path = tmp_path / "hardware.yaml"
    path.write_text(yaml.safe_dump(config))
    return str(path)


def bridge_node(ros: Ros, rig: LoopbackRig, tmp_path, **overrides) -> StageNode:
    values = {"backend": "visa", "hardware_file": hardware_file(rig, tmp_path), "rate_hz": 50.0,
              "time_scale": TIME_SCALE, "command_timeout": 5.0, **overrides}
    params = [Parameter(name, value=value) for name, value in values.items()]
    return ros.add(StageNode(context=ros.context, parameter_overrides=params))


def change_state(ros: Ros, probe: Node, transition: int) -> bool:
    request = ChangeState.Request()
    request.transition.id = transition
    return ros.call(probe, ChangeState, "/stage/change_state", request).success


def lifecycle_label(ros: Ros, probe: Node) -> str:
    return ros.call(probe, GetState, "/stage/get_state").current_state.label


def sender(probe: Node):
    publisher = probe.create_publisher(Float64, "current_cmd", COMMAND_QOS)
    return lambda value: publisher.publish(Float64(data=float(value)))


def output_off(rig: LoopbackRig) -> bool:
    return not rig.output[1] and rig.heating_current_a() == 0.0 and not (rig.output[2] or rig.output[3])


def test_the_bridge_waits_inactive_and_runs_through_the_lifecycle_services(rig, ros, tmp_path):
    stage = bridge_node(ros, rig, tmp_path)
    probe = ros.probe()
    assert lifecycle_label(ros, probe) == "inactive", "autostart auto: instruments wait, output off"
    assert output_off(rig) and stage.identity["supply"].startswith("RIGOL TECHNOLOGIES,DP832")
    send = sender(probe)
    wait_until(lambda: stage.count_publishers("current_cmd") >= 1, 5.0, "the command publisher")
    send(1.0)
    time.sleep(0.2)
    assert output_off(rig), "an inactive stage ignores commands"
    assert change_state(ros, probe, Transition.TRANSITION_ACTIVATE)
    for current in (1.0, -1.5, 0.5):
        send(current)
        wait_until(lambda c=current: rig.stage_current_a() == pytest.approx(c), 5.0, f"{current} A in the wires")
        wait_until(lambda c=current: stage.applied_a == pytest.approx(c), 5.0, "current_applied read back")
    assert rig.conflicts == 0
    assert not ros.call(probe, SetBool, "stage/freeze_time", SetBool.Request(data=True)).success, \
        "a real stage's time runs on"
    assert not stage.frozen
    assert change_state(ros, probe, Transition.TRANSITION_DEACTIVATE)
    assert output_off(rig) and lifecycle_label(ros, probe) == "inactive"
    assert change_state(ros, probe, Transition.TRANSITION_CLEANUP)
    assert lifecycle_label(ros, probe) == "unconfigured" and not stage.hardware.connected


NODE_FAULTS = [("meter", "drop", "meter: no reply to '"), ("meter", "garbage", "meter: reply to '"),
               ("meter", "late", "meter: no reply to '"),
               ("supply", "refuse", 'supply reports an error: -222,"Data out of range"'),
               ("supply", "trip", "supply: over-current protection tripped")]


@pytest.mark.parametrize(("instrument", "kind", "message"), NODE_FAULTS)
def test_a_fault_while_active_switches_off_and_a_reconnect_never_switches_on(rig, ros, tmp_path, instrument, kind,
                                                                             message):
    stage = bridge_node(ros, rig, tmp_path, autostart="active")
    probe = ros.probe()
    diagnostics = Listener(probe, DiagnosticArray, "/diagnostics")
    send = sender(probe)
    wait_until(lambda: stage.count_publishers("current_cmd") >= 1, 5.0, "the command publisher")
    send(1.5)
    wait_until(lambda: rig.heating_current_a() == 1.5, 5.0, "1.5 A flowing")
    rig.inject(instrument, kind, delay_s=0.4)
    faulted = time.monotonic()
    send(1.0)  # a new current: the supply gets a command (the refused one)
    wait_until(lambda: output_off(rig), 2.0, "the output off after the fault")
    off_s = min(e.time_s for e in rig.events if e.time_s > faulted and e.detail.startswith("CH1 OFF")) - faulted
    print(f"fault {kind}: output off {off_s * 1e3:.1f} ms after the fault was set")
    # one cycle (20 ms: the fault meets the next cycle's command) plus the timeout (200 ms), and 30 ms for
    # scheduling on a loaded machine (measured: at most 224 ms with two CPU-bound processes alongside)
    assert off_s < 0.02 + 0.2 + 0.03, "one cycle plus the timeout"
    wait_until(lambda: stage.lifecycle == "inactive", 10.0, "the reconnect (back-off 1 s)")
    send(1.5)
    time.sleep(0.3)
    assert output_off(rig), "reconnected but not activated: the output stays off"
    switched_on_after = [e for e in rig.events if e.time_s > faulted and e.kind == "output" and e.detail.endswith("ON")]
    assert switched_on_after == []
    wait_until(lambda: any(pair.key == "last_fault" and pair.value.startswith(message) for m in diagnostics.messages
                           for status in m.status for pair in status.values), 5.0, "the fault on /diagnostics")
    values = {pair.key: pair.value for pair in stage.diagnostic_status().values}
    assert values["faults"] == "1" and values["lifecycle_state"] == "inactive" and values["output_on"] == "False"


def test_the_watchdog_deactivates_the_bridge(rig, ros, tmp_path):
    stage = bridge_node(ros, rig, tmp_path, autostart="active", command_timeout=0.3)
    send = sender(ros.probe())
    wait_until(lambda: stage.count_publishers("current_cmd") >= 1, 5.0, "the command publisher")
    send(1.0)
    wait_until(lambda: rig.heating_current_a() == 1.0, 5.0, "1 A flowing")
    wait_until(lambda: stage.lifecycle == "inactive", 2.0, "the watchdog")
    assert output_off(rig) and stage.fault is None


def test_a_bad_hardware_file_is_one_line_at_start(ros, tmp_path):
    with pytest.raises(InputError, match=r"hardware_file.*needs the instruments' YAML file"):
        StageNode(context=ros.context, parameter_overrides=[Parameter("backend", value="visa")])
    (tmp_path / "hw.yaml").write_text("instruments: {}\n")
    with pytest.raises(InputError, match=r"hw\.yaml: instruments: at least one instrument is needed$"):
        StageNode(context=ros.context, parameter_overrides=[Parameter("backend", value="visa"),
                                                            Parameter("hardware_file", value=str(tmp_path / "hw.yaml"))])


def test_ctrl_c_switches_the_output_off(rig, tmp_path):
    """A separate process: Ctrl-C while the current flows ends with the output off, confirmed. Reads may take
    2 s here (a loaded CI machine once took longer than the tests' 200 ms, so the node faulted before
    the current flowed; the fault path has its own tests)."""
    domain = unique_domain()
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED="1")
    process = subprocess.Popen(
        [sys.executable, "-m", "sma_stage.nodes.stage_node", "--ros-args", "-p", "backend:=visa",
         "-p", f"hardware_file:={hardware_file(rig, tmp_path, timeout_ms=2000.0)}", "-p", "autostart:=active",
         "-p", f"time_scale:={TIME_SCALE}", "-p", "command_timeout:=30.0"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=REPO)
    context = Context()
    rclpy.init(context=context, domain_id=domain)
    node = Node("ctrl_c_probe", context=context)
    try:
        read_until(process, "active: accepting current_cmd")
        publisher = node.create_publisher(Float64, "current_cmd", COMMAND_QOS)
        deadline = time.monotonic() + 20.0
        while rig.heating_current_a() != 2.0 and time.monotonic() < deadline:
            publisher.publish(Float64(data=2.0))
            time.sleep(0.05)
        assert rig.heating_current_a() == 2.0
        process.send_signal(signal.SIGINT)
        rest, _ = process.communicate(timeout=20)
    finally:
        process.kill()
        node.destroy_node()
        context.try_shutdown()
    assert process.returncode == 0, rest
    assert output_off(rig) and "output off (confirmed)" in rest and "Traceback" not in rest, rest


def test_the_simulator_goes_through_the_same_states(ros):
    stage = ros.add(StageNode(context=ros.context, parameter_overrides=[
        Parameter("autostart", value="unconfigured"), Parameter("rate_hz", value=100.0),
        Parameter("command_timeout", value=5.0)]))
    probe = ros.probe()
    assert lifecycle_label(ros, probe) == "unconfigured" and stage.published_steps == 0
    assert change_state(ros, probe, Transition.TRANSITION_CONFIGURE)
    wait_until(lambda: stage.published_steps > 5, 5.0, "joint_states while inactive")
    send = sender(probe)
    wait_until(lambda: stage.count_publishers("current_cmd") >= 1, 5.0, "the command publisher")
    send(1.0)
    time.sleep(0.1)
    assert stage.applied_a == 0.0, "inactive: commands ignored"
    assert change_state(ros, probe, Transition.TRANSITION_ACTIVATE)
    send(1.0)
    wait_until(lambda: stage.applied_a == 1.0, 5.0, "the current applied once active")
    assert change_state(ros, probe, Transition.TRANSITION_DEACTIVATE)
    wait_until(lambda: stage.applied_a == 0.0, 5.0, "zero current once inactive")
    assert change_state(ros, probe, Transition.TRANSITION_CLEANUP)
    assert lifecycle_label(ros, probe) == "unconfigured"


def test_reconnect_attempts_back_off_while_the_instruments_are_gone(rig, ros, tmp_path):
    stage = bridge_node(ros, rig, tmp_path, reconnect_max_interval=2.0)
    wait_until(lambda: stage.published_steps > 3, 5.0, "cycles while inactive")
    rig.stop()
    wait_until(lambda: stage.lifecycle == "unconfigured" and stage._reconnect_s == 2.0, 8.0,
               "a failed attempt after 1 s, and the next interval doubled to the cap of 2 s")
    time.sleep(2.5)
    assert stage.lifecycle == "unconfigured" and stage._reconnect_s == 2.0, "capped, still trying, nothing on"
    assert stage.faults == 1 and "Connection refused" in stage.last_fault, stage.last_fault
