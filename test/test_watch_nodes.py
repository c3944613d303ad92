"""The model watch through the three node executables on simulated time, the stage in lockstep with the loop (its
`lockstep_timeout`, the compensator's `control_trigger: joint_states`): excite and refit, then tracking a sine
with the PI loop while the watch learns the residual along the path; a 2 N load step of the simulated stage is
flagged, the refit on drift swaps in a model fitted after the step that tracks within 1.5x the error before it,
and ~/rollback restores the model before it. WATCH_TEST_FAMILIES (default gpi) sets the refit's model families:
with `WATCH_TEST_FAMILIES=gpi,two_wire pytest -s test/test_watch_nodes.py` it watches the two-wire model."""

import json
import os

import numpy as np
import pytest

pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from rclpy.time import Time  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import String  # noqa: E402
from test_end_to_end import TEST_PRIORITY, refit_after_excitation  # noqa: E402

from sma_stage.model.kinds import any_model_from_yaml_text  # noqa: E402
from sma_stage.nodes._common import COMMAND_QOS, REPORT_QOS, STATE_SUBSCRIBE_QOS  # noqa: E402
from sma_stage.nodes.launch import CONFIG_DIR, NodeProcesses, RosClient, wait_for  # noqa: E402

TIME_SCALE = 50.0  # simulated s per wall s: one 0.5 s stage step every 10 ms, slower when the loop answers later
STEP_S = 0.5  # simulated s per stage step, control period and setpoint
LOCKSTEP_TIMEOUT_S = 0.5  # [wall s] the stage waits at most this long for the command answering its last position
AHEAD_STEPS = 20  # setpoints sent this many steps ahead of the stage (a test client starved by a loaded machine
# does not fall that far behind)
EXCITE_S = 500.0
LOAD_STEP_S = 4200.0  # the stage's load step [s of simulated time]: after the refit (it ended at 1618 s on a cold
# numba cache beside a CPU-bound process; the watch calibrates for 1100 s after it)
LOAD_STEP_N = 2.0  # the step: in lockstep a window's mean wanders as in process (bench/bench_watch_nodes.py)
PERIOD_S = 200.0  # the tracked sine's: at 100 s the loop's hand-over between the wires took one of two paths,
# and a period that took the other moved the GPI's residual (the watch flagged it, the same in process)
COMPARED_S = 400.0  # tracking error compared over this long before the step and after the swap
TRACKING_RATIO = 1.5  # the tracking error after the swap at most this times the error before the step
# The watch's 10 s windows and 30 of warm-up; 80 windows of calibration (120 by default) so that it ends 1100 s
# after the refit, in time for the step.
WATCH_WINDOWS = {"watch_calibration_windows": 80}
FAMILIES = os.environ.get("WATCH_TEST_FAMILIES", "gpi").split(",")  # the refit's families (docs: gpi,two_wire too)


class Tracking:
    """Publishes a sine setpoint at the simulated time and records the position, the model watch's state and
    ~/report."""

    def __init__(self, client: RosClient) -> None:
        self.client, self.middle, self.amplitude = client, 0.0, 0.0
        self.tracking = False  # set once the refit is in force: each position is answered with a setpoint
        self.published_tick_s: float | None = None  # the stage time [s] the last setpoint was published for
        self.longest_gap_s = 0.0  # the longest stage time between two setpoints published [s]
        self.states: list[tuple[float, float]] = []  # (stamp [s], position [m]), appended whole by the spin thread
        self.watch_states: list[tuple[float, str]] = []
        self.watch_values: list[tuple[float, dict[str, str]]] = []
        self.reports: list[dict] = []
        self.publisher = client.node.create_publisher(JointState, "setpoint_stamped", COMMAND_QOS)
        client.node.create_subscription(JointState, "joint_states", self.on_state, STATE_SUBSCRIBE_QOS)
        client.node.create_subscription(DiagnosticArray, "/diagnostics", self.on_diagnostics, 100)
        client.node.create_subscription(String, "identification/report",
                                        lambda m: self.reports.append(json.loads(m.data)), REPORT_QOS)

    def setpoint(self, t_s: float) -> float:
        return self.middle + self.amplitude * np.sin(2 * np.pi * t_s / PERIOD_S)

    def on_state(self, message: JointState) -> None:
        """Record the position and, once tracking, send the setpoint AHEAD_STEPS steps ahead, stamped with its time
        (`setpoint_stamped`): the compensator takes it at that step, never early or late."""
        stamp_s = message.header.stamp.sec + 1e-9 * message.header.stamp.nanosec
        self.states.append((stamp_s, message.position[0]))
        if self.tracking:
            self.publish_setpoint(stamp_s + AHEAD_STEPS * STEP_S)

    def publish_setpoint(self, time_s: float) -> None:
        """The sine's setpoint [m] for time_s [s], stamped with it; notes the longest gap between two."""
        message = JointState(name=["stage_x"], position=[float(self.setpoint(time_s))])
        message.header.stamp = Time(nanoseconds=round(time_s * 1e9)).to_msg()
        self.publisher.publish(message)
        if self.published_tick_s is not None:
            self.longest_gap_s = max(self.longest_gap_s, time_s - self.published_tick_s)
        self.published_tick_s = time_s

    def on_diagnostics(self, message: DiagnosticArray) -> None:
        for status in message.status:
            if status.name.endswith("model watch"):
                values = {item.key: item.value for item in status.values}
                stamp_s = message.header.stamp.sec + 1e-9 * message.header.stamp.nanosec
                self.watch_states.append((stamp_s, values["state"]))
                self.watch_values.append((stamp_s, values))

    def watch_summary(self, start_s: float, stop_s: float) -> str:
        """The largest of each drift statistic on /diagnostics between two times, and the bias test's scale."""
        seen = [values for stamp, values in self.watch_values if start_s <= stamp < stop_s]

        def largest(key: str) -> float:
            return max((float(values[key]) for values in seen if key in values), default=float("nan"))

        def last(key: str) -> str:
            return next((values[key] for values in reversed(seen) if key in values), "none")

        return (f"watch from {start_s:.0f} to {stop_s:.0f} s: largest statistics path {largest('drift_statistic')}, "
                f"bias {largest('bias_statistic')}, level {largest('level_statistic')}; bias_held_out_m "
                f"{last('bias_held_out_m')} (widened x{last('bias_scale_widening')}), size_held_out_m "
                f"{last('size_held_out_m')}")

    def statistic_steps(self, key: str, start_s: float, stop_s: float) -> str:
        """Each new value of a drift statistic on /diagnostics between two times, as 's after start_s: value'."""
        steps, last = [], None
        for stamp, values in self.watch_values:
            if start_s <= stamp < stop_s and key in values and values[key] != last:
                last = values[key]
                steps.append(f"{stamp - start_s:.0f}: {float(last):.2f}")
        return ", ".join(steps)

    def until(self, predicate, wall_timeout_s: float, what: str, check) -> None:
        """Track (on_state publishes the setpoints) until predicate() holds."""
        wait_for(predicate, wall_timeout_s, what, check)

    def tracking_rms_m(self, start_s: float, stop_s: float) -> float:
        stamps, positions = np.array(list(self.states)).T
        kept = (stamps >= start_s) & (stamps < stop_s)
        return float(np.sqrt(np.mean((positions[kept] - self.setpoint(stamps[kept])) ** 2)))


def test_the_watch_flags_a_load_step_swaps_in_a_refit_and_rolls_back(tmp_path):
    domain = int(os.environ["ROS_DOMAIN_ID"])
    with NodeProcesses(tmp_path / "nodes", domain) as nodes:
        nodes.start("compensator_node", {"rate_hz": 1.0 / STEP_S, "use_sim_time": True,
                                         "control_trigger": "joint_states"},
                    [CONFIG_DIR / "compensator.yaml"])
        nodes.start("identification_node", {"excite_duration": EXCITE_S, "excite_rate_hz": 1.0 / STEP_S, "operators": 5,
                                             "min_samples": 60, "model_file": str(tmp_path / "model.yaml"),
                                             "use_sim_time": True, "on_drift": "refit", "families": FAMILIES,
                                             **WATCH_WINDOWS, **TEST_PRIORITY},
                    [CONFIG_DIR / "identification.yaml"])
        with RosClient(domain, "watch_test", use_sim_time=True) as client:
            # the stage, whose clock the others run on, last: their start (seconds on a cold numba cache) is not
            # simulated time lost before the load step
            client.wait_for_services(["compensator/reload", "identification/refit", "identification/rollback"],
                                     60.0, nodes.check_running)
            nodes.start("stage_node", {"rate_hz": TIME_SCALE / STEP_S, "time_scale": TIME_SCALE, "command_timeout": 5.0,
                                       "lockstep_timeout": LOCKSTEP_TIMEOUT_S, "use_sim_time": True, "load_change_n": LOAD_STEP_N,
                                       "load_change_time_s": LOAD_STEP_S}, [CONFIG_DIR / "stage.yaml"])
            client.wait_for_services(["stage/stop"], 60.0, nodes.check_running)
            tracking = Tracking(client)
            first = refit_after_excitation(client, nodes.check_running)
            assert first["compensator"]["pushed"], first["compensator"]["message"]
            refitted = client.get_parameters("compensator", ["model"])["model"]
            positions = [position for _, position in tracking.states]
            low, high = min(positions), max(positions)
            tracking.middle, tracking.amplitude = 0.5 * (low + high), 0.3 * (high - low)
            for ahead in range(1, AHEAD_STEPS + 1):
                tracking.publish_setpoint(client.now_s() + ahead * STEP_S)
            tracking.tracking = True
            started_s = client.now_s()
            print(f"tracking from {started_s:.0f} s of simulated time")
            assert started_s + 1500.0 < LOAD_STEP_S, f"the refit took until {started_s:.0f} s of simulated time"

            def watch_state_at(time_s: float) -> str | None:
                seen = [state for stamp, state in tracking.watch_states if stamp >= time_s]
                return seen[0] if seen else None

            tracking.until(lambda: client.now_s() >= LOAD_STEP_S - 1.0, 300.0, "the load step", nodes.check_running)
            before = [state for stamp, state in tracking.watch_states if started_s + 1000.0 <= stamp < LOAD_STEP_S]
            summary = (f"{tracking.watch_summary(started_s + 1000.0, LOAD_STEP_S)}; the longest time between two "
                       f"setpoints published {tracking.longest_gap_s:.1f} s")
            print(summary)
            assert before and set(before) == {"ok"}, f"nothing changed: the watch stays ok ({summary})"
            tracking.until(lambda: watch_state_at(LOAD_STEP_S) is not None and
                           any(state == "drift" for stamp, state in tracking.watch_states if stamp >= LOAD_STEP_S),
                           60.0, "drift", nodes.check_running)
            flagged_s = next(stamp for stamp, state in tracking.watch_states if stamp >= LOAD_STEP_S and
                             state == "drift")
            print(f"drift flagged {flagged_s - LOAD_STEP_S:.0f} s after the step; statistics by s after it: bias "
                  f"{tracking.statistic_steps('bias_statistic', LOAD_STEP_S, flagged_s + 1.0)}; path "
                  f"{tracking.statistic_steps('drift_statistic', LOAD_STEP_S, flagged_s + 1.0)}")
            assert flagged_s - LOAD_STEP_S <= 120.0, f"flagged {flagged_s - LOAD_STEP_S:.0f} s after the step"

            tracking.until(lambda: any("swap" in report for report in tracking.reports), 120.0,
                           "the refit on drift", nodes.check_running)
            swap = next(report for report in tracking.reports if "swap" in report)["swap"]
            assert swap["swapped"], swap["reason"]
            swapped_s = client.now_s()
            tracking.until(lambda: client.now_s() >= swapped_s + COMPARED_S, 60.0, "tracking after the swap",
                           nodes.check_running)
            error_before = tracking.tracking_rms_m(LOAD_STEP_S - COMPARED_S, LOAD_STEP_S)
            error_after = tracking.tracking_rms_m(swapped_s, swapped_s + COMPARED_S)
            ratio = error_after / error_before
            print(f"tracking RMS {error_before:.3g} m before the step, {error_after:.3g} m after the swap "
                  f"({ratio:.2f}x; its first 60 s {tracking.tracking_rms_m(swapped_s, swapped_s + 60.0):.3g} m); "
                  f"the longest time between two setpoints published {tracking.longest_gap_s:.1f} s")
            assert ratio <= TRACKING_RATIO, (error_before, error_after)

            in_force = client.get_parameters("compensator", ["model"])["model"]
            assert any_model_from_yaml_text(in_force).without_state() != \
                any_model_from_yaml_text(refitted).without_state(), "the refit on drift is in force"
            ok, message = client.trigger("identification/rollback", timeout_s=30.0)
            assert ok, message
            wait_for(lambda: any_model_from_yaml_text(client.get_parameters("compensator", ["model"])["model"])
                     .without_state() == any_model_from_yaml_text(refitted).without_state(), 10.0,
                     "the model before to be in force again", nodes.check_running)
            history = client.latest(String, "identification/report", REPORT_QOS)
            reasons = [entry["reason"] for entry in json.loads(history.data)["history"]]
            assert reasons[-1].startswith("~/rollback") and reasons[-2].startswith("refit on drift"), reasons
        exits = nodes.stop_all()
    assert exits == {"stage_node": 0, "compensator_node": 0, "identification_node": 0}, exits
