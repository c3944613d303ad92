"""Stopping the nodes: each executable started and stopped by SIGINT and by SIGTERM, in each condition it can
be in (idle, publishing at its full rate, mid-excitation, mid-refit), optionally with CPU-bound processes
beside it. A stop passes when the process exits within --limit seconds of the signal with status 0, and its
output has no traceback, no [ERROR]/[FATAL] line and no "Failed to publish log message to rosout".

Run: .venv/bin/python bench/bench_shutdown.py [--trials 100] [--load 2] [--limit 5]
     [--cells stage:idle,compensator:full_rate,...] [--log-dir DIR]
A stop that misses the limit is dumped with py-spy when it is installed (`--py-spy PATH`), then killed.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from record_results import recorded

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from sma_stage.nodes.launch import CONFIG_DIR, NodeProcess, NodeProcesses, RosClient, wait_for  # noqa: E402

SIGNALS = {"INT": signal.SIGINT, "TERM": signal.SIGTERM}
BAD_OUTPUT = ("Traceback", "[ERROR]", "[FATAL]", "Failed to publish log message to rosout")
READY_TIMEOUT_S = 60.0
FULL_RATE_HZ = 2000.0  # the largest rate_hz the nodes accept
STAGE_FAST = {"rate_hz": 100.0, "time_scale": 50.0}
EXCITE = {"excite_duration": 300.0, "excite_rate_hz": 20.0, "excite_time_scale": 50.0, "min_samples": 60,
          "operators": 5}
ALL_CELLS = ("stage:idle", "stage:full_rate", "compensator:idle", "compensator:full_rate",
             "identification:idle", "identification:full_rate", "identification:mid_excitation",
             "identification:mid_refit")


@dataclass
class Cell:
    """The stops of one node in one condition by one signal."""

    node: str
    condition: str
    signal_name: str
    seconds: list[float] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)
    in_condition: int = 0

    def row(self) -> str:
        """One row of the table."""
        times = np.array(self.seconds) if self.seconds else np.array([np.nan])
        missed = sum(1 for reason in self.failures if reason.startswith("no exit"))
        return (f"| {self.node} | {self.condition} | SIG{self.signal_name} | {len(self.seconds)} | "
                f"{self.in_condition} | "
                f"{np.median(times):.2f} | {np.percentile(times, 99):.2f} | {times.max():.2f} | {missed} | "
                f"{len(self.failures)} |")


@contextmanager
def cpu_load(processes: int) -> Iterator[None]:
    """Run `processes` CPU-bound Python processes for the block's duration."""
    burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(processes)]
    try:
        yield
    finally:
        for burner in burners:
            burner.kill()
            burner.wait()


def bad_lines(log: Path) -> list[str]:
    """The lines of a node's output that a clean stop must not print."""
    text = log.read_text(errors="replace") if log.exists() else ""
    return [line for line in text.splitlines() if any(mark in line for mark in BAD_OUTPUT)]


class Trial:
    """One start and stop of a node under test, with what the condition needs running beside it."""

    def __init__(self, nodes: NodeProcesses, client: RosClient, node: str, condition: str, workdir: Path) -> None:
        self.nodes, self.client, self.node, self.condition, self.workdir = nodes, client, node, condition, workdir
        self._publishing = threading.Event()
        self._publisher_thread: threading.Thread | None = None

    def start(self) -> NodeProcess:
        """Start the node under test in its condition's set-up, and wait until it is in that condition."""
        if self.node == "stage":
            rate = FULL_RATE_HZ if self.condition == "full_rate" else 50.0
            process = self.nodes.start("stage_node", {"rate_hz": rate}, [CONFIG_DIR / "stage.yaml"])
            self.wait_for_log(process, "active: accepting current_cmd")
            if self.condition == "full_rate":
                self.publish_fast("current_cmd", lambda k: 2.0 * np.sin(k * 1e-3))
        elif self.node == "compensator":
            rate = FULL_RATE_HZ if self.condition == "full_rate" else 50.0
            process = self.nodes.start("compensator_node", {"rate_hz": rate, "feedback": False},
                                       [CONFIG_DIR / "compensator.yaml"])
            self.wait_for_log(process, "compensator ready")
            if self.condition == "full_rate":
                self.publish_fast("setpoint", lambda k: 1e-4 * np.sin(k * 1e-3))
                wait_for(lambda: self.client.node.count_publishers("current_cmd") >= 1, 10.0, "current_cmd")
        else:
            process = self.start_identification()
        return process

    def start_identification(self) -> NodeProcess:
        bag = {"record_bag": str(self.workdir / f"bag_{time.monotonic_ns()}")} if self.condition == "full_rate" \
            else {}
        process = self.nodes.start("identification_node", {**EXCITE, "pause_compensator": False, **bag},
                                   [CONFIG_DIR / "identification.yaml"])
        self.wait_for_log(process, "identification ready")
        if self.condition == "full_rate":
            self.publish_fast("current_applied", lambda k: 2.0 * np.sin(k * 1e-3))
        elif self.condition in ("mid_excitation", "mid_refit"):
            self.client.wait_for_services(["identification/excite"], 30.0, self.nodes.check_running)
            ok, message = self.client.trigger("identification/excite")
            if not ok:
                raise RuntimeError(f"~/excite refused: {message}")
            if self.condition == "mid_excitation":
                time.sleep(0.5)
            else:
                self.wait_for_log(process, "excitation finished")
                self.client.trigger_async("identification/refit")
                self.wait_for_log(process, "~/refit: fitting", timeout_s=10.0)
                time.sleep(0.3)
        return process

    def wait_for_log(self, process: NodeProcess, text: str, timeout_s: float = READY_TIMEOUT_S) -> None:
        """Wait until the node has printed text."""
        wait_for(lambda: text in process.log_path.read_text(errors="replace"), timeout_s, repr(text),
                 self.nodes.check_running, poll_s=0.02)

    def publish_fast(self, topic: str, value: Callable[[int], float]) -> None:
        """Publish Float64 on topic as fast as this process can, until stop_publishing()."""
        from std_msgs.msg import Float64

        from sma_stage.nodes._common import COMMAND_QOS

        publisher = self.client.node.create_publisher(Float64, topic, COMMAND_QOS)
        self._publishing.set()

        def run() -> None:
            k = 0
            while self._publishing.is_set():
                publisher.publish(Float64(data=float(value(k))))
                k += 1

        self._publisher_thread = threading.Thread(target=run, daemon=True)
        self._publisher_thread.start()

    def stop_publishing(self) -> None:
        """End publish_fast's thread."""
        self._publishing.clear()
        if self._publisher_thread is not None:
            self._publisher_thread.join()


def in_condition(condition: str, log: str) -> bool:
    """Whether the node's output up to the signal shows it in the condition (a refit running, an excitation
    running; idle and full rate: started)."""
    if condition == "mid_refit":
        return "~/refit: fitting" in log and "~/refit: refit ok" not in log and "refit refused" not in log
    if condition == "mid_excitation":
        return "exciting:" in log and "excitation finished" not in log
    return "ready" in log


def dump(process: NodeProcess, py_spy: str | None, out: Path) -> None:
    """The Python stacks of a process that did not exit, when py-spy is available."""
    if py_spy:
        with open(out, "w") as file:
            subprocess.run([py_spy, "dump", "--pid", str(process.popen.pid)], stdout=file, stderr=subprocess.STDOUT,
                           timeout=30, check=False)


def run_trial(nodes: NodeProcesses, client: RosClient, cell: Cell, limit_s: float, workdir: Path,
              py_spy: str | None, index: int) -> None:
    """Start the node, bring it into the condition, signal it and judge the exit."""
    trial = Trial(nodes, client, cell.node, cell.condition, workdir)
    try:
        process = trial.start()
    except Exception as error:  # noqa: BLE001 -- a set-up failure is reported in the table, not a crash
        trial.stop_publishing()
        cell.failures.append(f"set-up: {' '.join(str(error).split())[:200]}")
        nodes.stop_all()
        return
    before = process.log_path.read_text(errors="replace")
    sent = time.monotonic()
    process.popen.send_signal(SIGNALS[cell.signal_name])
    try:
        status = process.popen.wait(limit_s)
        seconds = time.monotonic() - sent
    except subprocess.TimeoutExpired:
        seconds = time.monotonic() - sent
        stem = workdir / f"{cell.node}_{cell.condition}_{cell.signal_name}_{index}"
        dump(process, py_spy, stem.with_suffix(".stacks"))
        try:
            status = process.popen.wait(30.0)
            seconds = time.monotonic() - sent
        except subprocess.TimeoutExpired:
            process.popen.kill()
            status = process.popen.wait()
        shutil.copy(process.log_path, stem.with_suffix(".log"))
        cell.failures.append(f"no exit within {limit_s:g} s (exited after {seconds:.1f} s, status {status}): "
                             f"{stem}.log")
    trial.stop_publishing()
    nodes.forget(process)
    cell.seconds.append(seconds)
    cell.in_condition += in_condition(cell.condition, before)
    problems = bad_lines(process.log_path)
    if status != 0:
        cell.failures.append(f"status {status}: {process.log_tail(3)}")
    elif problems:
        stem = workdir / f"{cell.node}_{cell.condition}_{cell.signal_name}_{index}"
        shutil.copy(process.log_path, stem.with_suffix(".log"))
        cell.failures.append(f"output: {problems[0][:200]} ({stem}.log)")
    process.log_path.unlink(missing_ok=True)


def helpers(nodes: NodeProcesses, node: str, condition: str) -> None:
    """What a condition needs running beside the node under test for all its trials."""
    if node == "identification" and condition in ("mid_excitation", "mid_refit"):
        nodes.start("stage_node", STAGE_FAST, [CONFIG_DIR / "stage.yaml"])


def run_cell(cell: Cell, trials: int, limit_s: float, domain: int, workdir: Path, py_spy: str | None) -> None:
    """All the trials of one cell in its own ROS domain."""
    with NodeProcesses(workdir / "helpers", domain) as helper_nodes, RosClient(domain, "shutdown_bench") as client:
        helpers(helper_nodes, cell.node, cell.condition)
        nodes = NodeProcesses(workdir / "nodes", domain)
        for index in range(trials):
            run_trial(nodes, client, cell, limit_s, workdir, py_spy, index)
            helper_nodes.check_running()
        nodes.stop_all()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=100, help="stops per node, condition and signal")
    parser.add_argument("--load", type=int, default=2, help="CPU-bound processes running beside the nodes")
    parser.add_argument("--limit", type=float, default=5.0, help="a stop must end within this [s]")
    parser.add_argument("--cells", default=",".join(ALL_CELLS), help="node:condition, comma-separated")
    parser.add_argument("--signals", default="INT,TERM", help="INT, TERM or both")
    parser.add_argument("--domain", type=int, default=170, help="first ROS domain id (one per cell)")
    parser.add_argument("--log-dir", type=Path, default=None, help="keep failing nodes' logs here")
    parser.add_argument("--py-spy", default=shutil.which("py-spy"), help="py-spy, to dump a node that hangs")
    args = parser.parse_args()
    os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    workdir = args.log_dir or Path(tempfile.mkdtemp(prefix="bench_shutdown_"))
    workdir.mkdir(parents=True, exist_ok=True)
    cells = [Cell(*name.split(":"), signal_name) for name in args.cells.split(",")
             for signal_name in args.signals.split(",")]
    started = time.monotonic()
    print(f"{args.trials} stops per row, {args.load} CPU-bound processes beside, limit {args.limit:g} s; logs of "
          f"failures in {workdir}\n")
    print("| node | condition | signal | stops | in the condition | median [s] | p99 [s] | max [s] | over the limit "
          "| failed |")
    print("|---|---|---|---|---|---|---|---|---|---|", flush=True)
    with cpu_load(args.load):
        for number, cell in enumerate(cells):
            run_cell(cell, args.trials, args.limit, args.domain + number, workdir, args.py_spy)
            print(cell.row(), flush=True)
    print(f"\n{(time.monotonic() - started) / 60:.1f} min")
    failures = [f"{cell.node} {cell.condition} SIG{cell.signal_name}: {reason}" for cell in cells
                for reason in cell.failures]
    for line in failures[:40]:
        print(f"- {line}")
    return 1 if failures else 0


if __name__ == "__main__":
    with recorded(__file__):
        sys.exit(main())
