"""The `identification` node: records `current_applied` [A] (the current the stage applied, whoever
commanded it; `input_topic`) and `joint_states` [m] into a bounded buffer (and
into a rosbag2 directory when `record_bag` is set), drives the paper's identification signal on request,
and refits the model on request.

Services (std_srvs/Trigger):
- `~/excite`: publish A(t) sin(2 pi t / excite_period) on current_cmd, A falling linearly from
  excite_amplitude_start to excite_amplitude_end over excite_duration [s of signal time]; returns at once.
  Signal time = node-clock time since the start times excite_time_scale (set it to the stage's time_scale
  when the stage runs faster than real time without use_sim_time; with use_sim_time keep 1). The recording's
  time axis is scaled the same way: the model refitted counts stage seconds, as the compensator does.
- `~/refit`: refused at once (success=false, one-line reason) while an excitation runs, while another refit
  runs, or when the recording cannot support a fit. Otherwise runs the identification pipeline
  (sma_stage.identify.pipeline.identify_recording): fits the first (1 - holdout_fraction) of the
  recording, validates on the held-out tail (the model runs over the whole recording, the errors are taken
  on the tail only), diagnoses the residual (diagnose_rounds > 0) and deploys the GPI with every effect the
  diagnosis added; with more than one of `families`, each family is fitted and the one with the lowest
  held-out error (then BIC) is deployed (a two-wire model or the GPI). Writes `model_file` atomically, pushes the whole model as one parameter (`model`, its
  YAML text) to `<compensator_name>/set_parameters_atomically`, and answers with the JSON report (also on
  `~/report`).
- `~/clear`: empties the buffer.

- `~/abort_excitation`: stops a running excitation at once (current_cmd 0 A, the compensator enabled again);
  refused in one line when none runs. /diagnostics carries the excitation's progress.
- `~/rollback`: pushes the model that was in force before the one in force now, started from where the
  recent record leaves it.

The model watch (`watch`, sma_stage.nodes.model_watch): the model the compensator publishes on
`<compensator_name>/model` is run on the applied current and compared with joint_states; `~/residual`
(sensor_msgs/JointState, the joint's position = measured - predicted [m], stamped as the position) and a
`/diagnostics` status `<node>: model watch` (state ok, drift, no_model or no_data; WARN on drift) say how well
it predicts the stage (sma_stage.identify.watch: the drift tests). On drift (`on_drift`): `report` logs it;
`refit` fits the recent record (the last `watch_record` s) in the background and pushes the new model only when
it predicts the record's held-out tail better than the model in force (sma_stage.identify.history.judge_swap);
`excite` runs a short excitation (`drift_excite_duration`) and then does the same on it. Every model that goes in
force (pushed by this node or set on the compensator) is one log line and one entry of the history (the last
`model_history`), which `~/report` carries under "history".

The recording is aligned as the offline reader aligns a bag (sma_stage.io.rosbag_io): input held at each
output time; output times are the JointState header stamps unless they run on another clock.
"""

from __future__ import annotations

import errno
import json
import queue
import shutil
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import SetParametersResult
from rcl_interfaces.srv import SetParametersAtomically
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64, String
from std_srvs.srv import Trigger

from sma_stage.errors import InputError
from sma_stage.identify.cancel import Cancelled
from sma_stage.identify.families import FAMILIES, check_families
from sma_stage.identify.history import ModelHistory, judge_swap, started_from
from sma_stage.identify.pipeline import (
    FIT_SAMPLES,
    Identification,
    deployed_held_out,
    dynamics_held_refusal,
    identify_recording,
    refit_hysteresis,
)
from sma_stage.identify.watch import DriftTest, ModelWatch
from sma_stage.identify.workers import MAX_NICENESS, WORKER_NICENESS, lower_priority, warm_up
from sma_stage.io import BagRecorder, align_zero_order_hold, make_series
from sma_stage.io.atomic import atomic_write_text
from sma_stage.io.plain import strict_json
from sma_stage.io.rosbag_io import joint_index, output_times, unfinished_bags
from sma_stage.io.series import Series
from sma_stage.model.kinds import AnyModel, any_model_from_yaml_text
from sma_stage.model.parameters import MAX_OPERATORS
from sma_stage.nodes._common import (
    COMMAND_QOS,
    JOINT_NAME,
    RECORD_COMMAND_QOS,
    RECORD_STATE_QOS,
    REPORT_QOS,
    Param,
    WorkerService,
    declare_all,
    exit_with,
    note_started,
    quiet_on_shutdown,
    run_node,
)
from sma_stage.nodes.model_watch import WATCH_PERIOD_S, WatchChannel
from sma_stage.signals import designed_identification_signal, paper_identification_signal

EXCITATIONS = ("paper", "designed")
ON_DRIFT = ("report", "refit", "excite")
DRIFT_REFIT_SCOPES = ("hysteresis", "full")
STORAGES = ("sqlite3", "mcap")
DIAGNOSTICS_PERIOD_S = 1.0

IDENTIFICATION_PARAMS = [
    Param("max_samples", 400000, "ring buffer length per topic [messages; an hour at 100 Hz is 360,000]; the oldest "
          "are dropped", 100, 10**8,
          read_only=True),
    Param("min_samples", 100, "fewest aligned samples a refit accepts", 20, 10**8),
    Param("holdout_fraction", 0.25, "tail of the recording held out for validation", 0.05, 0.5),
    Param("max_fit_samples", FIT_SAMPLES, "a longer recording is fitted on a copy thinned by whole blocks to at most "
          "this many samples, scored on every sample (0: never thin)", 0, 10**8),
    Param("operators", 10, "play operators of the fitted model (0: chosen by the fit)", 0, MAX_OPERATORS),
    Param("diagnose_rounds", 1, "rounds of residual diagnosis after the fit (0: none); the effects it adds are "
          "in the model written and pushed", 0, 4),
    Param("diagnose_workers", 1, "processes fitting a diagnosis round's candidates at once (1: in this node's "
          "process; more finish sooner and take CPU from a stage on the same computer)", 1, 64),
    Param("refit_niceness", WORKER_NICENESS, "nice levels a refit's thread and its worker processes run below the "
          "node's other threads (Linux), so that a stage on the same computer keeps its cycles; 0: at the node's "
          "priority (a computer that only identifies)", 0, MAX_NICENESS),
    Param("families", list(FAMILIES), "model families ~/refit fits on the same recording (default all: gpi, gpi_free, "
          "two_wire, bouc_wen); the one with the lowest held-out error (then BIC) is written and pushed, and the "
          "compensator runs it"),
    Param("model_file", "", "where ~/refit writes the fitted model (atomically); empty: not written"),
    Param("compensator_name", "compensator", "node that receives the fitted parameters (relative or absolute)",
          read_only=True),
    Param("max_held_out_rms_pct", 10.0, "a refit whose model misses the held-out tail by more than this RMS [% of the "
          "recording's span] is refused: nothing written or pushed (a recording cut short, a stage that stopped)",
          0.1, 1000.0),
    Param("push_timeout", 2.0, "wait for the compensator's parameter service [s]", 0.0, 60.0),
    Param("pause_compensator", True, "set the compensator's enabled false while ~/excite drives the stage, so "
          "one node at a time owns current_cmd"),
    Param("record_bag", "", "rosbag2 directory to record input_topic and joint_states into; empty: none"),
    Param("bag_storage", "mcap", f"rosbag2 storage: {' or '.join(STORAGES)} (mcap: Foxglove and PlotJuggler open it)"),
    Param("bag_overwrite", False, "replace an existing record_bag directory (when the bag is finished)"),
    Param("excite_signal", "paper", "identification signal: paper (the decaying sine) or designed (each wire's "
          "excursions to many peaks and reversal levels with holds, up to excite_amplitude_start; see gpi_tool "
          "excitation)"),
    Param("excite_amplitude_start", 5.0, "identification signal amplitude at its start [A] (designed: its "
          "largest current)", 0.0, 20.0),
    Param("excite_amplitude_end", 3.6, "identification signal amplitude at its end [A]", 0.0, 20.0),
    Param("excite_period", 250.0, "identification signal period [s of signal time]", 0.001, 1e6),
    Param("excite_duration", 1000.0, "identification signal length [s of signal time]", 0.001, 1e7),
    Param("excite_rate_hz", 50.0, "identification signal publication rate [Hz]", 1.0, 2000.0),
    Param("excite_time_scale", 1.0, "stage seconds per node-clock second (the stage's time_scale without "
          "use_sim_time; 1 with it): the excitation's signal time and the recording's time axis, so that the "
          "model refitted counts stage seconds", 0.001, 10000.0),
    Param("clear_on_excite", True, "empty the buffer when ~/excite starts, so a refit sees only the excitation"),
    Param("freeze_after_excite", True, "stop filling the buffer when an excitation ends (until ~/clear or "
          "~/excite), so a refit sees only the excitation; the bag records on"),
    Param("joint_name", JOINT_NAME, "joint of joint_states that carries the stage position", read_only=True),
    Param("watch", True, "watch the compensator's model against the stage: ~/residual and a /diagnostics status",
          read_only=True),
    Param("watch_window", 10.0, "the watch's window [s of stage time]: the drift tests look at the residual per "
          "window", 1.0, 3600.0, read_only=True),
    Param("watch_warmup_windows", 30, "windows after a model goes in force that are not counted (it and the stage settle "
          "from what came before: an excitation leaves the wires warm for minutes)", 0, 1000, read_only=True),
    Param("watch_calibration_windows", 120, "windows after the warm-up that measure the model's residual: its level and "
          "where along the stage's path it is what (the path test's memory)", 1, 100000, read_only=True),
    Param("watch_shift_allowance", 0.1, "path test: where the stage retraces its path, a residual moved by up to this "
          "fraction of the reference counts as no change", 0.0, 10.0, read_only=True),
    Param("watch_shift_threshold", 0.3, "path test: drift when the CUSUM of the moved fraction less the allowance "
          "exceeds this", 0.01, 100.0, read_only=True),
    Param("watch_bias_allowance", 1.5, "path test: where the stage retraces its path, a window's mean residual moved "
          "by up to this many standard errors (from how it wandered there while calibrating) counts as no change",
          0.0, 100.0, read_only=True),
    Param("watch_bias_threshold", 3.0, "path test: drift when the CUSUM of the mean's standard errors less the "
          "allowance exceeds this", 0.01, 1000.0, read_only=True),
    Param("watch_path_radius", 0.2, "path test: how near a remembered path [its standard deviations] counts as the "
          "same path", 0.001, 10.0, read_only=True),
    Param("watch_allowance", 1.5, "level test: windows up to this times the largest calibration window count as no "
          "change", 1.0, 100.0, read_only=True),
    Param("watch_threshold", 1.5, "level test: drift when the CUSUM of ln(window RMS / (allowance x largest)) "
          "exceeds this", 0.1, 100.0, read_only=True),
    Param("watch_record", 900.0, "recent samples the watch keeps [s of stage time]: what a refit on drift fits and "
          "where a model swapped in starts", 60.0, 86400.0, read_only=True),
    Param("on_drift", "report", "what the watch's drift does: report (log it), refit (fit the recent record and swap "
          "only if the new model predicts its held-out tail better), excite (stop tracking, excite "
          "drift_excite_duration, then the same on that)"),
    Param("drift_refit_record", 600.0, "on_drift refit: the refit waits for this much of the record from where the "
          "change began, and fits that [s of stage time; at most watch_record]", 60.0, 86400.0),
    Param("drift_refit_scope", "hysteresis", "on_drift refit, on the tracking record: hysteresis (refit the GPI "
          "parameters with the model in force's thermal dynamics held; a full identification for a model that is "
          "not a GPI with input effects only) or full (identify everything again, as ~/refit)"),
    Param("drift_excite_duration", 300.0, "on_drift excite: the excitation's length [s of signal time]", 1.0, 1e6),
    Param("model_history", 5, "models in force kept, newest last (~/rollback restores the one before)", 2, 1000,
          read_only=True),
    Param("input_topic", "current_applied", "std_msgs/Float64 topic of the current recorded and fitted [A]: what "
          "the stage applied (current_cmd for a stage that does not publish it, or a bag of commands)",
          read_only=True),
]


def recording_series(inputs: list[tuple[int, float]], outputs: list[tuple[int, int, float]],
                     min_samples: int, input_topic: str = "current_applied", time_scale: float = 1.0) -> Series:
    """The checked Series (t [s of stage time: node-clock seconds times time_scale], input [A], output [m]) of a
    recording; InputError saying what is missing."""
    if not inputs:
        raise InputError(f"no messages on {input_topic} were recorded: is anything publishing it?")
    if not outputs:
        raise InputError("no messages on joint_states were recorded: is the stage running?")
    input_ns, input_values = (np.array(column) for column in zip(*inputs, strict=True))
    receive_ns, stamp_ns, positions = (np.array(column) for column in zip(*outputs, strict=True))
    t, u, y = align_zero_order_hold(input_ns.astype(np.int64), input_values.astype(float),
                                    output_times(receive_ns.astype(np.int64), stamp_ns.astype(np.int64)),
                                    positions.astype(float))
    if t.size == 0:
        raise InputError(f"no joint_states message came at or after the first {input_topic} message")
    return make_series(t * time_scale, u, y, "recording", min_samples=min_samples)


def report_json(report: dict) -> str:
    """The refit's report as strict JSON (non-finite numbers as null)."""
    return strict_json(report)


def report_path(model_file: str | None) -> str | None:
    """Where the refit's report goes: beside the model file, `<model file without .yaml>.report.json`."""
    if model_file is None:
        return None
    path = Path(model_file)
    return str(path.with_name(path.name.removesuffix(".yaml").removesuffix(".yml") + ".report.json"))


def refit_summary(report: dict) -> str:
    """~/refit's one-line answer: the effects named, the held-out error before and after, where the model and
    the report went, whether the compensator took the model, and the warnings."""
    diagnosis = report.get("diagnosis")
    validation = report["validation"]
    if diagnosis is not None:
        named = ", ".join(diagnosis["effects"]) or "no effect"
        before = diagnosis["before"]["validation"]["rms_pct"]
        after = diagnosis["after"]["validation"]["rms_pct"]
        error = f"{named} added; held-out RMS {before:.3g} % -> {after:.3g} %"
    else:
        error = f"no diagnosis; held-out RMS {validation['rms_pct']:.3g} %"
    parts = [f"refit ok: {report['model']['operators']} operators, {error}"]
    families = report.get("families")
    if families:
        scores = ", ".join(f"{row['family']} {row['validation']['rms_pct']:.3g} %" if row["validation"] else
                           f"{row['family']} not fitted" for row in families)
        chosen = [row["family"] for row in families if row["chosen"]]
        parts.append(f"family {chosen[0] if chosen else 'gpi'} deployed (held-out RMS: {scores})")
    parts += [f"model {report['model_file'] or 'not written (model_file empty)'}",
             f"report {report['report_file'] or 'on ~/report only'}",
             "pushed to the compensator" if report["compensator"]["pushed"] else "NOT pushed to the compensator"]
    parts += [f"warning: {warning}" for warning in report["warnings"]]
    return "; ".join(parts)


BAG_QUEUE_LIMIT = 100_000  # messages waiting for the bag writer (25 s of both topics at 2 kHz); more are dropped
BAG_CHECKPOINT_S = 1.0  # the bag is made durable and the free space looked at this often [s]
MIN_FREE_BYTES = 64 << 20  # below this much free space the recording ends, the bag finished while it can be


class BagThread:
    """A BagRecorder driven from one thread of its own (the sqlite3 storage must stay in the thread that
    opened it, while the executor calls back from several), behind a bounded queue. A failure of the recorder
    (a full disk, a write error) ends the recording: the bag is finished as far as it can be, `failure` says
    what happened and where the data are, on_failure is told once, and further messages are dropped."""

    def __init__(self, path: Path, storage: str, overwrite: bool = False, input_topic: str = "current_applied",
                 on_failure: Callable[[str], None] | None = None) -> None:
        self.path = path
        if (path.exists() or path.is_symlink()) and not overwrite:
            raise InputError(f"record_bag {path} exists already: choose another path or set bag_overwrite true")
        self._queue: queue.Queue = queue.Queue(maxsize=BAG_QUEUE_LIMIT)
        self._opened = threading.Event()
        self._error: Exception | None = None
        self._on_failure = on_failure
        self.failure: str | None = None
        self.written = self.dropped = 0
        self._thread = threading.Thread(target=self._run, args=(storage, overwrite, input_topic), name="bag-writer",
                                        daemon=True)
        self._thread.start()
        self._opened.wait()
        if self._error is not None:
            raise self._error

    def _run(self, storage: str, overwrite: bool, input_topic: str) -> None:
        try:
            recorder = BagRecorder.open(self.path, storage, overwrite=overwrite, input_topic=input_topic)
        except Exception as error:  # noqa: BLE001 -- handed to the opening thread
            self._error = error if isinstance(error, InputError) else InputError(f"cannot record {self.path}: {error}")
            self._opened.set()
            return
        self._opened.set()
        checkpoint_at = time.monotonic() + BAG_CHECKPOINT_S
        while (item := self._queue.get()) is not None:
            if self.failure is not None:
                continue
            method, arguments = item
            try:
                getattr(recorder, method)(*arguments)
                self.written += 1
                if time.monotonic() >= checkpoint_at:
                    checkpoint_at = time.monotonic() + BAG_CHECKPOINT_S
                    self._checkpoint(recorder)
            except Exception as error:  # noqa: BLE001 -- any failure ends the recording, in one line
                self._fail(" ".join(str(error).split()) or type(error).__name__, recorder)
        if self.failure is None:
            try:
                recorder.close()
            except Exception as error:  # noqa: BLE001 -- as above
                self._fail(f"finishing the bag: {' '.join(str(error).split())}", recorder)

    def _checkpoint(self, recorder: BagRecorder) -> None:
        recorder.checkpoint()
        free = shutil.disk_usage(self.path.parent).free
        if free < MIN_FREE_BYTES:
            raise OSError(errno.ENOSPC, f"only {free / 2**20:.0f} MiB left on the disk (recording ends below "
                                        f"{MIN_FREE_BYTES >> 20} MiB)")

    def _fail(self, reason: str, recorder: BagRecorder) -> None:
        try:
            kept = f"the bag {recorder.close()} holds the {self.written} messages written"
        except Exception as error:  # noqa: BLE001 -- say where the data are instead
            kept = (f"what was written is in {recorder.staging} (the bag could not be finished: "
                    f"{' '.join(str(error).split())})")
        self.failure = f"recording stopped: {reason}; {kept}"
        if self._on_failure is not None:
            self._on_failure(self.failure)

    def _put(self, item: tuple) -> None:
        if self.failure is not None:
            return
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            self.dropped += 1

    def write_input(self, stamp_ns: int, value: float) -> None:
        """Queue a current command [A] received at stamp_ns."""
        self._put(("write_input", (stamp_ns, value)))

    def write_output(self, stamp_ns: int, position: float, velocity: float, receive_ns: int) -> None:
        """Queue a JointState (header stamp stamp_ns, position [m], velocity [m/s]) received at receive_ns."""
        self._put(("write_output", (stamp_ns, position, velocity, receive_ns)))

    def close(self) -> Path:
        """Write what is queued, finish the bag (renamed into place) and return its path."""
        self._queue.put(None)
        self._thread.join()
        return self.path


class IdentificationNode(Node):
    """Records the stage's input and output, excites it, and refits the model on request."""

    NODE_NAME = "identification"

    def __init__(self, **node_options: object) -> None:
        self._lock = threading.Lock()
        self.recorder: BagThread | None = None  # set before the handle exists: destroy_node reads them
        self.refit_service: WorkerService | None = None
        self.rollback_service: WorkerService | None = None
        super().__init__(self.NODE_NAME, **node_options)
        note_started(self)
        try:
            self.values = declare_all(self, IDENTIFICATION_PARAMS)
            self.check_storage(str(self.values["bag_storage"]))
            check_families(list(self.values["families"]))
            self.check_drift_settings(self.values)
            self.open_bag(str(self.values["record_bag"]), str(self.values["bag_storage"]),
                          bool(self.values["bag_overwrite"]))
        except InputError:
            self.destroy_node()
            raise
        self.inputs: deque[tuple[int, float]] = deque(maxlen=int(self.values["max_samples"]))
        self.outputs: deque[tuple[int, int, float]] = deque(maxlen=int(self.values["max_samples"]))
        self.excite_start_ns: int | None = None
        self.excite_duration_s = float(self.values["excite_duration"])
        self.excite_timer = None
        self.record_until_ns: int | None = None  # set when an excitation ends with freeze_after_excite
        self.refitting = False
        self.last_report: dict | None = None
        self.history = ModelHistory(int(self.values["model_history"]))
        self._push_reason: str | None = None  # why this node pushed the model the compensator publishes next
        self._refit_after_excitation = False
        self._drift_refit_from_s: float | None = None  # on_drift refit: fit the recent record from here once it is long
        self.add_on_set_parameters_callback(self.on_set_parameters)
        self.command_pub = self.create_publisher(Float64, "current_cmd", COMMAND_QOS)
        self.report_pub = self.create_publisher(String, "~/report", REPORT_QOS)
        self.create_subscription(Float64, str(self.values["input_topic"]), self.on_command, RECORD_COMMAND_QOS)
        self.create_subscription(JointState, "joint_states", self.on_joint_states, RECORD_STATE_QOS)
        self.create_service(Trigger, "~/excite", self.on_excite)
        self.create_service(Trigger, "~/clear", self.on_clear)
        self.create_service(Trigger, "~/abort_excitation", self.on_abort_excitation)
        self.push_client = self.create_client(
            SetParametersAtomically, f"{self.values['compensator_name']}/set_parameters_atomically")
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_timer(DIAGNOSTICS_PERIOD_S, quiet_on_shutdown(self, self.publish_diagnostics))
        self.watch: WatchChannel | None = None
        if self.values["watch"]:
            test = DriftTest(
                window_s=float(self.values["watch_window"]), allowance=float(self.values["watch_allowance"]),
                threshold=float(self.values["watch_threshold"]),
                calibration_windows=int(self.values["watch_calibration_windows"]),
                warmup_windows=int(self.values["watch_warmup_windows"]),
                shift_allowance=float(self.values["watch_shift_allowance"]),
                shift_threshold=float(self.values["watch_shift_threshold"]),
                path_radius=float(self.values["watch_path_radius"]),
                bias_allowance=float(self.values["watch_bias_allowance"]),
                bias_threshold=float(self.values["watch_bias_threshold"]))
            self.watch = WatchChannel(self, test, float(self.values["excite_time_scale"]),
                                      str(self.values["joint_name"]), float(self.values["watch_record"]),
                                      self.on_drift)
            self.create_timer(WATCH_PERIOD_S, quiet_on_shutdown(self, self.on_watch_tick))
        self.create_subscription(String, f"{str(self.values['compensator_name']).rstrip('/')}/model",
                                 self.on_model_in_force, REPORT_QOS)
        # The refit's kernels load (or build, seconds on a cold numba cache) now: in the refit's lowered-priority
        # thread a build beside CPU-bound work held a stop for over 5 s.
        warm_up()
        self.refit_service = WorkerService(self, Trigger, "refit", self.on_refit)
        self.rollback_service = WorkerService(self, Trigger, "rollback", self.on_rollback)
        self.get_logger().info("identification ready"
                               + (f", recording into {self.recorder.path}" if self.recorder else ""))

    # --- parameters and the bag ------------------------------------------------------------------

    @staticmethod
    def check_drift_settings(values: dict[str, object]) -> None:
        """Refuse an on_drift this node does not know, or a drift refit's record longer than the watch keeps."""
        if values["on_drift"] not in ON_DRIFT:
            raise InputError(f"on_drift must be one of {', '.join(ON_DRIFT)}, got {values['on_drift']!r}")
        if values["drift_refit_scope"] not in DRIFT_REFIT_SCOPES:
            raise InputError(f"drift_refit_scope must be one of {', '.join(DRIFT_REFIT_SCOPES)}, got "
                             f"{values['drift_refit_scope']!r}")
        if float(values["drift_refit_record"]) > float(values["watch_record"]):
            raise InputError(f"drift_refit_record {values['drift_refit_record']:g} s is longer than the watch keeps "
                             f"(watch_record {values['watch_record']:g} s)")

    @staticmethod
    def check_storage(storage: str) -> None:
        """Refuse a rosbag2 storage this node cannot write."""
        if storage not in STORAGES:
            raise InputError(f"bag_storage must be one of {', '.join(STORAGES)}, got {storage!r}")

    def open_bag(self, path: str, storage: str, overwrite: bool) -> None:
        """Start recording into a new rosbag2 directory (none for an empty path)."""
        self.recorder = self.new_recorder(path, storage, overwrite)

    def new_recorder(self, path: str, storage: str, overwrite: bool) -> BagThread | None:
        """A recorder into a new rosbag2 directory (None for an empty path); InputError when it cannot be.
        Unfinished bags of the same path (a node killed while recording) are reported, and kept."""
        if not path:
            return None
        leftovers = unfinished_bags(path)
        if leftovers:
            self.get_logger().warning(
                f"{len(leftovers)} unfinished bag(s) of {path} from a recording that was killed, kept as they are "
                f"(the storage file up to the kill, no metadata.yaml): {', '.join(map(str, leftovers))}")
        return BagThread(Path(path), storage, overwrite, str(self.values["input_topic"]),
                         on_failure=self.get_logger().error)

    def close_bag(self) -> None:
        """Finish the bag being recorded (renamed into place)."""
        recorder, self.recorder = self.recorder, None
        if recorder is not None:
            path = recorder.close()
            if recorder.failure is None:
                self.get_logger().info(f"bag written: {path} ({recorder.written} messages"
                                       + (f", {recorder.dropped} dropped while the writer was behind)" if
                                          recorder.dropped else ")"))

    def on_set_parameters(self, changes: list[Parameter]) -> SetParametersResult:
        """Check changes; a new record_bag starts the new bag, then finishes the current one (a bag that cannot
        be started is refused and the current one records on)."""
        candidate = {**self.values, **{change.name: change.value for change in changes}}
        try:
            self.check_storage(str(candidate["bag_storage"]))
            check_families(list(candidate["families"]))
            self.check_drift_settings(candidate)
            switch = candidate["record_bag"] != self.values["record_bag"]
            if switch:
                started = self.new_recorder(str(candidate["record_bag"]), str(candidate["bag_storage"]),
                                            bool(candidate["bag_overwrite"]))
        except (InputError, OSError) as error:
            return SetParametersResult(successful=False, reason=" ".join(str(error).split()))
        if switch:
            self.close_bag()
            self.recorder = started
        self.values = candidate
        return SetParametersResult(successful=True)

    def close(self) -> None:
        """Stop exciting and finish the bag (called before the node is destroyed)."""
        self.stop_excitation()
        self.close_bag()

    def destroy_node(self) -> None:
        """Stop the refit and rollback workers, then destroy the node."""
        for service in (self.refit_service, self.rollback_service):
            if service is not None:
                service.close()
        super().destroy_node()

    # --- health ----------------------------------------------------------------------------------

    def diagnostic_status(self) -> DiagnosticStatus:
        """The node's state as one DiagnosticStatus: ERROR when recording failed, WARN when the bag writer
        dropped messages, else OK; the recording, the buffer, the excitation and the refit."""
        recorder = self.recorder
        level, text = DiagnosticStatus.OK, "refitting" if self.refitting else "idle"
        if self.exciting:
            text = f"exciting: {self.signal_time_s():.0f} of {self.excite_duration_s:g} s of signal"
        if recorder is not None and recorder.failure is not None:
            level, text = DiagnosticStatus.ERROR, recorder.failure
        elif recorder is not None and recorder.dropped:
            level, text = DiagnosticStatus.WARN, f"the bag writer fell behind: {recorder.dropped} messages dropped"
        values = {
            "recording": str(recorder.path) if recorder is not None else "off",
            "bag_messages_written": recorder.written if recorder is not None else 0,
            "bag_messages_dropped": recorder.dropped if recorder is not None else 0,
            "buffer_inputs": len(self.inputs),
            "buffer_outputs": len(self.outputs),
            "exciting": self.exciting,
            "excitation_left_s": round(self.excitation_left_s(), 3) if self.exciting else 0.0,
            "excitation_progress_pct": (round(100.0 * min(self.signal_time_s() / self.excite_duration_s, 1.0), 1)
                                        if self.exciting else 0.0),
            "refitting": self.refitting,
        }
        return DiagnosticStatus(level=level, name=f"{self.get_fully_qualified_name()}: identification", message=text,
                                hardware_id="sma_stage identification",
                                values=[KeyValue(key=key, value=str(value)) for key, value in values.items()])

    def publish_diagnostics(self) -> None:
        """Publish the status on /diagnostics."""
        statuses = [self.diagnostic_status()] + ([self.watch.diagnostic_status()] if self.watch is not None else [])
        array = DiagnosticArray(status=statuses)
        array.header.stamp = self.get_clock().now().to_msg()
        self.diagnostics_pub.publish(array)

    # --- recording -------------------------------------------------------------------------------

    def now_ns(self) -> int:
        """The node clock [ns] (simulated time with use_sim_time)."""
        return self.get_clock().now().nanoseconds

    def on_command(self, message: Float64) -> None:
        """Record a current command [A] at its arrival time."""
        receive_ns, value = self.now_ns(), float(message.data)
        with self._lock:
            if self.record_until_ns is None or receive_ns <= self.record_until_ns:
                self.inputs.append((receive_ns, value))
        if self.watch is not None:
            self.watch.add_input(receive_ns, value)
        recorder = self.recorder
        if recorder is not None:
            recorder.write_input(receive_ns, value)

    def on_joint_states(self, message: JointState) -> None:
        """Record the stage position [m] with its header stamp and arrival time."""
        index = joint_index(message, str(self.values["joint_name"]))
        if index is None:
            return
        receive_ns = self.now_ns()
        stamp_ns = message.header.stamp.sec * 10**9 + message.header.stamp.nanosec
        position = float(message.position[index])
        velocity = float(message.velocity[index]) if index < len(message.velocity) else 0.0
        with self._lock:
            if self.recording_output(receive_ns, stamp_ns):
                self.outputs.append((receive_ns, stamp_ns, position))
        if self.watch is not None:
            self.watch.add_output(receive_ns, stamp_ns, position)
        recorder = self.recorder
        if recorder is not None:
            recorder.write_output(stamp_ns, position, velocity, receive_ns)

    def recording_output(self, receive_ns: int, stamp_ns: int) -> bool:
        """Whether a position belongs in the buffer: always, unless it is frozen; then only positions
        received, or stamped during the excitation, before it ended (a busy node takes them late)."""
        limit = self.record_until_ns
        if limit is None:
            return True
        return receive_ns <= limit or (self.excite_start_ns or 0) <= stamp_ns <= limit

    def on_clear(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Empty the buffer."""
        with self._lock:
            dropped = len(self.inputs) + len(self.outputs)
            self.inputs.clear()
            self.outputs.clear()
            self.record_until_ns = None
        response.success, response.message = True, f"buffer cleared ({dropped} messages dropped)"
        return response

    # --- excitation ------------------------------------------------------------------------------

    @property
    def exciting(self) -> bool:
        """True while the identification signal is being driven."""
        return self.excite_timer is not None

    def signal_time_s(self) -> float:
        """Seconds of signal time since the excitation started."""
        return (self.now_ns() - self.excite_start_ns) * 1e-9 * float(self.values["excite_time_scale"])

    def on_excite(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Start driving the identification signal and return at once."""
        response.success, response.message = self.start_excitation(float(self.values["excite_duration"]))
        return response

    def start_excitation(self, duration_s: float) -> tuple[bool, str]:
        """Drive the identification signal for duration_s [s of signal time]: (started, one line saying so or why
        not)."""
        if self.exciting:
            return False, f"an excitation is running ({self.excitation_left_s():.1f} s of signal left)"
        if self.now_ns() == 0:
            return False, ("no time yet: use_sim_time is true and no /clock message has come (is the stage running "
                           "with use_sim_time?); the signal would start part-way through")
        if self.values["excite_signal"] not in EXCITATIONS:
            return False, f"excite_signal must be one of {', '.join(EXCITATIONS)}, got {self.values['excite_signal']!r}"
        if self.values["clear_on_excite"]:
            self.on_clear(Trigger.Request(), Trigger.Response())
        with self._lock:
            self.record_until_ns = None
        self.excite_start_ns = self.now_ns()
        self.excite_duration_s = duration_s
        self.set_compensator_enabled(False)
        self.excite_timer = self.create_timer(1.0 / float(self.values["excite_rate_hz"]),
                                              quiet_on_shutdown(self, self.on_excite_tick))
        self.on_excite_tick()
        if self.values["excite_signal"] == "designed":
            message = (f"exciting: the designed signal up to {self.values['excite_amplitude_start']:g} A, "
                       f"{duration_s:g} s of signal time")
        else:
            message = (f"exciting: {self.values['excite_amplitude_start']:g} A falling to "
                       f"{self.values['excite_amplitude_end']:g} A, period {self.values['excite_period']:g} s, "
                       f"{duration_s:g} s of signal time")
        self.get_logger().info(message)
        return True, message

    def excitation_left_s(self) -> float:
        """Seconds of signal time the excitation still runs."""
        return max(self.excite_duration_s - self.signal_time_s(), 0.0)

    def on_excite_tick(self) -> None:
        """Publish the signal's current value; at the end publish zero and stop."""
        if self.excite_timer is None:
            return
        t = self.signal_time_s()
        duration = self.excite_duration_s
        if t >= duration:
            self.command_pub.publish(Float64(data=0.0))
            self.stop_excitation()
            frozen = bool(self.values["freeze_after_excite"])
            with self._lock:
                self.record_until_ns = self.now_ns() if frozen else None
            if self._refit_after_excitation:
                self._refit_after_excitation = False
                self.get_logger().info("excitation on drift finished: refitting it")
                self.start_guarded_refit("the excitation on drift", self.snapshot)
                return
            self.get_logger().info("excitation finished: ~/refit can fit it now"
                                   + (" (buffer frozen until ~/clear or ~/excite)" if frozen else ""))
            return
        if self.values["excite_signal"] == "designed":
            value = designed_identification_signal(t, float(self.values["excite_amplitude_start"]), duration)
        else:
            value = paper_identification_signal(t, float(self.values["excite_amplitude_start"]),
                                                float(self.values["excite_amplitude_end"]),
                                                float(self.values["excite_period"]), duration)
        self.command_pub.publish(Float64(data=float(value)))

    def on_abort_excitation(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Stop a running excitation now: current_cmd 0 A, the compensator enabled again; the buffer keeps what
        was recorded and records on (not frozen)."""
        if not self.exciting:
            response.success, response.message = False, "no excitation is running"
            return response
        done, duration = self.signal_time_s(), self.excite_duration_s
        self._refit_after_excitation = False
        self.command_pub.publish(Float64(data=0.0))
        self.stop_excitation()
        response.success = True
        response.message = (f"excitation aborted after {done:.1f} of {duration:g} s of signal: current_cmd 0 A, "
                            "current_cmd handed back to the compensator; the buffer keeps what was recorded")
        self.get_logger().warning(response.message)
        return response

    def stop_excitation(self) -> None:
        """Stop the excitation timer (the current stays at the last value published) and hand current_cmd
        back to the compensator."""
        timer, self.excite_timer = self.excite_timer, None
        if timer is not None:
            self.destroy_timer(timer)
            self.set_compensator_enabled(True)

    def set_compensator_enabled(self, enabled: bool) -> None:
        """Ask the compensator to publish again or to keep silent (pause_compensator); answers are logged,
        not awaited (a service callback must not block)."""
        if not self.values["pause_compensator"] or not self.context.ok():
            return
        name = self.push_client.srv_name
        if not self.push_client.service_is_ready():
            if not enabled:
                self.get_logger().warning(f"{name} not available: a compensator may publish during the excitation")
            return
        request = SetParametersAtomically.Request(parameters=[Parameter("enabled", value=enabled).to_parameter_msg()])
        future = self.push_client.call_async(request)

        def answered(done: object) -> None:
            result = done.result()
            if result is None or not result.result.successful:
                self.get_logger().warning(f"{name} did not take enabled={enabled}: "
                                          f"{result.result.reason if result is not None else 'no answer'}")

        future.add_done_callback(answered)

    # --- refit -----------------------------------------------------------------------------------

    def refusal(self) -> str | None:
        """Why a refit cannot start now (None when it can), and mark it running otherwise."""
        with self._lock:
            if self.exciting:
                return (f"an excitation is running ({self.excitation_left_s():.1f} s of signal left): "
                        "call ~/refit after it ends")
            if self.refitting:
                return "a refit is already running"
            self.refitting = True
            return None

    def snapshot(self) -> Series:
        """The recording so far as a checked Series (InputError when it cannot support a fit)."""
        return self.recording_snapshot(int(self.values["min_samples"]))

    def recording_snapshot(self, min_samples: int) -> Series:
        """The recording so far, aligned as a bag of it would be, with at least min_samples samples."""
        with self._lock:
            inputs, outputs = list(self.inputs), list(self.outputs)
        return recording_series(inputs, outputs, min_samples, str(self.values["input_topic"]),
                                float(self.values["excite_time_scale"]))

    def on_refit(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Fit the recording (in the refit worker thread) and answer with the JSON report."""
        reason = self.refusal()
        if reason is not None:
            response.success, response.message = False, reason
            self.get_logger().warning(f"~/refit refused: {reason}")
            return response
        try:
            report = self.refit()
        except InputError as error:
            response.success, response.message = False, f"refit refused: {error}"
            self.get_logger().warning(response.message)
            return response
        except Cancelled:
            response.success, response.message = False, "refit cancelled: the node is stopping (nothing written)"
            self.get_logger().warning(f"~/{response.message}")
            return response
        except Exception as error:  # noqa: BLE001 -- a failing fit must not take the node down
            response.success = False
            response.message = f"refit failed: {type(error).__name__}: {' '.join(str(error).split())}"
            self.get_logger().error(response.message)
            return response
        finally:
            with self._lock:
                self.refitting = False
        self.publish_report(report)
        response.success, response.message = True, refit_summary(report)
        self.get_logger().info(f"~/refit: {response.message}")
        return response

    def identify(self, series: Series, source: str) -> Identification:
        """The identification pipeline on series with this node's settings (held-out tail, operators,
        diagnosis, families, thinning)."""
        return identify_recording(series, holdout_fraction=float(self.values["holdout_fraction"]),
                                  operators=int(self.values["operators"]) or None,
                                  diagnose_rounds=int(self.values["diagnose_rounds"]), source=source,
                                  workers=int(self.values["diagnose_workers"]),
                                  families=tuple(self.values["families"]),
                                  max_fit_samples=int(self.values["max_fit_samples"]),
                                  niceness=self.refit_niceness())

    def refit_niceness(self) -> int:
        """Nice levels a refit's thread and its worker processes run below the node's other threads."""
        return int(self.values["refit_niceness"])

    def lower_refit_priority(self) -> None:
        """The calling thread (a refit's) refit_niceness levels down: a stage on the same computer keeps its cycles."""
        lower_priority(thread=True, niceness=self.refit_niceness())

    def refit(self) -> dict:
        """Identify, write the model file, push the model; the report (InputError when refused). Runs
        refit_niceness levels below the node's other threads (a stage on the same computer keeps its cycles)."""
        self.lower_refit_priority()
        series = self.snapshot()
        self.get_logger().info(f"~/refit: fitting {len(series)} samples")
        found = self.identify(series, "identification node ~/refit")
        report = found.report
        self.check_held_out(report, series)
        report["model_file"] = self.write_model(found.model)
        report["report_file"] = report_path(report["model_file"])
        report["compensator"] = self.push(found.model, "~/refit")
        if not report["compensator"]["pushed"]:
            report["warnings"].append(report["compensator"]["message"])
        if report["report_file"] is not None:
            self.write_report(report)
        return report

    def check_held_out(self, report: dict, series: Series) -> None:
        """InputError when the model to deploy misses the held-out tail by more than max_held_out_rms_pct."""
        held_out = deployed_held_out(report) or {}
        rms_pct, limit = held_out.get("rms_pct"), float(self.values["max_held_out_rms_pct"])
        if rms_pct is not None and rms_pct > limit:
            raise InputError(f"the model misses the held-out tail by {rms_pct:.3g} % RMS, more than "
                             f"max_held_out_rms_pct {limit:g} % (recording: {len(series)} samples over "
                             f"{series.t[-1] - series.t[0]:.3g} s): the model in force stays")

    def write_report(self, report: dict) -> None:
        """Write the JSON report beside the model file, atomically; a failure is a warning in the report."""
        try:
            atomic_write_text(report["report_file"], report_json(report) + "\n")
        except OSError as error:
            report["warnings"].append(f"cannot write {report['report_file']}: {error.strerror or error}")
            report["report_file"] = None

    def write_model(self, model: AnyModel) -> str | None:
        """Write the identified model's file atomically (None when model_file is empty)."""
        path = str(self.values["model_file"])
        if not path:
            return None
        try:
            model.save(path)
        except OSError as error:
            raise InputError(f"cannot write model_file {path}: {error.strerror or error}") from None
        return path

    def push(self, model: AnyModel, reason: str) -> dict:
        """Send the whole model to the compensator as one atomic parameter change (its `model`); reason: why, for
        the history."""
        self._push_reason = reason
        outcome = self._push(model)
        if not outcome["pushed"]:
            self._push_reason = None
        return outcome

    def _push(self, model: AnyModel) -> dict:
        name = self.push_client.srv_name
        if not self.push_client.wait_for_service(timeout_sec=float(self.values["push_timeout"])):
            return {"pushed": False, "message": f"compensator service {name} not available: model not pushed"}
        parameters = [Parameter("model", value=model.to_yaml_text()).to_parameter_msg()]
        future = self.push_client.call_async(SetParametersAtomically.Request(parameters=parameters))
        done = threading.Event()
        future.add_done_callback(lambda _: done.set())
        if not done.wait(max(float(self.values["push_timeout"]), 1.0)) or future.result() is None:
            return {"pushed": False, "message": f"no answer from {name}: the model may not be in force"}
        result = future.result().result
        if not result.successful:
            return {"pushed": False, "message": f"compensator refused the model: {result.reason}"}
        return {"pushed": True, "message": f"model set through {name}"}

    # --- the models in force: history, rollback, drift ---------------------------------------------

    def publish_report(self, report: dict | None = None) -> None:
        """Publish the last refit's report (or this new one) on ~/report with the history of the models in force."""
        if report is not None:
            self.last_report = report
        document = {**(self.last_report or {}), "history": self.history.to_report()}
        self.report_pub.publish(String(data=report_json(document)))

    def on_model_in_force(self, message: String) -> None:
        """The compensator's model in force: noted in the history (one log line when it is another one) and
        watched."""
        try:
            document = json.loads(message.data)
            model = any_model_from_yaml_text(str(document["model"]))
        except (InputError, ValueError, KeyError, TypeError) as error:
            self.get_logger().warning(f"the compensator's model cannot be read: {' '.join(str(error).split())}")
            return
        source = str(document.get("source", "unknown"))
        reason, self._push_reason = self._push_reason or "set on the compensator", None
        held_out = (model.metadata or {}).get("held_out_rms")
        span = (model.metadata or {}).get("output_span")
        held_out_pct = 100.0 * float(held_out) / float(span) if held_out and span else None
        entry = self.history.note(model, source, reason, self.now_ns() * 1e-9, held_out_pct)
        if entry is not None:
            self.get_logger().info(f"model in force: {source} ({reason}); {len(self.history.entries)} in the history")
            self._drift_refit_from_s = None
            self.publish_report()
        if self.watch is not None:
            self.watch.set_model(model, source)

    def on_rollback(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Push the model in force before the one now, started where the recent record leaves it."""
        previous = self.history.previous
        if previous is None:
            response.success, response.message = False, "no model before the one in force to roll back to"
            return response
        source, since_s = previous.source, previous.since_s  # the entry is noted again once the model is in force
        t_s, current_a, _ = self.watch.recent_arrays() if self.watch is not None else ((), (), ())
        pushed = self.push(started_from(previous.model, t_s, current_a), f"~/rollback to the model from {source}")
        response.success = pushed["pushed"]
        response.message = (f"rolled back to the model from {source} (in force from {since_s:.1f} s until the one "
                            "rolled back)" if pushed["pushed"] else f"rollback failed: {pushed['message']}")
        log = self.get_logger().info if pushed["pushed"] else self.get_logger().warning
        log(f"~/rollback: {response.message}")
        return response

    def on_watch_tick(self) -> None:
        """Run the watch; start a refit on drift once the record from the change's onset is long enough."""
        self.watch.run()
        start_s = self._drift_refit_from_s
        if start_s is None:
            return
        t_s, _, _ = self.watch.recent_arrays()
        if len(t_s) and t_s[-1] - start_s >= float(self.values["drift_refit_record"]):
            self._drift_refit_from_s = None
            self.start_guarded_refit(f"the record from {start_s:.0f} s, where the change began",
                                     lambda: self.recent_series(start_s),
                                     hysteresis_only=self.values["drift_refit_scope"] == "hysteresis")

    def on_drift(self, watch: ModelWatch) -> None:
        """The watch turned to drift: act as on_drift says (report: the watch logged it already)."""
        action = self.values["on_drift"]
        if action == "refit":
            self._drift_refit_from_s = watch.onset_s
            self.get_logger().info(f"drift: a refit follows once {self.values['drift_refit_record']:g} s are "
                                   f"recorded from where the change began ({watch.onset_s:.0f} s)")
        elif action == "excite":
            if self.refitting:
                self.get_logger().warning("drift: no excitation while a refit runs")
                return
            started, message = self.start_excitation(float(self.values["drift_excite_duration"]))
            self._refit_after_excitation = started
            if not started:
                self.get_logger().warning(f"drift: cannot excite: {message}")

    def recent_series(self, from_s: float) -> Series:
        """The watch's recent record from from_s [s of stage time] on, as a checked Series (InputError when it
        cannot support a fit)."""
        t_s, current_a, position_m = self.watch.recent_arrays()
        kept = t_s >= from_s
        return make_series(t_s[kept], current_a[kept], position_m[kept], "the watch's recent record",
                           min_samples=int(self.values["min_samples"]))

    def start_guarded_refit(self, what: str, series: Callable[[], Series], hysteresis_only: bool = False) -> None:
        """Refit what series() gives in the background (hysteresis_only: the model in force's GPI parameters with
        its dynamics held, where it can be); the model in force is replaced only when the new one predicts the
        held-out tail better."""
        reason = self.refusal()
        if reason is not None:
            self.get_logger().warning(f"refit on drift refused: {reason}")
            return

        def work() -> None:
            self.lower_refit_priority()
            try:
                self.guarded_refit(what, series(), hysteresis_only)
            except InputError as error:
                self.get_logger().warning(f"refit on drift refused: {error}")
            except Cancelled:
                self.get_logger().warning("refit on drift cancelled: the node is stopping (nothing pushed)")
            except Exception as error:  # noqa: BLE001 -- a failing fit must not take the node down
                self.get_logger().error(f"refit on drift failed: {type(error).__name__}: "
                                        f"{' '.join(str(error).split())}")
            finally:
                with self._lock:
                    self.refitting = False

        self.refit_service.run_in_background(work)

    def guarded_refit(self, what: str, series: Series, hysteresis_only: bool = False) -> None:
        """Fit series (see start_guarded_refit); push the model if it predicts the held-out tail better than the
        model in force."""
        in_force = self.history.current
        if in_force is None:
            raise InputError("no model in force is known (has the compensator published ~/model?)")
        refusal = dynamics_held_refusal(in_force.model) if hysteresis_only else None
        if hysteresis_only and refusal is None:
            self.get_logger().info(f"refit on drift: the hysteresis of the model in force on {what} ({len(series)} "
                                   "samples), its dynamics held")
            found = refit_hysteresis(series, in_force.model, float(self.values["holdout_fraction"]),
                                     source=f"identification node, hysteresis refit on drift ({what})")
        else:
            self.get_logger().info(f"refit on drift: fitting {what} ({len(series)} samples)"
                                   + (f"; all of it: {refusal}" if refusal else ""))
            found = self.identify(series, f"identification node, refit on drift ({what})")
        decision = judge_swap(found.model, in_force.model, series, found.scored_from)
        report = {**found.report, "swap": {"swapped": decision.swap, "reason": decision.reason,
                                           "candidate": decision.candidate.to_dict(),
                                           "in_force": decision.in_force.to_dict()},
                  "model_file": None, "report_file": None}
        if decision.swap:
            t_s, current_a, _ = self.watch.recent_arrays() if self.watch is not None else ((), (), ())
            model = started_from(found.model, t_s, current_a) if len(t_s) else found.model
            report["model_file"] = self.write_model(model)
            report["report_file"] = report_path(report["model_file"])
            report["compensator"] = self.push(model, f"refit on drift: {decision.reason}")
            if not report["compensator"]["pushed"]:
                report["warnings"].append(report["compensator"]["message"])
            if report["report_file"] is not None:
                self.write_report(report)
        self.publish_report(report)
        self.get_logger().info(f"refit on drift: {decision.reason}")


def main(args: list[str] | None = None) -> None:
    """Entry point `identification_node`."""
    exit_with(run_node(IdentificationNode, args))


if __name__ == "__main__":
    main()
