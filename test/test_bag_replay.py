"""Bags recorded from the simulated stage by the identification node (test/data, made by make_bags.py),
replayed with their original timing into a fresh identification node: its ~/refit equals the offline fit
of the same bag, and a bag with a missing topic or a truncated file fails with one clear line.

The replay is `ros2 bag play --clock` done by hand: each stored message (its CDR bytes unchanged) is
published at its recorded time offset, sped up uniformly by SPEEDUP, right after /clock carries its
recorded time; the node runs on that clock (use_sim_time), so it stamps each arrival with the time the
recording node stamped it. DDS keeps no order across two topics, so the player waits until the node has
taken each message before the next one (the node keeps up; a lag would stretch the timing, not reorder it).
"""

import json
import math
import os
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.time import Time  # noqa: E402
from rosbags.rosbag2 import Reader  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Float64  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from sma_stage.errors import InputError  # noqa: E402
from sma_stage.identify.fit import fit_gpi, predict  # noqa: E402
from sma_stage.identify.metrics import error_metrics  # noqa: E402
from sma_stage.io import load_series, write_csv  # noqa: E402
from sma_stage.io.rosbag_io import _typestore  # noqa: E402
from sma_stage.nodes._common import COMMAND_QOS, STATE_PUBLISH_QOS  # noqa: E402
from sma_stage.nodes.identification.refit import report_json  # noqa: E402
from sma_stage.nodes.identification_node import IdentificationNode  # noqa: E402
from sma_stage.nodes.launch import find_executable  # noqa: E402

DATA = Path(__file__).resolve().parent / "data"
SPEEDUP = 2.0
OPERATORS = 10
HOLDOUT = 0.25
# The node and the offline fit get bit-identical arrays (asserted first) and run the same code, and on this
# machine their results are bit-identical too (the tests pass with 0). The tolerance only allows for the
# summation order of threaded BLAS inside the least-squares solver, which may differ between threads/machines.
RTOL = 1e-9


class Player:
    """A private context holding the fresh identification node and a bag player, spun in the background."""

    def __init__(self, domain_id: int, **overrides) -> None:
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        settings = dict(use_sim_time=True, operators=OPERATORS, holdout_fraction=HOLDOUT, push_timeout=0.0,
                        compensator_name="no_compensator_in_this_test", diagnose_rounds=0,
                        input_topic="current_cmd",  # the bags hold the commands the node recorded then
                        max_held_out_rms_pct=100.0)  # 5 s bags: the fitted head does not describe the tail
        settings.update(overrides)
        self.identification = IdentificationNode(
            context=self.context, parameter_overrides=[Parameter(k, value=v) for k, v in settings.items()])
        self.node = Node("bag_player", context=self.context)
        self.clock_pub = self.node.create_publisher(Clock, "/clock", 10)
        self.publishers = {"/current_cmd": self.node.create_publisher(Float64, "current_cmd", COMMAND_QOS),
                           "/joint_states": self.node.create_publisher(JointState, "joint_states",
                                                                       STATE_PUBLISH_QOS)}
        self.executor = SingleThreadedExecutor(context=self.context)
        for node in (self.identification, self.node):
            self.executor.add_node(node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()
        wait_until(lambda: self.identification.count_publishers("joint_states") >= 1
                   and self.identification.count_publishers("/clock") >= 1
                   and self.node.count_subscribers("current_cmd") >= 1, "discovery")

    def recorded(self) -> int:
        return len(self.identification.inputs) + len(self.identification.outputs)

    def play(self, messages: list[tuple[int, str, bytes]]) -> float:
        """Publish the messages at their recorded offsets / SPEEDUP; the wall seconds it took."""
        first_ns, began = messages[0][0], time.monotonic()
        for count, (stamp_ns, topic, raw) in enumerate(messages, start=1):
            delay = began + (stamp_ns - first_ns) * 1e-9 / SPEEDUP - time.monotonic()
            if delay > 0.0:
                time.sleep(delay)
            self.clock_pub.publish(Clock(clock=Time(nanoseconds=stamp_ns).to_msg()))
            wait_until(lambda: self.identification.now_ns() >= stamp_ns, "/clock to reach the node")  # noqa: B023
            self.publishers[topic].publish(raw)
            wait_until(lambda: self.recorded() >= count, f"message {count} to be recorded")  # noqa: B023
        return time.monotonic() - began

    def refit(self):
        client = self.node.create_client(Trigger, "identification/refit")
        assert client.wait_for_service(timeout_sec=10.0)
        future = client.call_async(Trigger.Request())
        wait_until(future.done, "the refit", timeout=60.0)
        return future.result()

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=5.0)
        self.thread.join(timeout=5.0)
        self.identification.close()
        for node in (self.identification, self.node):
            node.destroy_node()
        self.context.try_shutdown()


def wait_until(predicate, what: str, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.0002)


def bag_messages(path: Path) -> list[tuple[int, str, bytes]]:
    """(recorded time [ns], topic, CDR bytes) of every message, in recorded order."""
    with Reader(path) as reader:
        messages = [(stamp, connection.topic, bytes(raw)) for connection, stamp, raw in reader.messages()]
    return sorted(messages, key=lambda item: item[0])


def recorded_tuples(messages: list[tuple[int, str, bytes]]) -> tuple[list, list]:
    """What an identification node records from these messages arriving at their recorded times."""
    store, inputs, outputs = _typestore(), [], []
    for stamp_ns, topic, raw in messages:
        if topic == "/current_cmd":
            inputs.append((stamp_ns, store.deserialize_cdr(raw, "std_msgs/msg/Float64").data))
        else:
            state = store.deserialize_cdr(raw, "sensor_msgs/msg/JointState")
            header_ns = state.header.stamp.sec * 10**9 + state.header.stamp.nanosec
            effort = float(state.effort[0]) if len(state.effort) else math.nan
            outputs.append((stamp_ns, header_ns, float(state.position[0]), effort))
    return inputs, outputs


@pytest.fixture
def player_factory():
    players = []

    def make(**overrides) -> Player:
        players.append(Player(int(os.environ["ROS_DOMAIN_ID"]), **overrides))
        return players[-1]

    yield make
    for player in players:
        player.close()


def offline_fit(path: Path) -> dict:
    """fit_gpi on load_series(bag): the head fitted, the model run over all samples, errors on the tail."""
    series = load_series(path)
    ident, tail = series.split(1.0 - HOLDOUT)
    fit = fit_gpi(ident.input, ident.output, operators=OPERATORS)
    validation = error_metrics(tail.output, predict(fit, series.input)[len(ident):])
    return {"series": series, "ident": ident, "fit": fit, "validation": validation.to_dict()}


def assert_close(found: dict, expected: dict) -> None:
    assert found.keys() == expected.keys()
    for key, value in expected.items():
        assert math.isclose(found[key], value, rel_tol=RTOL, abs_tol=0.0), (key, found[key], value)


@pytest.mark.parametrize("bag", ["excitation_sqlite3", "excitation_mcap"])
def test_replayed_bag_refits_as_the_offline_fit(player_factory, bag):
    path = DATA / bag
    messages = bag_messages(path)
    assert {topic for _, topic, _ in messages} == {"/current_cmd", "/joint_states"} and len(messages) > 400
    player = player_factory()
    seconds = player.play(messages)
    recorded_s = (messages[-1][0] - messages[0][0]) * 1e-9
    assert seconds >= recorded_s / SPEEDUP, "the replay kept the recorded timing"
    inputs, outputs = recorded_tuples(messages)
    assert list(player.identification.inputs) == inputs
    np.testing.assert_array_equal(np.array(player.identification.outputs), np.array(outputs))  # NaN: no effort

    offline = offline_fit(path)
    live = player.identification.snapshot()
    for column in ("t", "input", "output"):
        np.testing.assert_array_equal(getattr(live, column), getattr(offline["series"], column))
    answer = player.refit()
    assert answer.success and answer.message.startswith("refit ok: "), answer.message
    report = json.loads(report_json(player.identification.last_report))  # what ~/report carries
    fit = offline["fit"]
    assert report["gpi_fit"]["operators"] == fit.operators == OPERATORS
    assert report["samples"] == {"identification": len(offline["ident"]),
                                 "validation": len(offline["series"]) - len(offline["ident"])}
    assert_close(report["gpi_fit"]["parameters"], fit.parameters.to_dict())
    assert_close(report["identification"], fit.identification.to_dict())
    assert_close(report["validation"], offline["validation"])
    print(f"{bag}: {len(messages)} messages replayed in {seconds:.2f} s ({recorded_s:.2f} s recorded, "
          f"speed-up {SPEEDUP:g}); identification rms {fit.identification.rms_pct:.3f} %")


def test_gpi_tool_fits_the_head_of_a_bag_as_the_node_does(tmp_path):
    path = DATA / "excitation_sqlite3"
    offline = offline_fit(path)
    head = tmp_path / "head.csv"
    write_csv(head, offline["ident"])
    done = subprocess.run([str(find_executable("gpi_tool")), "fit", str(head), "--operators", str(OPERATORS),
                           "--json", "--out", str(tmp_path / "fit")], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert_close(report["gpi_fit"]["parameters"], offline["fit"].parameters.to_dict())
    assert_close(report["identification"], offline["fit"].identification.to_dict())


def test_replayed_bag_without_joint_states_is_refused_by_the_refit(player_factory):
    messages = bag_messages(DATA / "no_joint_states")
    assert {topic for _, topic, _ in messages} == {"/current_cmd"}
    player = player_factory()
    player.play(messages)
    answer = player.refit()
    assert not answer.success
    assert "no messages on joint_states" in answer.message and "\n" not in answer.message


BAD_BAGS = {"no_joint_states": "no messages on topic '/joint_states'", "truncated_mcap": "truncated or damaged"}


def test_bad_bags_fail_with_one_line():
    for bag, phrase in BAD_BAGS.items():
        with pytest.raises(InputError) as caught:
            load_series(DATA / bag)
        assert phrase in str(caught.value) and "\n" not in str(caught.value)
    runs = {bag: subprocess.Popen([str(find_executable("gpi_tool")), "fit", str(DATA / bag), "--json"],
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for bag in BAD_BAGS}
    for bag, process in runs.items():
        stdout, stderr = process.communicate(timeout=120)
        assert process.returncode == 2, (bag, stderr)
        assert stdout == ""
        assert stderr.count("\n") == 1 and BAD_BAGS[bag] in stderr and "Traceback" not in stderr


def test_bags_are_small():
    bags = [folder for folder in DATA.iterdir() if (folder / "metadata.yaml").is_file()]
    assert len(bags) >= 3
    assert sum(f.stat().st_size for bag in bags for f in bag.rglob("*") if f.is_file()) < 300_000


def test_bags_were_recorded_by_the_identification_node():
    """The stage's stamps (node clock) and the recorder's arrival times agree to well under a second."""
    _, outputs = recorded_tuples(bag_messages(DATA / "excitation_mcap"))
    delays = np.array([(arrival - stamp) * 1e-9 for arrival, stamp, *_ in outputs])
    assert 0.0 < np.median(delays) < 0.5

