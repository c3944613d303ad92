"""The demonstration's third part (`./run.sh demo`): the three node executables on the simulated stage as
separate processes, driven over ROS as a user would: excite, refit, then track with the default and the
identified model, feedforward and with the PI loop. ROS is imported only inside the functions that use it."""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from sma_stage.errors import InputError
from sma_stage.identify.families import FAMILIES
from sma_stage.model.kinds import any_model_from_yaml_text
from sma_stage.nodes.launch import CONFIG_DIR, DEFAULT_MODEL_FILE
from sma_stage.plots import Panel, save_panels
from sma_stage.signals import paper_validation_signal

MAX_CURRENT_A = 5.0


@dataclass(frozen=True)
class EndToEndSettings:
    """How the end-to-end run is paced and how long each part lasts (signal times in simulated s)."""

    time_scale: float = 60.0           # simulated s per wall s: the stage's time_scale and the signals' pace
    step_s: float = 0.1                # simulated s per stage step, control period and setpoint: a 10 Hz loop
    excite_duration_s: float = 1000.0  # the paper's identification signal
    excite_period_s: float = 250.0
    operators: int = 10
    families: tuple[str, ...] = FAMILIES  # model families the refit compares (the node's `families`)
    run_s: float = 1000.0              # the paper's validation signal
    settle_s: float = 60.0             # before each run: at the bottom of the range, then at the first setpoint
    stroke_fraction: float = 0.8       # the setpoint spans this fraction of the measured stroke
    ready_timeout_s: float = 120.0     # [wall s] for the nodes to start
    refit_timeout_s: float = 120.0     # [wall s]

    @property
    def rate_hz(self) -> float:
        """Stage steps per wall second: time_scale / step_s."""
        return self.time_scale / self.step_s

    @property
    def control_rate_hz(self) -> float:
        """Control periods, setpoints and excitation values per simulated second: 1 / step_s."""
        return 1.0 / self.step_s

    def wall_s(self, simulated_s: float) -> float:
        """Nominal wall seconds for simulated_s."""
        return simulated_s / self.time_scale

    def wall_timeout_s(self, simulated_s: float) -> float:
        """Wall seconds allowed for simulated_s: three times the nominal, plus 10 s."""
        return 3.0 * self.wall_s(simulated_s) + 10.0


@dataclass(frozen=True)
class TrackingRun:
    """One tracking run: time [s simulated, 0 where the signal starts, negative while settling], setpoint and
    measured position [m], the last current command [A] at each sample; errors [% of stroke] for t >= 0;
    the change of current_cmd from one message to the next over t >= 0 (RMS, 99th percentile) [% of
    MAX_CURRENT_A]; the pace the run achieved [simulated s per wall s]; the longest time between two setpoints
    the demo published [s simulated] (step_s when it kept up: over it the stage held the last one)."""

    name: str
    t: np.ndarray
    setpoint: np.ndarray
    position: np.ndarray
    current: np.ndarray
    rms_pct: float
    max_pct: float
    current_step_rms_pct: float = float("nan")
    current_step_p99_pct: float = float("nan")
    pace: float = float("nan")  # simulated s per wall s achieved over the run
    setpoint_gap_s: float = float("nan")  # the longest time between two setpoints published [s simulated]


class StageSession:
    """The demo's own node: records joint_states and publishes a setpoint profile every step_s of simulated time.

    Times are the ROS clock's: simulated time, the stage's /clock, which also stamps joint_states (every
    node of the demo runs with use_sim_time); a profile is a function of it. time_scale only turns
    simulated seconds into wall-clock timeouts.
    """

    def __init__(self, node: object, settings: EndToEndSettings) -> None:
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64

        from sma_stage.nodes._common import COMMAND_QOS

        self._lock = threading.Lock()
        self._float = Float64
        self._clock = node.get_clock()
        self.time_scale = settings.time_scale
        self.stamps: list[float] = []
        self.positions: list[float] = []
        self.commands: list[tuple[float, float]] = []
        self.profile: Callable[[float], float] | None = None
        self.profile_start_s = 0.0
        self.last_published_s: float | None = None  # when the profile's last setpoint was published [s simulated]
        self.longest_gap_s = float("nan")  # the longest time between two of its setpoints published [s simulated]
        self.setpoint_pub = node.create_publisher(Float64, "setpoint", COMMAND_QOS)
        node.create_subscription(JointState, "joint_states", self.on_state,
                                 QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
        node.create_subscription(Float64, "current_cmd", self.on_command, COMMAND_QOS)
        node.create_timer(settings.step_s, self.on_tick)

    def now_s(self) -> float:
        """The ROS clock [s]."""
        return self._clock.now().nanoseconds * 1e-9

    def on_tick(self) -> None:
        """Publish the profile's setpoint [m] for the simulated time since its start."""
        with self._lock:
            profile, start = self.profile, self.profile_start_s
        if profile is not None:
            now_s = self.now_s()
            self.setpoint_pub.publish(self._float(data=float(profile(now_s - start))))
            with self._lock:
                if self.last_published_s is not None:
                    self.longest_gap_s = float(np.fmax(self.longest_gap_s, now_s - self.last_published_s))
                self.last_published_s = now_s

    def on_state(self, message: object) -> None:
        """Record the stage position [m] at its header stamp [s]."""
        if message.position:
            with self._lock:
                self.stamps.append(message.header.stamp.sec + 1e-9 * message.header.stamp.nanosec)
                self.positions.append(float(message.position[0]))

    def on_command(self, message: object) -> None:
        """Record a current command [A] at its arrival time [s]."""
        with self._lock:
            self.commands.append((self.now_s(), float(message.data)))

    def states_between(self, start_s: float, stop_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(stamps [s], positions [m]) recorded with start_s <= stamp <= stop_s."""
        with self._lock:
            stamps, positions = np.array(self.stamps), np.array(self.positions)
        kept = (stamps >= start_s) & (stamps <= stop_s)
        return stamps[kept], positions[kept]

    def commands_between(self, start_s: float, stop_s: float) -> np.ndarray:
        """The current commands [A] received with start_s <= arrival <= stop_s, in order."""
        with self._lock:
            commands = np.array(self.commands).reshape(-1, 2)
        kept = (commands[:, 0] >= start_s) & (commands[:, 0] <= stop_s)
        return commands[kept, 1]

    def commands_at(self, times_s: np.ndarray) -> np.ndarray:
        """The last current command [A] received at or before each time [s] (NaN before the first)."""
        with self._lock:
            commands = np.array(self.commands).reshape(-1, 2)
        index = np.searchsorted(commands[:, 0], times_s, side="right") - 1
        return np.where(index >= 0, commands[np.maximum(index, 0), 1] if len(commands) else np.nan, np.nan)

    def drive(self, profile: Callable[[float], float], simulated_s: float, check: Callable[[], None]) -> float:
        """Publish profile(simulated time) for simulated_s; the start [s of the ROS clock]. Returns once the
        stage's joint_states reached the end."""
        from sma_stage.nodes.launch import wait_for

        with self._lock:
            self.profile_start_s = start = self.now_s()
            self.profile = profile
            self.last_published_s, self.longest_gap_s = None, float("nan")
        stop = start + simulated_s
        try:
            wait_for(lambda: self.now_s() >= stop, 3.0 * simulated_s / self.time_scale + 10.0, "the end of a run",
                     check)
        finally:
            with self._lock:
                self.profile = None
        wait_for(lambda: self.stamps[-1] >= stop, 10.0, "joint_states up to the end of the run", check)
        return start

    def prime(self, setpoint_m: float, timeout_s: float, check: Callable[[], None]) -> None:
        """Publish one setpoint [m] and wait for a current command in answer (the compensator's first one
        loads its compiled inverse)."""
        from sma_stage.nodes.launch import wait_for

        with self._lock:
            seen = len(self.commands)
        self.setpoint_pub.publish(self._float(data=float(setpoint_m)))
        wait_for(lambda: len(self.commands) > seen, timeout_s, "a current command from the compensator", check)


def validation_profile(bottom_m: float, middle_m: float, half_span_m: float,
                       settle_s: float) -> Callable[[float], float]:
    """Setpoint [m] at time t [s]: settle_s at bottom_m, settle_s at the signal's start, then the signal."""
    def setpoint(t: float) -> float:
        if t < settle_s:
            return bottom_m
        shape = paper_validation_signal(max(t - 2.0 * settle_s, 0.0)) / 5.0
        return float(middle_m + half_span_m * shape)
    return setpoint


def tracking_run(session: StageSession, name: str, stroke: tuple[float, float], settings: EndToEndSettings,
                 check: Callable[[], None]) -> TrackingRun:
    """Drive the scaled validation signal through the compensator; errors over the signal part only."""
    low, high = stroke
    middle, half_span = 0.5 * (low + high), 0.5 * settings.stroke_fraction * (high - low)
    profile = validation_profile(middle - half_span, middle, half_span, settings.settle_s)
    lead_s = 2.0 * settings.settle_s
    session.prime(profile(0.0), settings.ready_timeout_s, check)
    began = time.monotonic()
    start = session.drive(profile, lead_s + settings.run_s, check)
    pace = (lead_s + settings.run_s) / (time.monotonic() - began)
    stamps, position = session.states_between(start, start + lead_s + settings.run_s)
    t = stamps - start
    setpoint = np.array([profile(value) for value in t])
    error = (position - setpoint)[t >= lead_s]
    scale = 100.0 / (high - low)
    steps = current_steps_pct(session.commands_between(start + lead_s, start + lead_s + settings.run_s))
    return TrackingRun(name, t - lead_s, setpoint, position, session.commands_at(stamps),
                       float(scale * np.sqrt(np.mean(error**2))), float(scale * np.max(np.abs(error))),
                       *steps, pace, session.longest_gap_s)


def current_steps_pct(commands: np.ndarray) -> tuple[float, float]:
    """(RMS, 99th percentile) of the change of the current from one command to the next [% of
    MAX_CURRENT_A] (NaN with fewer than two commands)."""
    if commands.size < 2:
        return float("nan"), float("nan")
    change = 100.0 * np.abs(np.diff(commands)) / MAX_CURRENT_A
    return float(np.sqrt(np.mean(change**2))), float(np.percentile(change, 99))


def node_parameters(settings: EndToEndSettings, work_dir: Path) -> dict[str, dict[str, object]]:
    """Overrides of config/<node>.yaml: the stage sped up by time_scale, every node on its simulated /clock
    (so the identification, the lead and the PI loop count simulated seconds); one stage step per control
    period, excitation value and setpoint (step_s simulated); feedforward with the compensator's default lead
    limits; the refit's diagnosis in two processes (nothing drives the stage
    meanwhile, so the stage's pace does not matter then)."""
    return {
        "stage_node": {"rate_hz": settings.rate_hz, "time_scale": settings.time_scale, "command_timeout": 2.0,
                       "use_sim_time": True},
        "compensator_node": {"rate_hz": settings.control_rate_hz, "feedback": False, "use_sim_time": True},
        "identification_node": {"operators": settings.operators, "use_sim_time": True,
                                "model_file": str(work_dir / "identified_model.yaml"),
                                "excite_duration": settings.excite_duration_s,
                                "excite_period": settings.excite_period_s,
                                "excite_rate_hz": settings.control_rate_hz,
                                "record_bag": str(work_dir / "session_bag"), "bag_overwrite": True,
                                "diagnose_workers": 2, "families": list(settings.families)},
    }


def excite_and_refit(client: object, session: StageSession, settings: EndToEndSettings,
                     check: Callable[[], None]) -> tuple[dict, tuple[float, float]]:
    """~/excite, wait for its end, ~/refit: the JSON report and the stroke measured meanwhile [m]."""
    from sma_stage.nodes.launch import wait_for


    deadline = time.monotonic() + settings.ready_timeout_s
    while True:
        start = session.now_s()
        ok, message = client.trigger("identification/excite")
        if ok or "no /clock" not in message or time.monotonic() > deadline:
            break
        check()
        time.sleep(0.1)
    if not ok:
        raise InputError(f"~/excite refused: {message}")
    stop = start + settings.excite_duration_s
    wait_for(lambda: session.now_s() >= stop, settings.wall_timeout_s(settings.excite_duration_s),
             "the end of the excitation", check)
    _, positions = session.states_between(start, stop)
    ok, message = refit_with_time_frozen(client, settings)
    if not ok:
        raise InputError(f"~/refit: {message}")
    from std_msgs.msg import String

    from sma_stage.nodes._common import REPORT_QOS

    report = client.latest(String, "identification/report", REPORT_QOS)
    return json.loads(report.data), (float(positions.min()), float(positions.max()))


def refit_with_time_frozen(client: object, settings: EndToEndSettings) -> tuple[bool, str]:
    """~/refit while the simulated stage is frozen (stage ~/freeze_time): at the demo's pace the three nodes
    and this client exchange 600 messages per wall second, which on two cores left the refit's diagnosis
    processes a third of a core each (its candidates ran 4-7 times slower than alone). While the
    identification node's excitation has not ended on its clock (a few steps behind the stage's), the
    stage runs on between tries."""
    deadline = time.monotonic() + 30.0
    while True:
        frozen, message = client.set_bool("stage/freeze_time", True)
        if not frozen:
            raise InputError(f"stage ~/freeze_time: {message}")
        try:
            ok, message = client.trigger("identification/refit", timeout_s=settings.refit_timeout_s)
        finally:
            client.set_bool("stage/freeze_time", False)
        if ok or "excitation is running" not in message or time.monotonic() > deadline:
            return ok, message
        time.sleep(0.1)


def describe_diagnosis(report: dict) -> str:
    """One line: what the refit's diagnosis named and what went to the compensator."""
    diagnosis = report.get("diagnosis")
    if diagnosis is None:
        return "no diagnosis (diagnose_rounds 0): the plain GPI went to the compensator"
    before, after = diagnosis["before"]["validation"]["rms_pct"], diagnosis["after"]["validation"]["rms_pct"]
    named = ", ".join(diagnosis["effects"]) or "none"
    line = f"diagnosis of the residual: {named}; held-out tail rms {before:.2f} % -> {after:.2f} %; "
    families = report.get("families") or []
    chosen = next((row for row in families if row["chosen"]), None)
    if chosen is not None and chosen["family"] != "gpi":
        scores = ", ".join(f"{row['family']} {row['validation']['rms_pct']:.2f} %" for row in families
                           if row["validation"])
        return line + f"families on the held-out tail: {scores}; the {chosen['model']} went to the compensator"
    effects = report["model"]["effects"]
    sent = ("the GPI with " + ", ".join(f"{effect['kind']} ({', '.join(f'{k} {v:.4g}' for k, v in effect['parameters'].items())})"
                                        for effect in effects) if effects else "the plain GPI")
    return line + f"{sent} went to the compensator"


RUN_ORDER = ("default, feedforward", "identified, feedforward", "identified, PI loop")


def track_with_both_models(client: object, session: StageSession, stroke: tuple[float, float],
                           settings: EndToEndSettings, check: Callable[[], None],
                           identified: bool) -> dict[str, TrackingRun]:
    """Tracking runs with the model ~/refit pushed (when it did), feedforward and with the PI loop at the gains
    the compensator derives from the model (its default tuning); then feedforward with the shipped default
    model reloaded from its file, the model a user has before any refit."""
    runs = {}
    if identified:
        runs["identified, feedforward"] = tracking_run(session, "identified model, feedforward", stroke, settings,
                                                       check)
        client.set_parameters("compensator", {"feedback": True})
        runs["identified, PI loop"] = tracking_run(session, "identified model, PI loop", stroke, settings, check)
    client.set_parameters("compensator", {"model": "", "model_file": str(DEFAULT_MODEL_FILE), "feedback": False})
    ok, message = client.trigger("compensator/reload")
    if not ok:
        raise InputError(f"compensator ~/reload: {message}")
    runs["default, feedforward"] = tracking_run(session, "default model, feedforward", stroke, settings, check)
    return runs


@contextmanager
def sigterm_as_exit() -> Iterator[None]:
    """Inside the block SIGTERM raises SystemExit in the main thread, so every `with` cleans up."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def leave(signum: int, frame: object) -> None:
        raise SystemExit(128 + signum)

    previous = signal.signal(signal.SIGTERM, leave)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def default_domain_id() -> int:
    """ROS_DOMAIN_ID from the environment, else one derived from the process id (1..101)."""
    value = os.environ.get("ROS_DOMAIN_ID", "").strip()
    return int(value) if value.isdigit() else 1 + os.getpid() % 101


NODE_CONFIGS = {"stage_node": "stage", "compensator_node": "compensator", "identification_node": "identification"}


def start_nodes(nodes: object, settings: EndToEndSettings) -> None:
    """Start the three executables with config/<node>.yaml and the run's overrides (returns at once)."""
    os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    parameters = node_parameters(settings, nodes.log_dir)
    for executable, config in NODE_CONFIGS.items():
        nodes.start(executable, parameters[executable], [CONFIG_DIR / f"{config}.yaml"])


def run_end_to_end(nodes: object, settings: EndToEndSettings, out_dir: Path, launched_at: float) -> dict:
    """With the nodes started: excite, refit, track with the identified and the default model, stop them."""
    from sma_stage.nodes.launch import RosClient, wait_for

    with RosClient(nodes.domain_id, "sma_demo", use_sim_time=True) as client:
        session = StageSession(client.node, settings)
        client.wait_for_services(["stage/stop", "compensator/reload", "identification/refit"],
                                 settings.ready_timeout_s, nodes.check_running)
        wait_for(lambda: session.stamps, settings.ready_timeout_s, "joint_states", nodes.check_running)
        ready = time.monotonic()
        report, stroke = excite_and_refit(client, session, settings, nodes.check_running)
        refitted = time.monotonic()
        held = client.get_parameters("compensator", ["model"])["model"]
        pushed = bool(held) and any_model_from_yaml_text(held).without_state().to_dict() == report["model"]
        runs = track_with_both_models(client, session, stroke, settings, nodes.check_running,
                                      identified=bool(report["compensator"]["pushed"]))
    exits = nodes.stop_all()
    loop = identification_loop(nodes.log_dir / "session_bag", Path(report["model_file"]), settings.excite_duration_s)
    save_tracking_plots(out_dir / "tracking.png", [runs[key] for key in RUN_ORDER if key in runs], loop)
    return {"report": report, "stroke_m": stroke, "compensator_holds_fit": pushed, "runs": runs,
            "exit_codes": exits, "domain_id": nodes.domain_id, "work_dir": nodes.log_dir,
            "seconds": {"start": ready - launched_at, "excite_and_refit": refitted - ready,
                        "total": time.monotonic() - launched_at}}


def identification_loop(bag: Path, model_file: Path, duration_s: float, input_topic: str = "current_applied"
                        ) -> list[Panel]:
    """The excitation as the session's bag recorded it (from the first nonzero current on input_topic, duration_s
    [s]) with the identified model's prediction from rest: the loop, the output over time and the residual, as
    `gpi_tool plot` draws them."""
    # Imported here, as the ROS parts are: imported with the module, the identified feedforward tracked 1.73-1.94 %
    # in place of 1.60-1.62 % (three demos each, 2026-11-26; the cause was not traced).
    from sma_stage.commands.plot import recording_panels
    from sma_stage.io import read_bag
    from sma_stage.model.kinds import load_any_model_file

    series = read_bag(bag, default_input_topic=input_topic)
    start = float(series.t[np.argmax(series.input != 0.0)])
    excitation = series.window(start, start + duration_s)
    predicted = load_any_model_file(model_file).predict(excitation.t, excitation.input)
    panels = recording_panels(excitation, "m", predicted)
    loop, (_, output), (residual, _) = panels["loop.png"][0], panels["time_series.png"], panels["residual.png"]
    titles = ("identification: the loop, measured and identified model", "identification: output over time",
              "identification: residual")
    return [replace(panel, title=title) for panel, title in zip((loop, output, residual), titles, strict=True)]


def save_tracking_plots(path: Path, runs: Sequence[TrackingRun], identification: Sequence[Panel] = ()) -> None:
    """The identification's panels (identification_loop) in the first row, then per run: setpoint and position
    against time, the current command, and position against setpoint over the signal (t >= 0; before it the
    stage settles)."""
    panels = list(identification)
    for run in runs:
        setpoint_um, position_um = 1e6 * run.setpoint, 1e6 * run.position
        signal = run.t >= 0.0
        panels.append(Panel(f"{run.name}: RMS {run.rms_pct:.2f} %, max {run.max_pct:.2f} % of stroke", run.t,
                            [("setpoint", setpoint_um), ("stage position", position_um)],
                            "time [s, simulated; settling before 0]", "position [um]"))
        panels.append(Panel(f"{run.name}: current command", run.t, [("current_cmd", run.current)],
                            "time [s, simulated]", "current [A]"))
        panels.append(Panel(f"{run.name}: setpoint to position (t >= 0)", setpoint_um[signal],
                            [("stage", position_um[signal]), ("ideal", setpoint_um[signal])],
                            "setpoint [um]", "position [um]"))
    save_panels(path, panels, columns=3)
