"""The identification node's watch of the model in force (sma_stage.identify.watch): the node hands it the model
the compensator publishes on `<compensator>/model`; it runs it on the applied current (from where the recent
record leaves it), publishes the residual on `~/residual` and its state on /diagnostics, keeps the recent record
(what a refit on drift fits, and where a model swapped in starts) and tells the node when it turns to drift."""

from __future__ import annotations

import json
import math
import threading
from collections import deque
from collections.abc import Callable

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.time import Time
from sensor_msgs.msg import JointState
from std_msgs.msg import String

from sma_stage.identify.watch import DriftTest, ModelWatch, RecentRecord, load_kernels
from sma_stage.io.rosbag_io import output_times
from sma_stage.model.identified import load_model_file
from sma_stage.model.kinds import AnyModel
from sma_stage.nodes._common import STATE_PUBLISH_QOS
from sma_stage.nodes.launch import DEFAULT_MODEL_FILE

WATCH_PERIOD_S = 0.2  # the queued samples are run through the model this often
QUEUE_LENGTH = 100_000  # samples kept for the watch between two runs [messages per topic]


def model_message(model_yaml: str, source: str) -> String:
    """What the compensator publishes on ~/model: the model in force and where it came from, as JSON."""
    return String(data=json.dumps({"source": source, "model": model_yaml}))


class WatchChannel:
    """The watch's inputs, its model and its outputs, for one node (`owner`): time_scale gives stage seconds
    per node-clock second; joint_name the joint of joint_states; record_s the stage seconds of recent samples
    kept; on_drift is called (from the owner's executor) when the watch turns to drift. With from_effort the
    current of a position is its message's effort (stamped together) when every queued position has one; else
    the latest input received by the position's time."""

    def __init__(self, owner: Node, test: DriftTest, time_scale: float, joint_name: str, record_s: float,
                 on_drift: Callable[[ModelWatch], None], from_effort: bool = True) -> None:
        self.owner, self.test, self.time_scale, self.joint_name = owner, test, time_scale, joint_name
        self.on_drift, self.from_effort = on_drift, from_effort
        self._lock = threading.Lock()
        self._inputs: deque[tuple[int, float]] = deque(maxlen=QUEUE_LENGTH)
        self._outputs: deque[tuple[int, int, float, float]] = deque(maxlen=QUEUE_LENGTH)
        self._last_input: tuple[int, float] | None = None
        self.recent = RecentRecord(record_s)
        self.watch: ModelWatch | None = None
        self.source = "none"
        self.since_ns: int | None = None
        self.last_sample_ns: int | None = None
        self._reported_state = "no_model"
        self.residual_pub = owner.create_publisher(JointState, "~/residual", STATE_PUBLISH_QOS)
        load_kernels(load_model_file(DEFAULT_MODEL_FILE))

    def set_model(self, model: AnyModel, source: str) -> None:
        """A new model in force: the watch starts again with it, from where the recent record leaves it."""
        with self._lock:
            t_s, current_a, _ = self.recent.arrays()
            self.watch = ModelWatch(model, self.test, history=(t_s, current_a))
            self.source = source
            self.since_ns = self.owner.get_clock().now().nanoseconds
            self._outputs.clear()
            self._reported_state = "ok"
        self.owner.get_logger().info(f"model watch: watching the model from {source}")

    def recent_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The recent record: (t [s of stage time], applied current [A], position [m])."""
        with self._lock:
            return self.recent.arrays()

    def add_input(self, receive_ns: int, value: float) -> None:
        with self._lock:
            self._inputs.append((receive_ns, value))

    def add_output(self, receive_ns: int, stamp_ns: int, position: float, effort: float = math.nan) -> None:
        with self._lock:
            self._outputs.append((receive_ns, stamp_ns, position, effort))

    def run(self) -> None:
        """Run the queued positions through the model and publish their residuals."""
        with self._lock:
            outputs = list(self._outputs)
            inputs = ([self._last_input] if self._last_input is not None else []) + list(self._inputs)
            self._outputs.clear()
            self._inputs.clear()
            if inputs:
                self._last_input = inputs[-1]
        if not outputs:
            return
        receive_ns, stamp_ns, positions, efforts = (np.array(column) for column in zip(*outputs, strict=True))
        times_ns = output_times(receive_ns.astype(np.int64), stamp_ns.astype(np.int64))
        order = np.argsort(times_ns, kind="stable")
        times_ns, positions, efforts = times_ns[order], positions[order], efforts[order].astype(float)
        if self.from_effort and np.all(np.isfinite(efforts)):
            currents = efforts  # stamped with the position they led to
        elif inputs:
            input_ns, values = (np.array(column) for column in zip(*inputs, strict=True))
            in_order = np.argsort(input_ns, kind="stable")
            latest = np.searchsorted(input_ns[in_order], times_ns, side="right") - 1  # the current held then
            currents = np.where(latest >= 0, values[in_order][np.maximum(latest, 0)].astype(float), math.nan)
        else:
            return
        usable = np.isfinite(currents) & np.append(np.diff(times_ns) > 0, True)
        if self.last_sample_ns is not None:
            usable &= times_ns > self.last_sample_ns
        if not usable.any():
            return
        kept_ns, measured, held = times_ns[usable], positions[usable].astype(float), currents[usable]
        stage_s = kept_ns * 1e-9 * self.time_scale
        self.last_sample_ns = int(kept_ns[-1])
        with self._lock:  # a model set from here on starts from the record with these samples in it
            self.recent.add(stage_s, held, measured)
            watch = self.watch
        if watch is None:
            return
        residual = watch.step(stage_s, held, measured)
        for time_ns, value in zip(kept_ns, residual, strict=True):
            message = JointState(name=[self.joint_name], position=[float(value)])
            message.header.stamp = Time(nanoseconds=int(time_ns)).to_msg()
            self.residual_pub.publish(message)
        self._log_change(watch)

    def _log_change(self, watch: ModelWatch) -> None:
        state = watch.state
        if state == self._reported_state:
            return
        self._reported_state = state
        if state != "drift":
            return
        if watch.bias_drift:
            evidence = (f"where the stage retraces its path the residual moved steadily, by {watch.last_bias_z:.3g} "
                        f"times what its mean did with nothing changed in the last window (bias statistic "
                        f"{watch.bias_statistic:.3g} > {self.test.bias_threshold:g})")
        elif watch.path_drift:
            evidence = (f"where the stage retraces its path the residual moved by {watch.last_innovation_rms:.3g} m "
                        f"RMS (path statistic {watch.path_statistic:.3g} > {self.test.shift_threshold:g}, reference "
                        f"{watch.cusum.reference:.3g} m)")
        else:
            evidence = (f"the residual's RMS {watch.last_window_rms:.3g} m rose above {self.test.allowance:g} x the "
                        f"largest while calibrating {watch.cusum.ceiling:.3g} m (level statistic "
                        f"{watch.cusum.statistic:.3g} > {self.test.threshold:g})")
        self.owner.get_logger().warning(f"model watch: drift: {evidence}: the model in force no longer describes "
                                        "the stage")
        self.on_drift(watch)

    def state(self) -> str:
        """ok, drift, no_model or no_data."""
        if self.watch is None:
            return "no_model"
        if self.watch.samples == 0:
            return "no_data"
        return self.watch.state

    def diagnostic_status(self) -> DiagnosticStatus:
        """`<node>: model watch`: OK unless drift (WARN)."""
        state, watch = self.state(), self.watch
        now_ns = self.owner.get_clock().now().nanoseconds
        values: dict[str, object] = {"state": state, "model_source": self.source}
        if watch is not None:
            reference = watch.cusum.reference
            span = (getattr(watch.model, "metadata", None) or {}).get("output_span")
            rms = watch.last_window_rms
            values.update({
                "residual_rms_m": rms if rms is not None else "none",
                "residual_rms_pct_of_stroke": (round(100.0 * rms / float(span), 3) if rms is not None and span
                                               else "unknown"),
                "reference_rms_m": reference if reference is not None else "calibrating",
                "drift_statistic": round(watch.path_statistic, 4),
                "drift_threshold": self.test.shift_threshold,
                "bias_statistic": round(watch.bias_statistic, 4),
                "bias_threshold": self.test.bias_threshold,
                "bias_held_out_m": watch.held_out_bias_m if watch.held_out_bias_m is not None else "calibrating",
                "bias_scale_widening": round(watch.bias_scale_widening, 3),
                "size_held_out_m": watch.held_out_size_m if watch.held_out_size_m is not None else "calibrating",
                "path_coverage": round(watch.coverage, 3) if watch.coverage is not None else "none",
                "level_statistic": round(watch.cusum.statistic, 4),
                "level_threshold": self.test.threshold,
                "windows": watch.cusum.windows,
                "model_age_s": round((now_ns - self.since_ns) * 1e-9, 1) if self.since_ns is not None else "none",
            })
        level = DiagnosticStatus.WARN if state == "drift" else DiagnosticStatus.OK
        message = {"ok": "the model in force predicts the stage", "no_model": "no model from the compensator yet",
                   "no_data": "no joint_states and applied current to compare",
                   "drift": "drift: the model in force no longer describes the stage"}[state]
        if state == "ok" and watch is not None and watch.calibrating:
            message = "calibrating: learning the residual along the stage's path"
        return DiagnosticStatus(level=level, name=f"{self.owner.get_fully_qualified_name()}: model watch",
                                message=message, hardware_id="sma_stage model watch",
                                values=[KeyValue(key=key, value=str(value)) for key, value in values.items()])
