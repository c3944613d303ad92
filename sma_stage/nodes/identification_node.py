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

This file holds the wiring, the recording's callbacks and the health; the rest is in sma_stage.nodes.identification
(params, recording, excitation, refit, models: the history, ~/rollback and the watch's drift).
"""

from __future__ import annotations

import math
import threading
from collections import deque
from pathlib import Path

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import SetParametersResult
from rcl_interfaces.srv import SetParametersAtomically
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.time import Time
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64, String
from std_srvs.srv import Trigger

from sma_stage.errors import InputError
from sma_stage.experiment.probe import ProbeResult
from sma_stage.identify.families import check_families
from sma_stage.identify.history import ModelHistory
from sma_stage.identify.watch import DriftTest
from sma_stage.identify.workers import warm_up
from sma_stage.io.rosbag_io import joint_index, unfinished_bags
from sma_stage.nodes._common import (
    COMMAND_QOS,
    RECORD_COMMAND_QOS,
    RECORD_STATE_QOS,
    REPORT_QOS,
    WorkerService,
    declare_all,
    exit_with,
    note_started,
    quiet_on_shutdown,
    run_node,
)
from sma_stage.nodes.identification.excitation import ExcitationRoom
from sma_stage.nodes.identification.models import ModelsRoom
from sma_stage.nodes.identification.params import (
    DIAGNOSTICS_PERIOD_S,
    IDENTIFICATION_PARAMS,
    IdentificationSettings,
    check_drift_settings,
    check_storage,
)
from sma_stage.nodes.identification.recording import BagThread
from sma_stage.nodes.identification.refit import RefitRoom
from sma_stage.nodes.model_watch import WATCH_PERIOD_S, WatchChannel


class IdentificationNode(ExcitationRoom, RefitRoom, ModelsRoom, Node):
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
            self.settings = IdentificationSettings.of(declare_all(self, IDENTIFICATION_PARAMS))
            check_storage(self.settings.bag_storage)
            check_families(self.settings.families)
            check_drift_settings(self.settings)
            self.open_bag(self.settings.record_bag, self.settings.bag_storage,
                          self.settings.bag_overwrite)
        except InputError:
            self.destroy_node()
            raise
        self.inputs: deque[tuple[int, float]] = deque(maxlen=self.settings.max_samples)
        self.outputs: deque[tuple[int, int, float, float]] = deque(maxlen=self.settings.max_samples)
        self.excite_start_ns: int | None = None
        self.excite_duration_s = self.settings.excite_duration
        self.probe: ProbeResult | None = None  # what the designed excitation's probe found
        self.design: tuple[np.ndarray, np.ndarray] | None = None  # the designed excitation's breakpoints
        self.excite_timer = None
        self.record_until_ns: int | None = None  # set when an excitation ends with freeze_after_excite
        self.refitting = False
        self.last_report: dict | None = None
        self.history = ModelHistory(self.settings.model_history)
        self._push_reason: str | None = None  # why this node pushed the model the compensator publishes next
        self._refit_after_excitation = False
        self._drift_refit_from_s: float | None = None  # on_drift refit: fit the recent record from here once it is long
        self.add_on_set_parameters_callback(self.on_set_parameters)
        self.command_pub = self.create_publisher(Float64, "current_cmd", COMMAND_QOS)
        self.report_pub = self.create_publisher(String, "~/report", REPORT_QOS)
        self.create_subscription(Float64, self.settings.input_topic, self.on_command, RECORD_COMMAND_QOS)
        self.create_subscription(JointState, "joint_states", self.on_joint_states, RECORD_STATE_QOS)
        self.create_service(Trigger, "~/excite", self.on_excite)
        self.create_service(Trigger, "~/clear", self.on_clear)
        self.create_service(Trigger, "~/abort_excitation", self.on_abort_excitation)
        self.push_client = self.create_client(
            SetParametersAtomically, f"{self.settings.compensator_name}/set_parameters_atomically")
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_timer(DIAGNOSTICS_PERIOD_S, quiet_on_shutdown(self, self.publish_diagnostics))
        self.watch: WatchChannel | None = None
        if self.settings.watch:
            test = DriftTest(
                window_s=self.settings.watch_window, allowance=self.settings.watch_allowance,
                threshold=self.settings.watch_threshold,
                calibration_windows=self.settings.watch_calibration_windows,
                warmup_windows=self.settings.watch_warmup_windows,
                shift_allowance=self.settings.watch_shift_allowance,
                shift_threshold=self.settings.watch_shift_threshold,
                path_radius=self.settings.watch_path_radius,
                bias_allowance=self.settings.watch_bias_allowance,
                bias_threshold=self.settings.watch_bias_threshold)
            self.watch = WatchChannel(self, test, self.settings.excite_time_scale,
                                      self.settings.joint_name, self.settings.watch_record,
                                      self.on_drift, self.settings.input_from_effort)
            self.create_timer(WATCH_PERIOD_S, quiet_on_shutdown(self, self.on_watch_tick))
        self.create_subscription(String, f"{self.settings.compensator_name.rstrip('/')}/model",
                                 self.on_model_in_force, REPORT_QOS)
        # The refit's kernels load (or build, seconds on a cold numba cache) now: in the refit's lowered-priority
        # thread a build beside CPU-bound work held a stop for over 5 s.
        warm_up()
        self.refit_service = WorkerService(self, Trigger, "refit", self.on_refit)
        self.rollback_service = WorkerService(self, Trigger, "rollback", self.on_rollback)
        self.get_logger().info("identification ready"
                               + (f", recording into {self.recorder.path}" if self.recorder else ""))

    # --- parameters and the bag ------------------------------------------------------------------

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
        return BagThread(Path(path), storage, overwrite, self.settings.input_topic,
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
        candidate = self.settings.changed({change.name: change.value for change in changes})
        try:
            check_storage(candidate.bag_storage)
            check_families(candidate.families)
            check_drift_settings(candidate)
            switch = candidate.record_bag != self.settings.record_bag
            if switch:
                started = self.new_recorder(candidate.record_bag, candidate.bag_storage,
                                            candidate.bag_overwrite)
        except (InputError, OSError) as error:
            return SetParametersResult(successful=False, reason=" ".join(str(error).split()))
        if switch:
            self.close_bag()
            self.recorder = started
        self.settings = candidate
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
        """Record the stage position [m] with its header stamp and arrival time, and the current [A] applied over
        the period that ended at it (its effort; NaN when the message has none)."""
        index = joint_index(message, self.settings.joint_name)
        if index is None:
            return
        receive_ns = self.now_ns()
        stamp_ns = Time.from_msg(message.header.stamp).nanoseconds
        position = float(message.position[index])
        velocity = float(message.velocity[index]) if index < len(message.velocity) else 0.0
        effort = float(message.effort[index]) if index < len(message.effort) else math.nan
        with self._lock:
            if self.recording_output(receive_ns, stamp_ns):
                self.outputs.append((receive_ns, stamp_ns, position, effort))
        if self.watch is not None:
            self.watch.add_output(receive_ns, stamp_ns, position, effort)
        recorder = self.recorder
        if recorder is not None:
            recorder.write_output(stamp_ns, position, velocity, receive_ns, effort if math.isfinite(effort) else None)

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


def main(args: list[str] | None = None) -> None:
    """Entry point `identification_node`."""
    exit_with(run_node(IdentificationNode, args))


if __name__ == "__main__":
    main()

