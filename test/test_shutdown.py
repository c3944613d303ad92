"""Stopping: each node executable ends within 5 s of SIGINT or SIGTERM with status 0 and nothing alarming in
its output; a long start-up and a running refit do not hold the stop; a cancelled fit ends within an
iteration. The 100-stop table under load is bench/bench_shutdown.py's (docs/reliability.md)."""

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")

from scpi_server import LoopbackRig  # noqa: E402
from test_hardware import rig_config  # noqa: E402

from sma_stage.identify.cancel import Cancelled, cancellable, check_cancelled  # noqa: E402
from sma_stage.identify.fit import fit_gpi  # noqa: E402
from sma_stage.identify.workers import Workers  # noqa: E402
from sma_stage.nodes._common import COMMAND_QOS, make_executor, spin_while  # noqa: E402
from sma_stage.nodes.launch import CONFIG_DIR, NodeProcesses, wait_for  # noqa: E402
from sma_stage.signals import paper_identification_signal  # noqa: E402

STOP_LIMIT_S = 5.0
BAD_OUTPUT = ("Traceback", "[ERROR]", "[FATAL]", "Failed to publish log message to rosout")
READY = {"stage_node": "active: accepting current_cmd", "compensator_node": "compensator ready",
         "identification_node": "identification ready"}


def stop_and_judge(process, number: int) -> tuple[float, str]:
    """Send the signal, wait for the exit; (seconds it took, the whole output)."""
    sent = time.monotonic()
    process.popen.send_signal(number)
    process.popen.wait(30.0)
    return time.monotonic() - sent, process.log_path.read_text(errors="replace")


@pytest.mark.parametrize("number", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
@pytest.mark.parametrize("executable", list(READY))
def test_each_node_stops_cleanly_on_a_signal(tmp_path, executable, number):
    """The stage used to print `Failed to publish log message to rosout` twice (its last lines logged after
    rclpy's handler had shut the context down under it)."""
    with NodeProcesses(tmp_path, int(os.environ["ROS_DOMAIN_ID"])) as nodes:
        process = nodes.start(executable, {}, [CONFIG_DIR / f"{executable.removesuffix('_node')}.yaml"])
        wait_for(lambda: READY[executable] in process.log_path.read_text(), 60.0, "the node", nodes.check_running)
        time.sleep(0.5)
        seconds, output = stop_and_judge(process, number)
        nodes.forget(process)
    assert process.popen.returncode == 0, output
    assert seconds < STOP_LIMIT_S, f"{executable} took {seconds:.1f} s to stop"
    assert not [line for line in output.splitlines() if any(mark in line for mark in BAD_OUTPUT)], output
    if executable == "stage_node":
        assert "output off (confirmed)" in output and "published" in output


def test_the_spin_loop_ends_on_a_stop_under_a_flood_of_messages():
    """rclpy 7.1's EventsExecutor looks at its spin timeout only when its queue runs empty: an identification
    node flooded with commands faster than it handled them spun on after SIGTERM until it was killed (1 of 100
    stops in bench_shutdown). The stop future now ends the spin whatever the queue holds."""
    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node
    from rclpy.task import Future
    from std_msgs.msg import Float64

    context = Context()
    rclpy.init(context=context, domain_id=int(os.environ["ROS_DOMAIN_ID"]))
    flooded, flooder = Node("flooded", context=context), Node("flooder", context=context)
    flooded.create_subscription(Float64, "flood", lambda message: time.sleep(0.001), COMMAND_QOS)
    publisher = flooder.create_publisher(Float64, "flood", COMMAND_QOS)
    executor = make_executor("events", context)
    executor.add_node(flooded)
    flooding = threading.Event()
    flooding.set()

    def flood() -> None:
        while flooding.is_set():
            publisher.publish(Float64(data=1.0))

    stopped = Future()
    spinner = threading.Thread(target=spin_while, args=(executor, stopped, context), daemon=True)
    publishing = threading.Thread(target=flood, daemon=True)
    try:
        spinner.start()
        publishing.start()
        time.sleep(1.0)
        sent = time.monotonic()
        stopped.set_result("SIGTERM")
        spinner.join(timeout=STOP_LIMIT_S)
        seconds = time.monotonic() - sent
        assert not spinner.is_alive(), f"the spin loop went on {seconds:.1f} s after the stop"
        assert seconds < 1.0
    finally:
        flooding.clear()
        publishing.join()
        spinner.join()
        executor.shutdown(timeout_sec=1.0)
        flooded.destroy_node()
        flooder.destroy_node()
        context.try_shutdown()


def test_a_signal_during_a_long_start_ends_the_start(tmp_path):
    """The stage connecting to instruments that take 30 s to answer: SIGTERM used to wait for the answer (rclpy's
    handler only shut the context down); now the start is interrupted."""
    with LoopbackRig() as rig:
        config = rig_config(rig)
        config["timeout_ms"] = 60000.0
        (tmp_path / "hardware.yaml").write_text(__import__("yaml").safe_dump(config))
        rig.inject("supply", "late", delay_s=30.0)
        with NodeProcesses(tmp_path, int(os.environ["ROS_DOMAIN_ID"])) as nodes:
            process = nodes.start("stage_node", {"backend": "visa", "hardware_file": str(tmp_path / "hardware.yaml"),
                                                 "autostart": "active"})
            wait_for(lambda: "stage ready" in process.log_path.read_text(), 60.0, "the stage", nodes.check_running)
            time.sleep(0.5)
            seconds, output = stop_and_judge(process, signal.SIGTERM)
            nodes.forget(process)
    assert process.popen.returncode == 0 and "Traceback" not in output, output
    assert seconds < STOP_LIMIT_S, f"the stage took {seconds:.1f} s to stop"


INTERRUPTED_START = """
import importlib, os, signal, sys
from sma_stage.nodes import _common
module = importlib.import_module("sma_stage.nodes." + sys.argv[1])
node_class = next(value for value in vars(module).values() if getattr(value, "NODE_NAME", None) and
                  value.__module__ == module.__name__)
if sys.argv[2] == "after_handle":  # the signal lands as Node.__init__ returns, before the node's own set-up
    started = module.note_started
    def note_started(node):
        started(node)
        os.kill(os.getpid(), signal.SIGINT)
    module.note_started = note_started
    make = node_class
else:  # the signal lands as the constructor returns, before run_nodes holds the node
    def make():
        node = node_class()
        os.kill(os.getpid(), signal.SIGINT)
        return node
sys.exit(_common.run_node(make, ["--ros-args", "-p", "rate_hz:=50.0"]))
"""


# The abort came at interpreter exit, in about half of the runs of the code before the fix (2 of 4, 5 of 6).
INTERRUPTED_START_TRIES = {"after_handle": 1, "constructed": 3}


@pytest.mark.parametrize("moment", ["after_handle", "constructed"])
@pytest.mark.parametrize("module", ["stage_node", "compensator_node", "identification_node"])
def test_a_signal_inside_a_constructor_stops_the_node_cleanly(tmp_path, module, moment):
    """A SIGINT just after a node printed that it was ready, before run_nodes held it, aborted the process at
    exit ("terminate called without an active exception", status -6: 2 of 30 stops of the identification node
    in bench_shutdown.py): the half-built node was never destroyed."""
    for _ in range(INTERRUPTED_START_TRIES[moment]):
        result = subprocess.run([sys.executable, "-c", INTERRUPTED_START, module, moment], capture_output=True,
                                text=True, timeout=60, cwd=tmp_path,
                                env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parent.parent)})
        output = result.stdout + result.stderr
        assert result.returncode == 0, output
        assert not [line for line in output.splitlines() if any(mark in line for mark in BAD_OUTPUT)], output


def slow_record(samples: int = 40000) -> tuple[np.ndarray, np.ndarray]:
    """A hysteretic record long enough that a fit takes seconds."""
    t = np.linspace(0.0, 1000.0, samples)
    u = paper_identification_signal(t, 5.0, 3.6, 250.0, 1000.0)
    y = np.tanh(0.5 * u) + 0.1 * np.sin(np.cumsum(np.abs(np.diff(u, prepend=0.0))))
    return u, y


def test_a_cancelled_fit_ends_within_an_iteration():
    u, y = slow_record()
    event = threading.Event()
    outcome: dict[str, object] = {}

    def fit() -> None:
        try:
            with cancellable(event):
                outcome["fit"] = fit_gpi(u, y, operators=10)
        except Cancelled as error:
            outcome["cancelled"] = error

    worker = threading.Thread(target=fit)
    worker.start()
    time.sleep(0.3)
    cancelled_at = time.monotonic()
    event.set()
    worker.join(30.0)
    assert "cancelled" in outcome, "the fit ended before it could be cancelled: make the record longer"
    assert time.monotonic() - cancelled_at < 1.0


def test_check_cancelled_does_nothing_outside_a_cancellable_block():
    check_cancelled()
    event = threading.Event()
    with cancellable(event):
        check_cancelled()
        event.set()
        with pytest.raises(Cancelled):
            check_cancelled()
    check_cancelled()


def sleep_in_worker(seconds: int) -> int:
    time.sleep(seconds)
    return seconds


def test_cancelling_a_job_in_worker_processes_ends_them():
    """A cancelled diagnosis does not wait for its worker processes' running jobs."""
    event = threading.Event()
    pool = Workers(2)
    threading.Timer(1.0, event.set).start()
    started = time.monotonic()
    with pytest.raises(Cancelled), cancellable(event), pool:
        pool.run(sleep_in_worker, [(60,), (60,)], None, "sleeping {}")
    assert time.monotonic() - started < 10.0
    assert pool._executor is None
