"""The installed node executables as separate processes: excite, refit, the compensator receives the fitted
parameters, and a setpoint then drives the simulated stage through the compensator (a short demo run)."""

import gc
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import weakref

import numpy as np
import pytest
import yaml

pytest.importorskip("rclpy")

from scpi_server import LoopbackRig  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Float64, String  # noqa: E402

from sma_stage.control import Compensator  # noqa: E402
from sma_stage.identify.effects import EFFECT_NAMES  # noqa: E402
from sma_stage.model.kinds import (  # noqa: E402
    AnyModel,  # noqa: E402
    any_model_from_yaml_text,
    load_any_model_file,
)
from sma_stage.nodes._common import COMMAND_QOS, REPORT_QOS, STATE_SUBSCRIBE_QOS  # noqa: E402
from sma_stage.nodes.launch import CONFIG_DIR, NodeProcesses, RosClient, find_executable, wait_for  # noqa: E402

TIME_SCALE = 100.0  # simulated s per wall s on a quiet machine: the 500 s excitation takes about 5 s
EXCITE_S = 500.0
COOLED_S = 300.0  # simulated s at 0 A after the push: the wires' lag (tau ~11 s) has cooled to e^-27
STAGE_RATE_HZ = 100.0  # stage steps per wall s
STAGE_STEP_S = TIME_SCALE / STAGE_RATE_HZ  # [s of simulated time]
CLOCK_SLACK_S = 200.0  # how far the compensator's model time may be from the test's reading of /clock [s]
# Every node on the stage's /clock: the recording, the excitation and the PI run on simulated time, so a
# loaded machine slows the run down instead of distorting it.


class Recorder:
    """The joint_states positions [m] and stamps [s of simulated time] and the current_cmd values [A] seen by
    the test's node."""

    def __init__(self, node) -> None:
        self.positions: list[float] = []
        self.stamps_s: list[float] = []
        self.commands: list[float] = []
        node.create_subscription(JointState, "joint_states", self.on_joint_states, STATE_SUBSCRIBE_QOS)
        node.create_subscription(Float64, "current_cmd", lambda m: self.commands.append(m.data), COMMAND_QOS)

    def on_joint_states(self, message: JointState) -> None:
        self.positions.append(message.position[0])
        self.stamps_s.append(message.header.stamp.sec + 1e-9 * message.header.stamp.nanosec)


def first_command_bounds(model: AnyModel, target_m: float, model_time_s: tuple[float, float]
                         ) -> tuple[float, float]:
    """The compensator's first command [A] for target_m after the stage rested at 0 A long enough for the lag
    to cool (feedforward_lead_limit 1: the model's inverse with no lead), for the model's drift time anywhere in
    model_time_s [s after the push] (the same both ends without a drift). The rest followed one stage step at a
    time, as the node follows current_applied: a two-wire model's wires cool along a path (their thresholds move
    with the position the cooling changes)."""
    commands = []
    for elapsed_s in model_time_s:
        compensator = Compensator(model, 5.0, feedforward_lead_limit=1.0)
        for _ in range(max(round(elapsed_s / STAGE_STEP_S), 0)):
            compensator.follow_applied(0.0, STAGE_STEP_S)
        commands.append(compensator.command(target_m))
    return min(commands), max(commands)


# The refits at the test's priority: ten nice levels below (the default), a refit beside two busy processes on two
# cores took more than the tests wait (test_nodes.py::test_a_refit_runs_refit_niceness_levels_below_the_node checks it)
TEST_PRIORITY = {"refit_niceness": 0}
REFIT_WAIT_S = 120.0  # these refits (every family, one diagnosis round): 13-16 s alone, 14-27 s beside two busy processes


def start_system(nodes: NodeProcesses, model_file, stage_backend: dict | None = None) -> None:
    nodes.start("stage_node", {"rate_hz": STAGE_RATE_HZ, "time_scale": TIME_SCALE, "command_timeout": 5.0,
                                "use_sim_time": True, **(stage_backend or {})}, [CONFIG_DIR / "stage.yaml"])
    nodes.start("compensator_node", {"rate_hz": 1.0, "use_sim_time": True, "feedback": False,
                                          "feedforward_lead_limit": 1.0},
                [CONFIG_DIR / "compensator.yaml"])
    nodes.start("identification_node", {"excite_duration": EXCITE_S, "excite_rate_hz": 1.0, "operators": 5,
                                         "min_samples": 60, "model_file": str(model_file), "use_sim_time": True,
                                         **TEST_PRIORITY}, [CONFIG_DIR / "identification.yaml"])


def refit_after_excitation(client: RosClient, check) -> dict:
    deadline = time.monotonic() + 30.0
    while True:
        ok, message = client.trigger("identification/excite")
        if ok or "no /clock" not in message or time.monotonic() > deadline:
            break
        check()
        time.sleep(0.1)
    assert ok, message
    time.sleep(EXCITE_S / TIME_SCALE)
    deadline = time.monotonic() + 60.0
    while True:
        ok, message = client.trigger("identification/refit", timeout_s=REFIT_WAIT_S)
        if ok or "excitation is running" not in message or time.monotonic() > deadline:
            break
        check()
        time.sleep(0.1)
    assert ok and message.startswith("refit ok: "), message
    return json.loads(client.latest(String, "identification/report", REPORT_QOS).data)


@pytest.fixture(params=["sim", "visa"])
def stage_backend(request, tmp_path):
    """The stage node's backend parameters: the simulator, or the bridge on the loopback SCPI rig running the
    same simulator at TIME_SCALE (the example's relay settle times scaled to the rig's time)."""
    if request.param == "sim":
        yield {}
        return
    with LoopbackRig(time_scale=TIME_SCALE) as rig:
        data = rig.simulator_equivalent(yaml.safe_load((CONFIG_DIR / "hardware_example.yaml").read_text()))
        # The rig answers from this process: with the whole suite on two cores a reply once came later than the
        # example's 200 ms, the bridge faulted (output off) and the excitation drove nothing
        data["timeout_ms"] = 2000.0
        (tmp_path / "hardware.yaml").write_text(yaml.safe_dump(data))
        # command_timeout longer than the test: on instruments the watchdog deactivates the stage, and whether it
        # fired between the excitation and the setpoint would depend on how long the refit took
        yield {"backend": "visa", "hardware_file": str(tmp_path / "hardware.yaml"), "autostart": "active",
               "command_timeout": 120.0}
        assert rig.conflicts == 0, "a relay closed while the other carried current"


def test_executables_excite_refit_push_and_track(tmp_path, stage_backend):
    model_file = tmp_path / "fitted.yaml"
    domain = int(os.environ["ROS_DOMAIN_ID"])
    with NodeProcesses(tmp_path / "nodes", domain) as nodes:
        start_system(nodes, model_file, stage_backend)
        assert {p.name for p in nodes.processes} == {"stage_node", "compensator_node", "identification_node"}
        with RosClient(domain, "e2e_test") as client:
            seen = Recorder(client.node)
            client.wait_for_services(["stage/stop", "compensator/reload", "identification/refit"], 60.0,
                                     nodes.check_running)
            wait_for(lambda: len(seen.positions) > 10, 30.0, "joint_states", nodes.check_running)
            report = refit_after_excitation(client, nodes.check_running)
            pushed_s = seen.stamps_s[-1]
            assert report["compensator"]["pushed"], report["compensator"]["message"]
            assert report["samples"]["identification"] + report["samples"]["validation"] >= 60, "min_samples"
            assert report["diagnosis"]["effect"] in ("none", *EFFECT_NAMES)
            deployed = load_any_model_file(model_file)  # of the family the refit chose (every family by default)
            assert deployed.without_state().to_dict() == report["model"]
            held = any_model_from_yaml_text(client.get_parameters("compensator", ["model"])["model"])
            assert held == deployed, "the compensator holds the model written"

            stroke = (min(seen.positions), max(seen.positions))
            assert stroke[1] - stroke[0] > 2e-4, f"the excitation moved the stage: {stroke}"
            start = float(np.mean(seen.positions[-10:]))
            target = start + (0.3 if start < np.mean(stroke) else -0.3) * (stroke[1] - stroke[0])
            assert client.lifecycle("stage") == "active"
            setpoint = client.node.create_publisher(Float64, "setpoint", COMMAND_QOS)
            wait_for(lambda: client.node.count_subscribers("setpoint") >= 1, 10.0, "the compensator")
            wait_for(lambda: seen.stamps_s[-1] > pushed_s + COOLED_S, 30.0, "the lag to cool", nodes.check_running)
            commands_before = len(seen.commands)
            rested_s = seen.stamps_s[-1] - pushed_s
            setpoint.publish(Float64(data=target))
            wait_for(lambda: len(seen.commands) > commands_before, 10.0, "a current command", nodes.check_running)
            low, high = first_command_bounds(deployed, target, (rested_s - CLOCK_SLACK_S, rested_s + CLOCK_SLACK_S))
            assert low - 1e-9 <= seen.commands[commands_before] <= high + 1e-9, \
                "feedforward: the fitted model's inverse, from the state the stage's applied current left it in"
            client.set_parameters("compensator", {"feedback": True, "tuning": "manual", "kp": 1.0, "ki": 0.1})

            def close_to_target() -> bool:
                setpoint.publish(Float64(data=target))
                return abs(np.mean(seen.positions[-5:]) - target) < 0.5 * abs(start - target)

            wait_for(close_to_target, 60.0, f"the stage to move from {start:.3g} m toward {target:.3g} m",
                     nodes.check_running, poll_s=0.05)
        exits = nodes.stop_all()
    assert exits == {"stage_node": 0, "compensator_node": 0, "identification_node": 0}, exits


class _Cyclic:
    def __init__(self) -> None:
        self.me = self


def test_open_ros_clients_keep_the_objects_before_them_out_of_full_collections():
    """While RosClients are open (two at once here), what the process held before the first is frozen out of the
    garbage collector (a full collection paused the demo's setpoints 0.3-0.7 s); all of it is given back when
    the last one closes, and what the clients' time created is still collected."""
    domain = int(os.environ["ROS_DOMAIN_ID"])
    frozen_before = gc.get_freeze_count()
    with RosClient(domain, "freeze_test"):
        assert gc.get_freeze_count() > 10_000, "the modules, numpy's and rclpy's objects among them"
        with RosClient(domain, "freeze_test_2"):
            assert gc.get_freeze_count() > 10_000
        assert gc.get_freeze_count() > 10_000, "one client still open"  # (frozen objects still die by refcount)
        in_a_cycle = _Cyclic()
        collected = weakref.ref(in_a_cycle)
        del in_a_cycle
        gc.collect()
        assert collected() is None, "garbage made while a client is open is still collected"
    assert gc.get_freeze_count() == frozen_before


def test_node_processes_are_stopped_when_the_block_fails(tmp_path):
    domain = int(os.environ["ROS_DOMAIN_ID"])
    with pytest.raises(RuntimeError, match="leaving early"), NodeProcesses(tmp_path, domain) as nodes:
        process = nodes.start("stage_node", {"rate_hz": 20.0})
        wait_for(lambda: "stage ready" in process.log_path.read_text(), 30.0, "the stage", nodes.check_running)
        raise RuntimeError("leaving early")
    assert process.popen.returncode == 0, process.log_tail()
    assert not nodes.processes


def test_a_child_that_cannot_start_is_reported_with_its_error_line(tmp_path):
    domain = int(os.environ["ROS_DOMAIN_ID"])
    with NodeProcesses(tmp_path, domain) as nodes:
        process = nodes.start("stage_node", {"rate_hz": 1e6})
        process.popen.wait(60)
        with pytest.raises(ValueError, match=r"stage_node exited with status 2: \[ERROR\] .*\[stage\]: cannot start: parameter 'rate_hz'"):
            nodes.check_running()
    assert find_executable("stage_node").name == "stage_node"


def test_stage_and_compensator_run_in_one_process_in_their_namespace(tmp_path):
    """`stage_and_compensator`: both nodes under the namespace given, each with its own section of the
    parameter files; a setpoint to the namespace moves the stage; /diagnostics names the stage by its full
    name (ten stages publish there); SIGTERM ends both with status 0."""
    from diagnostic_msgs.msg import DiagnosticArray

    domain = int(os.environ["ROS_DOMAIN_ID"])
    with NodeProcesses(tmp_path, domain) as nodes:
        nodes.start("stage_and_compensator", {"rate_hz": 50.0},
                    [CONFIG_DIR / "stage.yaml", CONFIG_DIR / "compensator.yaml"], namespace="/stage_7")
        with RosClient(domain, "pair_test") as client:
            positions: list[float] = []
            client.node.create_subscription(JointState, "/stage_7/joint_states",
                                            lambda m: positions.append(m.position[0]), STATE_SUBSCRIBE_QOS)
            diagnostics: list[DiagnosticArray] = []
            client.node.create_subscription(DiagnosticArray, "/diagnostics", diagnostics.append, 10)
            client.wait_for_services(["/stage_7/stage/stop", "/stage_7/compensator/reload"], 60.0, nodes.check_running)
            wanted = {("stage", "/stage_7"), ("compensator", "/stage_7")}
            wait_for(lambda: wanted <= set(client.node.get_node_names_and_namespaces()), 10.0, "both nodes' names")
            assert client.get_parameters("/stage_7/compensator", ["rate_hz"])["rate_hz"] == 50.0
            wait_for(lambda: len(positions) > 10, 30.0, "joint_states", nodes.check_running)
            names = {"/stage_7/stage: sim stage", "/stage_7/compensator: compensator"}
            wait_for(lambda: names <= {status.name for array in diagnostics for status in array.status}, 10.0,
                     "/diagnostics of both nodes, by their full names", nodes.check_running)
            start = float(np.mean(positions[-5:]))
            setpoint = client.node.create_publisher(Float64, "/stage_7/setpoint", COMMAND_QOS)
            wait_for(lambda: client.node.count_subscribers("/stage_7/setpoint") >= 1, 10.0, "the compensator")

            def moved() -> bool:
                setpoint.publish(Float64(data=start + 1e-4))
                return float(np.mean(positions[-5:])) - start > 5e-5

            wait_for(moved, 60.0, "the stage to move toward the setpoint", nodes.check_running, poll_s=0.05)
        exits = nodes.stop_all()
    assert exits == {"/stage_7/stage_and_compensator": 0}, exits


def test_a_pair_whose_compensator_cannot_start_exits_with_its_error_line(tmp_path):
    domain = int(os.environ["ROS_DOMAIN_ID"])
    with NodeProcesses(tmp_path, domain) as nodes:
        process = nodes.start("stage_and_compensator", {"rate_hz": 50.0, "kp": -1.0},
                              [CONFIG_DIR / "stage.yaml", CONFIG_DIR / "compensator.yaml"])
        process.popen.wait(60)
        with pytest.raises(ValueError, match=r"stage_and_compensator exited with status 2: \[ERROR\] .*"
                                             r"\[compensator\]: cannot start: parameter 'kp'"):
            nodes.check_running()


def test_a_child_dies_with_its_parent(tmp_path):
    """A parent killed without cleaning up (SIGKILL) takes its node process with it (Linux)."""
    script = (f"import sys, time; from pathlib import Path; from sma_stage.nodes.launch import NodeProcesses; "
              f"n = NodeProcesses(Path({str(tmp_path)!r}), {os.environ['ROS_DOMAIN_ID']}); "
              f"p = n.start('stage_node', {{'rate_hz': 20.0}}); print(p.popen.pid, flush=True); time.sleep(60)")
    parent = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        child = int(parent.stdout.readline())
        parent.send_signal(signal.SIGKILL)
        parent.wait(10)
        wait_for(lambda: not _alive(child), 20.0, "the orphaned node to exit")
    finally:
        parent.kill()


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().split(")")[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False



def test_a_refit_killed_midway_leaves_the_old_model_file_or_the_new_one_whole(tmp_path):
    """SIGKILL the identification node at several moments of a refit: the model file is the old one or a
    whole new one (written by one atomic rename), never half of either."""
    from std_srvs.srv import Trigger

    model_file = tmp_path / "model.yaml"
    shutil.copy(CONFIG_DIR / "model_default.yaml", model_file)
    old = model_file.read_bytes()
    domain = int(os.environ["ROS_DOMAIN_ID"])
    found = []
    for attempt, kill_after_s in enumerate((0.05, 2.0, None)):
        with NodeProcesses(tmp_path / f"nodes_{attempt}", domain) as nodes:
            nodes.start("stage_node", {"rate_hz": 100.0, "time_scale": TIME_SCALE, "command_timeout": 5.0,
                                       "use_sim_time": True}, [CONFIG_DIR / "stage.yaml"])
            identification = nodes.start("identification_node", {
                "excite_duration": 300.0, "excite_rate_hz": 1.0, "operators": 5, "min_samples": 60,
                "model_file": str(model_file), "use_sim_time": True, "push_timeout": 0.1, **TEST_PRIORITY,
                "max_held_out_rms_pct": 100.0},  # 300 s records miss their held-out tail by 9-11 %: not tested here
                [CONFIG_DIR / "identification.yaml"])
            with RosClient(domain, f"kill_test_{attempt}") as client:
                client.wait_for_services(["identification/refit"], 60.0, nodes.check_running)
                deadline = time.monotonic() + 30.0
                while not client.trigger("identification/excite")[0]:
                    assert time.monotonic() < deadline, "~/excite refused for 30 s"
                    time.sleep(0.1)
                time.sleep(300.0 / TIME_SCALE + 1.0)
                refit = client.node.create_client(Trigger, "identification/refit").call_async(Trigger.Request())
                if kill_after_s is None:
                    wait_for(refit.done, REFIT_WAIT_S, "the refit", nodes.check_running)
                else:
                    time.sleep(kill_after_s)
                    identification.popen.send_signal(signal.SIGKILL)
                    identification.popen.wait(10)
        written = model_file.read_bytes()
        found.append("old" if written == old else "new")
        if written != old:
            load_any_model_file(model_file)  # a new model file is a whole model: a part raises InputError
    assert found[-1] == "new", found
    print(f"model file after a SIGKILL 0.05 and 2.0 s into a refit, and after a whole refit: {found}")
