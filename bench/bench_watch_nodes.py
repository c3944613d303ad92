"""The model watch through the three node executables beside the same loop in process, on the same record: how far
the GPI's residual wanders with nothing changed (`bias_held_out_m`), how soon a load step is flagged, alarms before
it. Prints one table and writes it to bench/results/watch_nodes.md.

    .venv/bin/python bench/bench_watch_nodes.py [--time-scales 20,50] [--setpoints sine,levels] [--families gpi]
                                                [--load-step-n 2] [--runs 1] [--hours 0]

Each run starts stage_node (simulator on simulated time, `lockstep_timeout` so that it steps once per command;
frozen by `~/freeze_time` while the refit runs, so that the refit's wall time is not simulated time),
compensator_node (`control_trigger: joint_states`, the PI loop) and identification_node (the watch's defaults,
on_drift report) as processes; excites 500 s, refits (families), then tracks a setpoint (a sine of 200 s period,
or random levels held 60 s, over +-30 % of the excitation's range) with a load step at LOAD_STEP_S. The bench
records every joint_states (position and the current applied, in effort) and what /diagnostics says of the watch.
Three figures per run:
- nodes: the identification node's watch, from /diagnostics;
- record: the same record watched in this process from where the node started its watch (checks the node's
  watch against the library on the same samples);
- process: the record replayed through a fresh simulator up to the tracking's start (the replay must reproduce
  every recorded position: it checks that the record is whole), then the same loop (`Compensator`, the node's
  settings, the model the compensator published) tracking the same setpoint in this process, watched the same way.
The issue's target: nodes within 2x of process. `--hours H` adds a run per time scale with H hours of the sine and
no load step (false alarms). ROS_DOMAIN_ID: each run takes its own, from 220 to 232 (above the 120-219 the
tests hand out, so that a test suite beside the bench cannot call its nodes).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))

from record_results import recorded  # noqa: E402

from sma_stage.control import Compensator  # noqa: E402
from sma_stage.errors import InputError  # noqa: E402
from sma_stage.identify.watch import DriftTest, ModelWatch  # noqa: E402
from sma_stage.model.kinds import any_model_from_yaml_text  # noqa: E402
from sma_stage.nodes._common import JOINT_NAME  # noqa: E402
from sma_stage.nodes.launch import CONFIG_DIR, NodeProcesses, RosClient, wait_for  # noqa: E402
from sma_stage.plant import Effects, StageConfig, StageSimulator  # noqa: E402

STEP_S = 0.5  # simulated s per stage step, control period and setpoint
EXCITE_S = 500.0
LOAD_STEP_S = 6000.0  # [s simulated]: the refit (the stage runs on meanwhile) and the watch's calibration before it
AFTER_STEP_S = 400.0
SINE_PERIOD_S = 200.0
HOLD_S = 60.0
FRACTION = 0.3  # of the excitation's range, each side of its middle
LOCKSTEP_TIMEOUT_S = 0.5  # [wall s]
AHEAD_STEPS = 20  # setpoints are sent this many steps ahead: with 2, a client starved beside a test suite fell
# behind, held levels stepped late and the two loops' positions came 47 um RMS apart
WATCH_RECORD_S = 900.0  # the identification node's watch_record default: the history a new model's watch starts from
CHUNK = 10  # samples per call of the in-process watch
FIRST_DOMAIN, LAST_DOMAIN = 220, 232


class Session:
    """The bench's node: records joint_states, the watch's /diagnostics and the model in force; while a profile is
    set, answers each position with the setpoint AHEAD_STEPS steps ahead, stamped with its time (`setpoint_stamped`:
    the compensator takes it at that time, so that no setpoint reaches it early, nor late unless this node falls
    AHEAD_STEPS behind the stage)."""

    def __init__(self, node) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState
        from std_msgs.msg import String

        from sma_stage.nodes._common import COMMAND_QOS, REPORT_QOS

        self._lock = threading.Lock()
        self._joint_state = JointState
        self.states: list[tuple[float, float, float]] = []  # (stamp [s], position [m], effort: current [A])
        self.watch: list[tuple[float, dict[str, str]]] = []
        self.models: list[tuple[float, str]] = []  # (stamp of the last state then [s], model YAML)
        self.profile = None
        self.lockstep_timeouts = "?"  # the stage's count on /diagnostics
        self.setpoint_pub = node.create_publisher(JointState, "setpoint_stamped", COMMAND_QOS)
        node.create_subscription(JointState, "joint_states", self.on_state,
                                 QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
        node.create_subscription(DiagnosticArray, "/diagnostics", self.on_diagnostics, 100)
        node.create_subscription(String, "compensator/model", self.on_model, REPORT_QOS)

    def on_state(self, message) -> None:
        stamp_s = message.header.stamp.sec + 1e-9 * message.header.stamp.nanosec
        with self._lock:
            self.states.append((stamp_s, float(message.position[0]), float(message.effort[0])))
            profile = self.profile
        if profile is not None:
            self.publish_setpoint(stamp_s + AHEAD_STEPS * STEP_S)

    def publish_setpoint(self, time_s: float) -> None:
        """The profile's setpoint [m] for time_s [s], stamped with it."""
        from rclpy.time import Time

        message = self._joint_state(name=[JOINT_NAME], position=[float(self.profile(time_s))])
        message.header.stamp = Time(nanoseconds=round(time_s * 1e9)).to_msg()
        self.setpoint_pub.publish(message)

    def on_diagnostics(self, message) -> None:
        stamp_s = message.header.stamp.sec + 1e-9 * message.header.stamp.nanosec
        for status in message.status:
            if status.name.endswith("sim stage"):
                values = {item.key: item.value for item in status.values}
                self.lockstep_timeouts = values.get("lockstep_timeouts", "?")
            if status.name.endswith("model watch"):
                with self._lock:
                    self.watch.append((stamp_s, {item.key: item.value for item in status.values}))

    def on_model(self, message) -> None:
        with self._lock:
            last_s = self.states[-1][0] if self.states else 0.0
            self.models.append((last_s, json.loads(message.data)["model"]))

    def now_s(self) -> float:
        with self._lock:
            return self.states[-1][0] if self.states else 0.0


@dataclass
class NodesRun:
    """What one run through the nodes left: the record, the watch's statuses, the model in force and when."""

    states: np.ndarray  # rows (stamp [s], position [m], current [A])
    watch: list[tuple[float, dict[str, str]]]
    model_yaml: str
    pushed_s: float  # the last state's stamp when the refitted model was seen in force [s]
    tracking_s: float  # the stamp of the position the first command answered [s]
    setpoint: object
    until_s: float  # the last time tracked [s]
    wall_s: float
    lockstep_timeouts: str = "?"
    notes: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class BenchSettings:
    """What the command line may change: the sine's period [s] and the watch's calibration windows."""

    sine_period_s: float = SINE_PERIOD_S
    calibration_windows: int = DriftTest().calibration_windows

    @property
    def test(self) -> DriftTest:
        return DriftTest(calibration_windows=self.calibration_windows)

    @property
    def calibration_s(self) -> float:
        """Simulated s from a model in force to the end of the watch's calibration."""
        return (self.test.warmup_windows + self.test.calibration_windows) * self.test.window_s


settings = BenchSettings()


def make_setpoint(kind: str, low: float, high: float, start_s: float):
    """The setpoint [m] as a function of time [s]: a sine, or random levels, over +-FRACTION of the range."""
    middle, amplitude = 0.5 * (low + high), FRACTION * (high - low)
    if kind == "sine":
        return lambda t: middle + amplitude * math.sin(2 * math.pi * (t - start_s) / settings.sine_period_s)
    levels = middle + amplitude * np.random.default_rng(5).uniform(-1.0, 1.0, 10_000)
    return lambda t: float(levels[int(max(t - start_s, 0.0) // HOLD_S)])


def run_nodes(domain: int, time_scale: float, kind: str, families: list[str], load_n: float, watched_s: float | None,
              out_dir: Path) -> NodesRun:
    """Excite, refit and track through the three nodes: until AFTER_STEP_S after the load step, or (watched_s)
    until the watch has judged watched_s [s] after its calibration."""
    started = time.monotonic()
    with NodeProcesses(out_dir, domain) as nodes:
        nodes.start("compensator_node", {"rate_hz": 1.0 / STEP_S, "use_sim_time": True,
                                         "control_trigger": "joint_states"}, [CONFIG_DIR / "compensator.yaml"])
        nodes.start("identification_node", {"excite_duration": EXCITE_S, "excite_rate_hz": 1.0 / STEP_S,
                                            "min_samples": 60, "model_file": str(out_dir / "model.yaml"),
                                            "use_sim_time": True, "families": families,
                                            "watch_calibration_windows": settings.calibration_windows},
                    [CONFIG_DIR / "identification.yaml"])
        with RosClient(domain, "bench_watch_nodes", use_sim_time=True) as client:
            session = Session(client.node)
            client.wait_for_services(["compensator/reload", "identification/refit"], 120.0, nodes.check_running)
            nodes.start("stage_node", {"rate_hz": time_scale / STEP_S, "time_scale": time_scale,
                                       "command_timeout": 5.0, "use_sim_time": True,
                                       "lockstep_timeout": LOCKSTEP_TIMEOUT_S, "load_change_n": load_n,
                                       "load_change_time_s": LOAD_STEP_S}, [CONFIG_DIR / "stage.yaml"])
            client.wait_for_services(["stage/stop"], 60.0, nodes.check_running)
            retried(client, "identification/excite", "no /clock", nodes.check_running)
            excited_s = session.now_s()
            wait_for(lambda: session.now_s() > excited_s + EXCITE_S + 10.0, 20.0 * EXCITE_S / time_scale + 60.0,
                     "the excitation", nodes.check_running)
            models_before = len(session.models)
            refit_frozen(client, session, nodes.check_running)
            wait_for(lambda: len(session.models) > models_before, 60.0, "the refitted model", nodes.check_running)
            client.set_bool("stage/freeze_time", False)
            pushed_s, model_yaml = session.models[-1]
            positions = np.array([row[1] for row in session.states])
            tracking_s = session.now_s() + STEP_S
            setpoint = make_setpoint(kind, positions.min(), positions.max(), tracking_s)
            session.profile = setpoint
            until_s = LOAD_STEP_S + AFTER_STEP_S if watched_s is None else \
                tracking_s + settings.calibration_s + watched_s
            for ahead in range(AHEAD_STEPS):
                session.publish_setpoint(tracking_s + ahead * STEP_S)
            wait_for(lambda: session.now_s() >= until_s, 20.0 * (until_s - tracking_s) / time_scale + 120.0,
                     f"{until_s:.0f} s of simulated time", nodes.check_running)
            session.profile = None
            with session._lock:
                states, watch, timeouts = np.array(session.states), list(session.watch), session.lockstep_timeouts
        nodes.stop_all()
    stage_log = (out_dir / "stage_node.log").read_text() if (out_dir / "stage_node.log").exists() else ""
    commanded = states[(states[:, 0] > tracking_s - STEP_S) & (states[:, 2] != 0.0), 0]
    tracking_s = float(commanded[0]) - STEP_S if len(commanded) else tracking_s  # the state the first command answered
    notes = [] if tracking_s + settings.calibration_s < LOAD_STEP_S else \
        [f"tracking from {tracking_s:.0f} s: the watch was still calibrating at the load step"]
    return NodesRun(states, watch, model_yaml, pushed_s, tracking_s, setpoint, until_s, time.monotonic() - started,
                    timeouts,
                    notes=notes + ([line for line in stage_log.splitlines() if "Traceback" in line][:1]))


def refit_frozen(client: RosClient, session: Session, check) -> None:
    """Call identification/refit with the stage's time frozen (the refit's wall time is not simulated time). An
    excitation that started late in simulated time (a second of wall time at the start is 50 s at 50x) is let run
    on unfrozen, 20 s of simulated time at a time, until it has ended."""
    for _ in range(20):
        frozen, message = client.set_bool("stage/freeze_time", True)
        if not frozen:
            raise RuntimeError(f"stage/freeze_time: {message}")
        ok, message = client.trigger("identification/refit", timeout_s=600.0)
        if ok:
            return
        if "excitation is running" not in message:
            raise RuntimeError(f"identification/refit: {message}")
        client.set_bool("stage/freeze_time", False)
        until_s = session.now_s() + 20.0
        wait_for(lambda until_s=until_s: session.now_s() > until_s, 60.0, "the excitation's end", check)
    raise RuntimeError("identification/refit: the excitation did not end")


def retried(client: RosClient, service: str, busy: str, check, timeout_s: float = 30.0) -> str:
    """Call a Trigger service until it succeeds or answers something other than busy (RuntimeError then)."""
    deadline = time.monotonic() + 60.0
    while True:
        ok, message = client.trigger(service, timeout_s=timeout_s)
        if ok:
            return message
        if busy not in message or time.monotonic() > deadline:
            raise RuntimeError(f"{service}: {message}")
        check()
        time.sleep(0.1)


def replay_and_track(run: NodesRun, load_n: float) -> tuple[np.ndarray, float]:
    """The record replayed through a fresh simulator up to the tracking's start, then the same loop in this process:
    (rows (t [s], position [m], current [A]) like the record's, the replay's largest position difference [m])."""
    from sma_stage.nodes.compensator_node import COMPENSATOR_PARAMS, CompensatorSettings, loop_settings

    effects = Effects(load_change_n=load_n, load_change_time_s=LOAD_STEP_S)
    stage = StageSimulator(StageConfig(), effects, 0)
    t, position, current = run.states.T
    replayed = t < run.tracking_s
    first_step = int(round(t[0] / STEP_S))
    for _ in range(first_step - 1):  # before the first state recorded: nobody commanded the stage
        stage.step(0.0, STEP_S)
    difference = max(abs(stage.step(value, STEP_S).measured_position_m - measured)
                     for value, measured in zip(current[replayed], position[replayed], strict=True))
    model = any_model_from_yaml_text(run.model_yaml)
    values = CompensatorSettings(**{param.name: param.default for param in COMPENSATOR_PARAMS})
    core = Compensator(model, values.max_current, values.inverse_method, **loop_settings(model, values, STEP_S))
    for value in current[(t > run.pushed_s) & replayed]:
        core.follow_applied(value, STEP_S)
    rows = [row for row in run.states if row[0] < run.tracking_s]
    measured, time_s = rows[-1][1], rows[-1][0]
    ahead_s = STEP_S * min(math.floor(core.preview_s() / STEP_S + 1e-9), AHEAD_STEPS)  # the node's preview
    for k in range(int(round((run.states[-1, 0] - time_s) / STEP_S))):
        command = core.command(run.setpoint(time_s), measured, STEP_S if k else 0.0,
                               ahead_m=run.setpoint(time_s + ahead_s))
        time_s += STEP_S
        measured = stage.step(command, STEP_S).measured_position_m
        rows.append((time_s, measured, command))
    return np.array(rows), difference


def watched(model_yaml: str, rows: np.ndarray, start_s: float) -> tuple[float, list[float]]:
    """The watch over rows from start_s on, started with the record before it as the node starts it:
    (bias_held_out_m [m], the times of its drift flags [s], the tests restarted after each)."""
    before = (rows[:, 0] <= start_s) & (rows[:, 0] > start_s - WATCH_RECORD_S)
    watch = ModelWatch(any_model_from_yaml_text(model_yaml), settings.test, (rows[before, 0], rows[before, 2]))
    after = rows[rows[:, 0] > start_s]
    flags = []
    for start in range(0, len(after) - CHUNK + 1, CHUNK):
        chunk = after[start:start + CHUNK]
        watch.step(chunk[:, 0], chunk[:, 2], chunk[:, 1])
        if watch.state == "drift":
            flags.append(float(chunk[-1, 0]))
            watch.restart_tests()
    return (watch.held_out_bias_m if watch.held_out_bias_m is not None else math.nan), flags


def node_watch(run: NodesRun) -> tuple[float, list[float]]:
    """The node's watch from /diagnostics after the refit: (bias_held_out_m [m] before the load step, the times
    [s] it turned to drift)."""
    seen = [(stamp, values) for stamp, values in run.watch if stamp > run.pushed_s + 1.0]
    scales = [float(values["bias_held_out_m"]) for stamp, values in seen
              if stamp < LOAD_STEP_S and values.get("bias_held_out_m", "calibrating") != "calibrating"]
    flags, last = [], "ok"
    for stamp, values in seen:
        if values["state"] == "drift" and last != "drift":
            flags.append(stamp)
        last = values["state"]
    return (scales[-1] if scales else math.nan), flags


def delay(flags: list[float], load_n: float) -> str:
    """The first flag after the load step [s after it], or 'none'."""
    if not load_n:
        return "-"
    after = [flag - LOAD_STEP_S for flag in flags if flag >= LOAD_STEP_S]
    return f"{after[0]:.0f}" if after else "none"


def before(flags: list[float], start_s: float, load_n: float) -> int:
    """Flags between start_s and the load step (or the end with no step)."""
    stop = LOAD_STEP_S if load_n else math.inf
    return sum(start_s <= flag < stop for flag in flags)


def ratio(nodes: float, process: float) -> float:
    """nodes / process, NaN when the process figure is 0 or NaN (a watch that never calibrated its bias test)."""
    return nodes / process if process > 0.0 else math.nan


def rms_um(a: np.ndarray, b: np.ndarray) -> float:
    return 1e6 * float(np.sqrt(np.mean(np.square(a - b))))


def loops_apart_um(nodes: np.ndarray, process: np.ndarray) -> float:
    """RMS difference [um] of the positions through the nodes and in process at the same times (before a load
    step): zero when each command acted as in process."""
    common, in_nodes, in_process = np.intersect1d(np.round(nodes[:, 0] / STEP_S), np.round(process[:, 0] / STEP_S),
                                                  return_indices=True)
    kept = common * STEP_S < LOAD_STEP_S
    return rms_um(nodes[in_nodes[kept], 1], process[in_process[kept], 1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--time-scales", default="20,50")
    parser.add_argument("--setpoints", default="sine,levels")
    parser.add_argument("--families", default="gpi;gpi,two_wire",
                        help="the refit's families (the node's `families`), one run set per ';'-separated value")
    parser.add_argument("--load-step-n", type=float, default=2.0)
    parser.add_argument("--runs", type=int, default=1, help="runs per time scale and setpoint")
    parser.add_argument("--save", type=Path, default=None, help="a folder for each run's records (.npz)")
    parser.add_argument("--hours", type=float, default=0.0,
                        help="a run at the largest time scale, the first families: the sine, no step, this long")
    parser.add_argument("--sine-period", type=float, default=SINE_PERIOD_S, help="the sine's period [s]")
    parser.add_argument("--calibration-windows", type=int, default=DriftTest().calibration_windows,
                        help="the watch's calibration windows (the node's watch_calibration_windows)")
    args = parser.parse_args()
    global settings
    settings = BenchSettings(args.sine_period, args.calibration_windows)
    family_sets = [value.split(",") for value in args.families.split(";")]
    scales = [float(scale) for scale in args.time_scales.split(",")]
    plan = [(families, scale, kind, args.load_step_n, None) for families in family_sets
            for scale in scales for kind in args.setpoints.split(",") for _ in range(args.runs)]
    if args.hours:
        plan.append((family_sets[0], max(scales), "sine", 0.0, 3600.0 * args.hours))
    header = ("| families: model in force | time scale | setpoint | load step | bias_held_out_m um: nodes / record / process (ratio nodes:process) "
              "| flagged s after the step: nodes / record / process | flags before it: nodes / process "
              "| tracking RMS um: nodes / process | nodes - process RMS um | replay max um | lockstep timeouts | wall s |")
    print(f"refit after {EXCITE_S:g} s; sine period {settings.sine_period_s:g} s; watch defaults but "
          f"{settings.calibration_windows} calibration windows; load step at {LOAD_STEP_S:g} s")
    print(header, "|" + "---|" * 11, sep="\n", flush=True)
    for index, (families, scale, kind, load_n, watched_s) in enumerate(plan):
        with tempfile.TemporaryDirectory() as folder:
            try:
                run = run_nodes(FIRST_DOMAIN + index % (LAST_DOMAIN - FIRST_DOMAIN + 1), scale, kind, families, load_n, watched_s, Path(folder))
            except (RuntimeError, InputError) as error:
                print(f"| {','.join(families)} | {scale:g} | {kind} | {load_n:g} N | failed: {error} |", flush=True)
                continue
        process, replay_m = replay_and_track(run, load_n)
        if args.save:
            args.save.mkdir(parents=True, exist_ok=True)
            np.savez(args.save / f"run{index}.npz", nodes=run.states, process=process, tracking_s=run.tracking_s,
                     pushed_s=run.pushed_s, model=run.model_yaml)
        scale_nodes, flags_nodes = node_watch(run)
        scale_record, flags_record = watched(run.model_yaml, run.states, run.pushed_s)
        scale_process, flags_process = watched(run.model_yaml, process, run.pushed_s)
        tracked = run.states[run.states[:, 0] >= run.tracking_s]
        tracked_process = process[process[:, 0] >= run.tracking_s]
        reference = np.array([run.setpoint(t) for t in tracked[:, 0]])
        reference_process = np.array([run.setpoint(t) for t in tracked_process[:, 0]])
        in_force = getattr(any_model_from_yaml_text(run.model_yaml), "FAMILY", "GPI")
        line = (f"| {','.join(families)}: {in_force} | {scale:g} | {kind} | {load_n:g} N, tracked {run.tracking_s:.0f}-{run.until_s:.0f} s | {1e6 * scale_nodes:.2f} / "
                f"{1e6 * scale_record:.2f} / {1e6 * scale_process:.2f} ({ratio(scale_nodes, scale_process):.2f}) | "
                f"{delay(flags_nodes, load_n)} / {delay(flags_record, load_n)} / {delay(flags_process, load_n)} | "
                f"{before(flags_nodes, run.pushed_s, load_n)} / {before(flags_process, run.pushed_s, load_n)} | "
                f"{rms_um(tracked[:, 1], reference):.1f} / {rms_um(tracked_process[:, 1], reference_process):.1f} | "
                f"{loops_apart_um(tracked, tracked_process):.3f} | "
                f"{1e6 * replay_m:.3f} | {run.lockstep_timeouts} | {run.wall_s:.0f} |" + (f" {'; '.join(run.notes)}" if run.notes else ""))
        print(line, flush=True)
    return 0


if __name__ == "__main__":
    with recorded(__file__):
        sys.exit(main())
