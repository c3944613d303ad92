"""The three ROS 2 nodes in-process: each test has its own rclpy context and DDS domain, spins its nodes
in a background executor and talks to them through topics, services and parameters."""

import itertools
import math
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import MultiThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rosgraph_msgs.msg import Clock as ClockMessage  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Float64  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from sma_stage.errors import InputError  # noqa: E402
from sma_stage.nodes._common import COMMAND_QOS, STATE_SUBSCRIBE_QOS  # noqa: E402
from sma_stage.nodes.stage_node import StageNode  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
_domains = itertools.count()


def unique_domain() -> int:
    """A DDS domain id no other test of this run uses (and unlikely to clash with another run)."""
    return 120 + (os.getpid() * 7 + next(_domains)) % 100


class Ros:
    """A private rclpy context with a background MultiThreadedExecutor and helpers to wait and call."""

    def __init__(self) -> None:
        self.context = Context()
        rclpy.init(context=self.context, domain_id=unique_domain())
        self.executor = MultiThreadedExecutor(num_threads=4, context=self.context)
        self.nodes: list[Node] = []
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except Exception:  # noqa: BLE001 -- the context is shut down under the executor at the end
            pass

    def add(self, node: Node) -> Node:
        self.nodes.append(node)
        self.executor.add_node(node)
        return node

    def probe(self, name: str = "probe") -> Node:
        return self.add(Node(name, context=self.context))

    def call(self, node: Node, service_type, name: str, request=None, timeout: float = 10.0):
        client = node.create_client(service_type, name)
        assert client.wait_for_service(timeout_sec=timeout), f"service {name} not available"
        future = client.call_async(request if request is not None else service_type.Request())
        wait_until(future.done, timeout, f"no answer from {name}")
        return future.result()

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=5.0)
        self.thread.join(timeout=5.0)
        for node in self.nodes:
            close = getattr(node, "close", None)
            if close is not None:
                close()
            node.destroy_node()
        self.context.try_shutdown()


def wait_until(predicate, timeout: float = 5.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.01)


@pytest.fixture
def ros():
    harness = Ros()
    yield harness
    harness.close()


def stage_node(ros: Ros, **overrides) -> StageNode:
    params = [Parameter(name, value=value) for name, value in overrides.items()]
    return ros.add(StageNode(context=ros.context, parameter_overrides=params))


class Listener:
    """Records every message of a topic (with its wall arrival time)."""

    def __init__(self, node: Node, message_type, topic: str, qos=10) -> None:
        self.messages: list = []
        self.arrivals: list[float] = []
        node.create_subscription(message_type, topic, self._on_message, qos)

    def _on_message(self, message) -> None:
        self.arrivals.append(time.monotonic())
        self.messages.append(message)


def command_publisher(probe: Node):
    publisher = probe.create_publisher(Float64, "current_cmd", COMMAND_QOS)
    return lambda value: publisher.publish(Float64(data=float(value)))


def diagnostic_values(array: DiagnosticArray) -> dict[str, str]:
    return {pair.key: pair.value for status in array.status for pair in status.values}


# --- stage ---------------------------------------------------------------------------------------


def test_stage_publishes_joint_states_at_its_rate(ros):
    stage_node(ros, rate_hz=100.0)
    listener = Listener(ros.probe(), JointState, "joint_states", STATE_SUBSCRIBE_QOS)
    wait_until(lambda: len(listener.messages) >= 60, 10.0, "60 joint_states messages")
    stamps = [m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in listener.messages[-50:]]
    intervals = np.diff(stamps)
    assert np.all(intervals > 0.0)
    assert 0.008 <= np.median(intervals) <= 0.012, "median interval at rate_hz=100"
    message = listener.messages[-1]
    assert list(message.name) == ["stage_x"]
    assert len(message.position) == 1 and math.isfinite(message.position[0])
    assert len(message.velocity) == 1 and math.isfinite(message.velocity[0])


def test_stage_clamps_and_refuses_non_finite_commands(ros):
    stage = stage_node(ros, rate_hz=100.0, max_current=2.0, command_timeout=5.0)
    send = command_publisher(ros.probe())
    wait_until(lambda: stage.count_publishers("current_cmd") >= 1, 5.0, "the command publisher")
    send(9.0)
    wait_until(lambda: stage.applied_a == 2.0, 5.0, "the clamped current")
    assert stage.clamped_count == 1
    send(-1.5)
    wait_until(lambda: stage.applied_a == -1.5, 5.0, "an in-range command")
    for bad in (math.nan, math.inf, -math.inf):
        send(bad)
    wait_until(lambda: stage.rejected_count == 3, 5.0, "three refused commands")
    time.sleep(0.05)
    assert stage.applied_a == -1.5
    assert stage.state.current_a == -1.5


def test_stage_watchdog_zeroes_a_stale_command(ros):
    stage = stage_node(ros, rate_hz=100.0, command_timeout=0.3)
    probe = ros.probe()
    send = command_publisher(probe)
    diagnostics = Listener(probe, DiagnosticArray, "/diagnostics")
    wait_until(lambda: stage.count_publishers("current_cmd") >= 1, 5.0, "the command publisher")
    send(1.0)
    wait_until(lambda: stage.applied_a == 1.0, 5.0, "the commanded current")
    commanded_at = time.monotonic()
    wait_until(lambda: stage.applied_a == 0.0, 2.0, "the watchdog")
    assert time.monotonic() - commanded_at >= 0.25
    assert stage.watchdog_tripped
    wait_until(lambda: any(diagnostic_values(a).get("watchdog_tripped") == "True" for a in diagnostics.messages),
               3.0, "diagnostics with the watchdog tripped")
    values = diagnostic_values(diagnostics.messages[-1])
    for key in ("wire_a_temperature_k", "wire_b_temperature_k", "command_age_s", "clamped_commands", "stopped"):
        assert key in values
    assert 250.0 < float(values["wire_a_temperature_k"]) < 500.0


def test_stage_stop_latches_until_resume(ros):
    stage = stage_node(ros, rate_hz=100.0, command_timeout=5.0)
    probe = ros.probe()
    send = command_publisher(probe)
    wait_until(lambda: stage.count_publishers("current_cmd") >= 1, 5.0, "the command publisher")
    send(1.0)
    wait_until(lambda: stage.applied_a == 1.0, 5.0, "the commanded current")
    answer = ros.call(probe, Trigger, "stage/stop")
    assert answer.success
    send(2.0)
    time.sleep(0.2)
    assert stage.applied_a == 0.0 and stage.stopped
    answer = ros.call(probe, Trigger, "stage/resume")
    assert answer.success and not stage.stopped
    time.sleep(0.05)
    assert stage.applied_a == 0.0, "resume must not bring back an old command"
    send(0.5)
    wait_until(lambda: stage.applied_a == 0.5, 5.0, "a command after resume")


def test_stage_parameter_ranges_are_enforced(ros):
    stage = stage_node(ros)
    result = stage.set_parameters([Parameter("max_current", value=50.0)])[0]
    assert not result.successful and result.reason
    assert stage.get_parameter("max_current").value == 5.0
    assert stage.set_parameters([Parameter("max_current", value=1.0)])[0].successful
    with pytest.raises(InputError) as excinfo:
        StageNode(context=ros.context, parameter_overrides=[Parameter("rate_hz", value=1e6)])
    assert "rate_hz" in str(excinfo.value) and "\n" not in str(excinfo.value)


def test_stage_with_sim_time_publishes_a_fast_clock(ros):
    stage_node(ros, rate_hz=100.0, time_scale=20.0, use_sim_time=True)
    listener = Listener(ros.probe(), ClockMessage, "/clock")
    wait_until(lambda: len(listener.messages) >= 2, 10.0, "/clock")
    first, start = listener.messages[-1].clock, time.monotonic()
    time.sleep(0.5)
    last, wall = listener.messages[-1].clock, time.monotonic() - start
    simulated = (last.sec - first.sec) + 1e-9 * (last.nanosec - first.nanosec)
    assert simulated > 5.0 * wall, f"{simulated:.2f} s simulated in {wall:.2f} s of wall time"


def test_stage_executable_refuses_an_out_of_range_parameter():
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    done = subprocess.run([sys.executable, "-m", "sma_stage.nodes.stage_node", "--ros-args", "-p", "rate_hz:=1e6"],
                          capture_output=True, text=True, timeout=60, env=env, cwd=REPO)
    assert done.returncode == 2
    assert "Traceback" not in done.stderr
    lines = [line for line in done.stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and "rate_hz" in lines[0]


def node_process(module: str, *ros_args: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""),
               ROS_DOMAIN_ID=str(unique_domain()), PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, "-m", f"sma_stage.nodes.{module}", "--ros-args", *ros_args],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=REPO)


def read_until(process: subprocess.Popen, phrase: str, timeout: float = 30.0) -> str:
    """Output of the process up to the first line holding phrase (a background reader enforces the timeout)."""
    seen: list[str] = []
    found = threading.Event()

    def reader() -> None:
        for line in process.stdout:
            seen.append(line)
            if phrase in line:
                found.set()
                return

    threading.Thread(target=reader, daemon=True).start()
    if not found.wait(timeout):
        process.kill()
        raise AssertionError(f"'{phrase}' not printed within {timeout} s: {''.join(seen)}")
    return "".join(seen)


def test_stage_executable_reads_the_config_file_and_stops_on_sigterm():
    process = node_process("stage_node", "--params-file", str(REPO / "config" / "stage.yaml"), "-r", "__ns:=/lab")
    try:
        read_until(process, "stage ready: backend sim, 50 Hz")
        process.terminate()
        rest, _ = process.communicate(timeout=20)
    finally:
        process.kill()
    assert process.returncode == 0, rest
    assert "Traceback" not in rest
