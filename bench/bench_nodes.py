"""Node benchmarks: `setpoint` -> `current_cmd` latency of the compensator across processes, and the timing
of the stage's `joint_states` at 500 Hz. The nodes run as separate processes from their installed
executables; a probe node in this process drives them and timestamps every message (loopback only).

Run: .venv/bin/python bench/bench_nodes.py [--setpoints 2000] [--setpoint-rate 200] [--seconds 60]
"""

from __future__ import annotations

import argparse
import functools
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from record_results import recorded

REPO = Path(__file__).resolve().parent.parent
SHIPPED_MODEL_FILE = REPO / "config" / "model_default.yaml"
BIN_DIR = Path(sys.executable).parent
SETPOINT_AMPLITUDE_M = 1.5e-4   # within the default model's reach (about -0.26..+0.30 mm)
SETPOINT_PERIOD_S = 1.0
WARMUP_SETPOINTS = 200
NODE_START_TIMEOUT_S = 60.0
FIRST_REPLY_TIMEOUT_S = 60.0
REPLY_GAP_S = 2.0
MATCH_TOLERANCE_A = 1e-9        # consecutive setpoints' currents differ by millamperes
STAGE_DRIVE_RATE_HZ = 50.0
STAGE_DRIVE_AMPLITUDE_A = 3.0
STAGE_DRIVE_PERIOD_S = 5.0


def isolate_ros(domain_id: int) -> None:
    """Loopback-only Fast DDS on a private domain, for this process and the nodes it starts."""
    os.environ["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ["ROS_DOMAIN_ID"] = str(domain_id)
    os.environ.pop("ROS_LOCALHOST_ONLY", None)
    os.environ.pop("ROS_STATIC_PEERS", None)
    os.environ["PYTHONUNBUFFERED"] = "1"


# ---------------------------------------------------------------------------------------------------------
# child processes


@dataclass
class Child:
    """A node started as a separate process, its output in a temporary log file."""

    name: str
    process: subprocess.Popen
    log: Path

    def tail(self, lines: int = 20) -> str:
        """The last lines of the node's output."""
        text = self.log.read_text(errors="replace").splitlines()
        return "\n".join(text[-lines:])

    def check_alive(self) -> None:
        """RuntimeError with the node's output when it has exited."""
        code = self.process.poll()
        if code is not None:
            raise RuntimeError(f"{self.name} exited with {code}:\n{self.tail()}")

    def cpu_seconds(self) -> float:
        """User plus system CPU time [s] the process has used so far (Linux /proc)."""
        fields_after_name = Path(f"/proc/{self.process.pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields_after_name[11]) + int(fields_after_name[12])) / os.sysconf("SC_CLK_TCK")

    def stop(self, timeout_s: float = 5.0) -> None:
        """SIGINT, then SIGKILL when it has not ended within timeout_s."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
            try:
                self.process.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout=timeout_s)
        self.log.unlink(missing_ok=True)


def start_child(name: str, command: Sequence[str]) -> Child:
    """Start command with its output going to a log file (a pipe could fill and block the node)."""
    handle, path = tempfile.mkstemp(prefix=f"bench_{name}_", suffix=".log")
    with os.fdopen(handle, "w") as log:
        process = subprocess.Popen(list(command), stdout=log, stderr=subprocess.STDOUT, cwd=REPO,
                                   stdin=subprocess.DEVNULL)
    return Child(name, process, Path(path))


def node_command(executable: str, *ros_args: str) -> list[str]:
    """The installed executable next to this Python, with --ros-args."""
    path = BIN_DIR / executable
    if not path.exists():
        raise SystemExit(f"error: {path} not found: install the package (./run.sh setup) or pass --bin-dir")
    return [str(path), "--ros-args", *ros_args]


def runner_command(node: str, executor: str, *ros_args: str) -> list[str]:
    """bench/node_runner.py: node (stage, compensator, echo) under executor (single, events)."""
    return [sys.executable, str(REPO / "bench" / "node_runner.py"), node, executor, "--ros-args", *ros_args]


# ---------------------------------------------------------------------------------------------------------
# ROS helpers


class Ros:
    """A private rclpy context with an executor the benchmark spins itself: rclpy's EventsExecutor, as the
    nodes use, so the probe's own overhead weighs as little as theirs."""

    def __init__(self, domain_id: int) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.experimental import EventsExecutor
        from rclpy.signals import SignalHandlerOptions

        self.context = Context()
        # Keep Python's Ctrl-C (KeyboardInterrupt), so the finally blocks stop the node processes.
        rclpy.init(context=self.context, domain_id=domain_id, signal_handler_options=SignalHandlerOptions.NO)
        self.executor = EventsExecutor(context=self.context)
        self.nodes: list = []

    def add(self, node):
        """Spin node with the others."""
        self.nodes.append(node)
        self.executor.add_node(node)
        return node

    def remove(self, node) -> None:
        """Stop spinning node and destroy it."""
        self.executor.remove_node(node)
        self.nodes.remove(node)
        node.destroy_node()

    def probe(self, name: str):
        """A fresh node in this context, without parameter services (a smaller wait set)."""
        from rclpy.node import Node

        return self.add(Node(name, context=self.context, start_parameter_services=False))

    def spin_until(self, predicate: Callable[[], bool], timeout_s: float, what: str,
                   children: Sequence[Child] = ()) -> None:
        """Spin until predicate() holds; RuntimeError after timeout_s or when a child has exited."""
        deadline = time.monotonic() + timeout_s
        while not predicate():
            for child in children:
                child.check_alive()
            if time.monotonic() > deadline:
                raise RuntimeError(f"timed out after {timeout_s:g} s waiting for {what}")
            self.executor.spin_once(timeout_sec=0.01)

    def close(self) -> None:
        """Destroy the nodes and shut the context down."""
        self.executor.shutdown(timeout_sec=2.0)
        for node in self.nodes:
            node.destroy_node()
        self.context.try_shutdown()


def percentiles_ms(values_ns: np.ndarray) -> tuple[float, float, float]:
    """p50, p99 and max [ms] of values [ns]."""
    p50, p99 = np.percentile(values_ns, [50, 99])
    return p50 * 1e-6, p99 * 1e-6, float(values_ns.max()) * 1e-6



# ---------------------------------------------------------------------------------------------------------
# 1. setpoint -> current_cmd latency


@dataclass(frozen=True)
class Case:
    """One configuration to measure: a command to start as a child process, or in-process when None."""

    label: str
    command: list[str] | None
    echo: bool = False


def setpoint_sequence(count: int, rate_hz: float) -> np.ndarray:
    """A sine of setpoints [m] sampled at rate_hz: consecutive values differ, so replies can be told apart."""
    t = np.arange(count) / rate_hz
    return SETPOINT_AMPLITUDE_M * np.sin(2.0 * np.pi * t / SETPOINT_PERIOD_S + 0.1)


@functools.cache
def plain_model_file() -> Path:
    """The shipped model's GPI without its lag, in a temporary file: the compensator (feedforward, no rate
    limit) then answers with the plain exact inverse, which this benchmark runs too to match replies."""
    from sma_stage.model import IdentifiedModel, load_model_file

    shipped = load_model_file(SHIPPED_MODEL_FILE)
    path = Path(tempfile.mkdtemp(prefix="bench_nodes_")) / "plain_model.yaml"
    IdentifiedModel(shipped.parameters, shipped.operators).save(path)
    return path


def expected_commands(setpoints: np.ndarray, max_current_a: float = 5.0) -> np.ndarray:
    """The currents [A] the compensator answers to setpoints: the same exact inverse stream, run here."""
    from sma_stage.model import GPIInverseStream, load_model_file

    model = load_model_file(plain_model_file())
    stream = GPIInverseStream(model.parameters, model.operators, "exact", input_range=(-max_current_a, max_current_a))
    return np.array([stream.step(value) for value in setpoints])


@dataclass
class LatencyRun:
    """Round-trip times [ns] of the timed setpoints, setpoints never answered, replies that matched none,
    and the node's CPU time [s] over the run."""

    latencies_ns: list[int] = field(default_factory=list)
    lost: int = 0
    unmatched: int = 0
    node_cpu_s: float | None = None


class LatencyProbe:
    """Publishes setpoints from a timer at a fixed rate and times the matching current_cmd replies.

    A reply answers the oldest pending setpoint whose expected current it equals (within MATCH_TOLERANCE_A);
    older pending ones were lost (the node's depth-10 queue overflowed). A reply that answers no pending
    setpoint (the compensator's periodic repeat of its last command) counts as unmatched."""

    def __init__(self, ros: Ros, setpoints: np.ndarray, expected: np.ndarray, rate_hz: float) -> None:
        from std_msgs.msg import Float64

        from sma_stage.nodes._common import COMMAND_QOS

        self.Float64 = Float64
        self.node = ros.probe("latency_probe")
        self.publisher = self.node.create_publisher(Float64, "setpoint", COMMAND_QOS)
        self.subscription = self.node.create_subscription(Float64, "current_cmd", self.on_reply, COMMAND_QOS)
        self.setpoints = setpoints.tolist()
        self.expected = expected.tolist()
        self.period_s = 1.0 / rate_hz
        self.next_index = 0
        self.stop_index = 0
        self.pending: deque[tuple[int, int]] = deque()
        self.last_reply_s = time.monotonic()
        self.reply_gap_s = REPLY_GAP_S
        self.run = LatencyRun()
        self.timer = None

    def connected(self) -> bool:
        """True once the node under test both listens to setpoint and publishes current_cmd."""
        return self.publisher.get_subscription_count() > 0 and self.subscription.get_publisher_count() > 0

    def send_next(self) -> None:
        """Publish the next setpoint, stamping the send time."""
        if self.next_index >= self.stop_index:
            return
        index = self.next_index
        self.next_index += 1
        message = self.Float64(data=self.setpoints[index])
        self.pending.append((index, time.perf_counter_ns()))
        self.publisher.publish(message)

    def on_reply(self, message) -> None:
        """Time a reply against the pending setpoint it answers."""
        now = time.perf_counter_ns()
        self.last_reply_s = time.monotonic()
        for position, (index, sent) in enumerate(self.pending):
            if abs(message.data - self.expected[index]) <= MATCH_TOLERANCE_A:
                for _ in range(position + 1):
                    self.pending.popleft()
                self.run.lost += position
                self.run.latencies_ns.append(now - sent)
                return
        self.run.unmatched += 1

    def finished(self) -> bool:
        """All sent and answered, or no reply for REPLY_GAP_S after the last send (the rest count as lost)."""
        if self.next_index < self.stop_index:
            return False
        return not self.pending or time.monotonic() - self.last_reply_s > self.reply_gap_s

    def send(self, ros: Ros, count: int, children: Sequence[Child], timeout_s: float,
             reply_gap_s: float = REPLY_GAP_S) -> LatencyRun:
        """Send the next count setpoints at the rate and collect the replies; the run's figures."""
        self.run = LatencyRun()
        self.reply_gap_s = reply_gap_s
        self.stop_index = self.next_index + count
        self.last_reply_s = time.monotonic()
        if self.timer is None:
            self.timer = self.node.create_timer(self.period_s, self.send_next)
        ros.spin_until(self.finished, timeout_s, f"{count} setpoints to be sent", children)
        self.run.lost += len(self.pending)
        self.pending.clear()
        if not self.run.latencies_ns:
            raise RuntimeError(f"no reply on current_cmd to {count} setpoints")
        return self.run


def measure_latency(ros: Ros, count: int, rate_hz: float, children: Sequence[Child], echo: bool) -> LatencyRun:
    """Prime (first reply, compile), warm up, then time count setpoint -> current_cmd round trips."""
    setpoints = setpoint_sequence(1 + WARMUP_SETPOINTS + count, rate_hz)
    expected = setpoints if echo else expected_commands(setpoints)
    probe = LatencyProbe(ros, setpoints, expected, rate_hz)
    try:
        ros.spin_until(probe.connected, NODE_START_TIMEOUT_S, "the node under test to connect", children)
        probe.send(ros, 1, children, FIRST_REPLY_TIMEOUT_S + 1.0, reply_gap_s=FIRST_REPLY_TIMEOUT_S)
        probe.send(ros, WARMUP_SETPOINTS, children, WARMUP_SETPOINTS / rate_hz + 30.0)
        cpu_before = children[0].cpu_seconds() if children else None
        run = probe.send(ros, count, children, count / rate_hz + 30.0)
        if children:
            run.node_cpu_s = children[0].cpu_seconds() - cpu_before
        return run
    finally:
        ros.remove(probe.node)


def compensator_overrides():
    """The compensator's parameters for the benchmark: the plain model file, feedforward without the rate
    limit, repeats every 10 s only."""
    from rclpy.parameter import Parameter

    return [Parameter("model_file", value=str(plain_model_file())), Parameter("rate_hz", value=0.1),
            Parameter("feedback", value=False), Parameter("max_current_rate", value=0.0)]


def latency_case(case: Case, args: argparse.Namespace) -> LatencyRun:
    """Measure one case: its node as a child process, or CompensatorNode in the probe's executor."""
    ros = Ros(args.domain_id)
    child = start_child("latency", case.command) if case.command is not None else None
    try:
        if child is None:
            from sma_stage.nodes.compensator_node import CompensatorNode

            ros.add(CompensatorNode(context=ros.context, parameter_overrides=compensator_overrides()))
        return measure_latency(ros, args.setpoints, args.setpoint_rate, [child] if child else [], case.echo)
    except RuntimeError as error:
        raise RuntimeError(f"{case.label}: {error}") from None
    finally:
        if child is not None:
            child.stop()
        ros.close()


def callback_cost(count: int, rate_hz: float, domain_id: int) -> np.ndarray:
    """Time [ns] of CompensatorNode.on_setpoint called directly (inverse step and publish), count calls."""
    from std_msgs.msg import Float64

    from sma_stage.nodes.compensator_node import CompensatorNode

    ros = Ros(domain_id)
    try:
        node = ros.add(CompensatorNode(context=ros.context, parameter_overrides=compensator_overrides()))
        messages = [Float64(data=value) for value in setpoint_sequence(WARMUP_SETPOINTS + count, rate_hz)]
        costs = np.empty(len(messages), dtype=np.int64)
        for index, message in enumerate(messages):
            start = time.perf_counter_ns()
            node.on_setpoint(message)
            costs[index] = time.perf_counter_ns() - start
        return costs[WARMUP_SETPOINTS:]
    finally:
        ros.close()


def latency_cases(args: argparse.Namespace) -> list[Case]:
    """The target case first, then the comparisons."""
    model = ("-p", f"model_file:={plain_model_file()}", "-p", "rate_hz:=0.1", "-p", "feedback:=false",
             "-p", "max_current_rate:=0.0")
    cases = [Case("compensator_node (installed executable)", node_command("compensator_node", *model))]
    if args.compare:
        cases.append(Case("compensator, SingleThreadedExecutor", runner_command("compensator", "single", *model)))
    cases.append(Case("echo node (no model)", runner_command("echo", "events"), echo=True))
    if args.compare:
        cases.append(Case("echo node (no model), SingleThreadedExecutor", runner_command("echo", "single"),
                          echo=True))
    cases.append(Case("compensator in the probe's process and executor", None))
    return cases


def latency_table(args: argparse.Namespace) -> float:
    """Measure and print the latency table; returns the p99 [ms] of the target case."""
    rows = []
    for case in latency_cases(args):
        run = latency_case(case, args)
        values = np.array(run.latencies_ns, dtype=np.int64)
        cpu = "" if run.node_cpu_s is None else f"{run.node_cpu_s / values.size * 1e6:.0f}"
        rows.append((case.label, values, str(run.lost), str(run.unmatched), cpu))
    rows.append(("compensator `on_setpoint` called directly (no transport)",
                 callback_cost(args.setpoints, args.setpoint_rate, args.domain_id), "", "", ""))
    print(f"\n### setpoint -> current_cmd ({args.setpoints} setpoints at {args.setpoint_rate:g} Hz after "
          f"{WARMUP_SETPOINTS} warm-up ones, reliable QoS depth 10)\n")
    print("Round trip timed in the probe, from just before `publish(setpoint)` to the entry of its `current_cmd`")
    print("callback, so it includes the probe's own executor (EventsExecutor). Separate processes unless the row")
    print("says otherwise; executor EventsExecutor (as the installed executables) unless it says")
    print("SingleThreadedExecutor (bench/node_runner.py). Node CPU: the node process's user+system time per setpoint.")
    print("Lost: setpoints never answered (dropped from a full depth-10 queue); unmatched: replies that answer")
    print("no pending setpoint (the compensator repeats its last command every 1/rate_hz = 10 s).\n")
    print("| path | replies | lost | unmatched | p50 [ms] | p99 [ms] | max [ms] | node CPU per setpoint [us] |")
    print("|---|---|---|---|---|---|---|---|")
    for label, values, lost, unmatched, cpu in rows:
        p50, p99, peak = percentiles_ms(values)
        print(f"| {label} | {values.size} | {lost} | {unmatched} | {p50:.3f} | {p99:.3f} | {peak:.2f} | {cpu} |")
    return percentiles_ms(rows[0][1])[1]


# ---------------------------------------------------------------------------------------------------------
# 2. stage timing


@dataclass
class StageRecord:
    """joint_states as received: header stamps (ROS time), monotonic and wall arrival times [ns]."""

    stamps_ns: list[int] = field(default_factory=list)
    arrivals_ns: list[int] = field(default_factory=list)
    arrivals_wall_ns: list[int] = field(default_factory=list)
    recording: bool = False
    first_arrival_ns: int | None = None
    node_cpu_s: float = 0.0
    probe_cpu_s: float = 0.0


class StageProbe:
    """Drives the stage with a slow current sine and records every joint_states."""

    def __init__(self, ros: Ros) -> None:
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64

        from sma_stage.nodes._common import COMMAND_QOS

        self.Float64 = Float64
        self.node = ros.probe("stage_probe")
        deep = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
        self.subscription = self.node.create_subscription(JointState, "joint_states", self.on_state, deep)
        self.publisher = self.node.create_publisher(Float64, "current_cmd", COMMAND_QOS)
        self.node.create_timer(1.0 / STAGE_DRIVE_RATE_HZ, self.drive)
        self.start_s = time.monotonic()
        self.record = StageRecord()

    def drive(self) -> None:
        """Publish the drive current [A]: a sine that heats each wire in turn."""
        t = time.monotonic() - self.start_s
        value = STAGE_DRIVE_AMPLITUDE_A * math.sin(2.0 * math.pi * t / STAGE_DRIVE_PERIOD_S)
        self.publisher.publish(self.Float64(data=value))

    def on_state(self, message) -> None:
        """Keep the arrival times and the header stamp."""
        arrival, wall = time.perf_counter_ns(), time.time_ns()
        record = self.record
        if record.first_arrival_ns is None:
            record.first_arrival_ns = arrival
        if record.recording:
            stamp = message.header.stamp
            record.stamps_ns.append(stamp.sec * 1_000_000_000 + stamp.nanosec)
            record.arrivals_ns.append(arrival)
            record.arrivals_wall_ns.append(wall)


def measure_stage(command: list[str], args: argparse.Namespace) -> StageRecord:
    """Start the stage, wait for its first message, warm up, record args.seconds of joint_states."""
    ros = Ros(args.domain_id)
    child = start_child("stage", command)
    try:
        probe = StageProbe(ros)
        record = probe.record
        ros.spin_until(lambda: record.first_arrival_ns is not None, NODE_START_TIMEOUT_S,
                       "the first joint_states", [child])
        settle_until = time.monotonic() + args.warmup
        ros.spin_until(lambda: time.monotonic() >= settle_until, args.warmup + 5.0, "warm-up", [child])
        node_cpu, probe_cpu = child.cpu_seconds(), time.process_time()
        record.recording = True
        stop_at = time.monotonic() + args.seconds
        ros.spin_until(lambda: time.monotonic() >= stop_at, args.seconds + 5.0, "the recording", [child])
        record.recording = False
        record.node_cpu_s, record.probe_cpu_s = child.cpu_seconds() - node_cpu, time.process_time() - probe_cpu
        child.check_alive()
        return record
    except RuntimeError as error:
        raise RuntimeError(f"{' '.join(command[:3])}: {error}") from None
    finally:
        child.stop()
        ros.close()


@dataclass(frozen=True)
class Intervals:
    """Timing of a series of times [ns] against a period [ns]."""

    count: int
    rate_hz: float
    p50_ms: float
    p99_ms: float
    max_ms: float
    late: int
    late_pct: float

    @classmethod
    def of(cls, times_ns: np.ndarray, period_ns: float) -> Intervals:
        intervals = np.diff(times_ns)
        late = intervals > 2.0 * period_ns
        return cls(times_ns.size, intervals.size / ((times_ns[-1] - times_ns[0]) * 1e-9),
                   *percentiles_ms(intervals), int(late.sum()), float(late.mean()) * 100.0)

    def row(self, label: str) -> str:
        return (f"| {label} | {self.count} | {self.rate_hz:.2f} | {self.p50_ms:.3f} | {self.p99_ms:.3f} | "
                f"{self.max_ms:.2f} | {self.late} | {self.late_pct:.3f} |")


def missing_messages(stamps_ns: np.ndarray, period_ns: float) -> tuple[int, int]:
    """Messages short of one per period over the stamps' span, and the periods in that span."""
    expected = int(round((stamps_ns[-1] - stamps_ns[0]) / period_ns)) + 1
    return max(0, expected - stamps_ns.size), expected


def stage_cases(args: argparse.Namespace) -> list[Case]:
    """The target case first, then the SingleThreadedExecutor comparison."""
    rate = ("-p", f"rate_hz:={float(args.stage_rate)!r}")
    cases = [Case("stage_node (installed executable)", node_command("stage_node", *rate))]
    if args.compare:
        cases.append(Case("stage, SingleThreadedExecutor", runner_command("stage", "single", *rate)))
    return cases


def stage_table(args: argparse.Namespace) -> float:
    """Measure and print the stage timing tables; returns the late percentage of the target case's stamps."""
    period_ns = 1e9 / args.stage_rate
    results = []
    for case in stage_cases(args):
        record = measure_stage(case.command, args)
        stamps = np.array(record.stamps_ns, dtype=np.int64)
        arrivals = np.array(record.arrivals_ns, dtype=np.int64)
        delays = np.array(record.arrivals_wall_ns, dtype=np.int64) - stamps
        results.append((case.label, record, Intervals.of(stamps, period_ns), Intervals.of(arrivals, period_ns),
                        missing_messages(stamps, period_ns), percentiles_ms(delays)))
    print(f"\n### stage at {args.stage_rate:g} Hz for {args.seconds:g} s (period {period_ns * 1e-6:g} ms, after "
          f"{args.warmup:g} s of warm-up, driven by a {STAGE_DRIVE_AMPLITUDE_A:g} A sine on current_cmd at "
          f"{STAGE_DRIVE_RATE_HZ:g} Hz)\n")
    print("A cycle is *late* when its joint_states comes more than 2 periods after the previous one, i.e. more")
    print("than one period after it was due. Stamps: the header stamps the stage takes when it publishes (its")
    print("publication times); arrivals: when the probe's callback runs. Separate processes.\n")
    print("| node | times | messages | mean rate [Hz] | interval p50 [ms] | p99 [ms] | max [ms] | late cycles "
          "| late [%] |")
    print("|---|---|---|---|---|---|---|---|---|")
    for label, _, stamps, arrivals, _, _ in results:
        print(stamps.row(f"{label} | stamps"))
        print(arrivals.row(f"{label} | arrivals"))
    print("\nMissing: messages short of one per period over the span of the stamps (a timer that skips late")
    print("periods loses them; one that catches up does not).\n")
    print("| node | missing joint_states | stamp to arrival p50 / p99 / max [ms] | node CPU per cycle "
          "[us] | node CPU [% of a core] | probe CPU [% of a core] |")
    print("|---|---|---|---|---|---|")
    for label, record, stamps, _, (missed, spanned), (p50, p99, peak) in results:
        print(f"| {label} | {missed} of {spanned} ({100.0 * missed / spanned:.2f} %) | {p50:.3f} / {p99:.3f} / "
              f"{peak:.2f} | {record.node_cpu_s / stamps.count * 1e6:.0f} | "
              f"{100.0 * record.node_cpu_s / args.seconds:.1f} | {100.0 * record.probe_cpu_s / args.seconds:.1f} |")
    return results[0][2].late_pct


# ---------------------------------------------------------------------------------------------------------


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """Command-line options."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--setpoints", type=int, default=2000, help="timed setpoints per latency row")
    parser.add_argument("--setpoint-rate", type=float, default=200.0, help="setpoint rate [Hz]")
    parser.add_argument("--stage-rate", type=float, default=500.0, help="stage rate_hz [Hz]")
    parser.add_argument("--seconds", type=float, default=60.0, help="stage recording length [s]")
    parser.add_argument("--warmup", type=float, default=2.0, help="stage warm-up before recording [s]")
    parser.add_argument("--domain-id", type=int, default=220 + os.getpid() % 13,
                        help="ROS domain id (default 220..232, away from the tests' domains)")
    parser.add_argument("--bin-dir", type=Path, default=None, help="directory of the installed node executables")
    parser.add_argument("--no-compare", dest="compare", action="store_false",
                        help="skip the SingleThreadedExecutor comparison rows")
    parser.add_argument("--skip-latency", action="store_true", help="skip the setpoint -> current_cmd table")
    parser.add_argument("--skip-stage", action="store_true", help="skip the stage timing tables")
    args = parser.parse_args(argv)
    if not (args.setpoints >= 10 and args.setpoint_rate > 0 and args.seconds > 0 and args.warmup >= 0
            and 1 <= args.stage_rate <= 2000 and 0 <= args.domain_id <= 232):
        parser.error("--setpoints >= 10, rates and --seconds > 0, --stage-rate 1..2000, --domain-id 0..232")
    return args


def interrupt(signum: int, frame: object) -> None:
    """SIGTERM handler: unwind like Ctrl-C so the node processes are stopped."""
    raise KeyboardInterrupt


def main(argv: Sequence[str] | None = None) -> None:
    """Run the benchmarks and print the tables and the verdicts on the targets."""
    global BIN_DIR
    args = parse_args(argv)
    signal.signal(signal.SIGTERM, interrupt)
    if args.bin_dir is not None:
        BIN_DIR = args.bin_dir
    isolate_ros(args.domain_id)
    print(f"# Node benchmarks\n\n{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f} at the start, "
          f"{os.environ['RMW_IMPLEMENTATION']}, domain {args.domain_id}, {time.strftime('%Y-%m-%d %H:%M')}.")
    verdicts = []
    if not args.skip_latency:
        p99 = latency_table(args)
        verdicts.append(f"latency p99 {p99:.3f} ms across processes (target <= 2 ms: "
                        f"{'met' if p99 <= 2.0 else 'missed'})")
    if not args.skip_stage:
        late = stage_table(args)
        verdicts.append(f"stage late cycles {late:.3f} % (target <= 1 %: {'met' if late <= 1.0 else 'missed'})")
    print(f"\nLoad average {os.getloadavg()[0]:.2f} at the end. " + "; ".join(verdicts) + ".")


if __name__ == "__main__":
    with recorded(__file__):
        try:
            main()
        except KeyboardInterrupt:
            sys.exit("interrupted (the node processes were stopped)")
        except RuntimeError as error:
            sys.exit(f"error: {error}")
