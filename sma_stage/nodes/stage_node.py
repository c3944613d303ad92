"""The `stage` node, a managed (lifecycle) node: applies `current_cmd` [A] to the stage and publishes
`joint_states` (stage_x position [m], velocity [m/s]) and `current_applied` (the current applied over the
step: clamped, zero while stopped, inactive or after the watchdog [A]; reliable) at rate_hz, with
/diagnostics at 1 Hz.

Backends: `sim`, the embedded physics simulator, or `visa`, the stage on SCPI instruments described by
`hardware_file` (sma_stage.plant.visa; docs/hardware.md). Both go through the same lifecycle states:
configure connects (output off), activate accepts current_cmd, deactivate zeroes the current and switches
the output off (confirmed), cleanup disconnects; shutdown and errors (Ctrl-C included) switch the output off
as best they can. `autostart` takes the node to a state by itself at start (auto: active for the simulator,
inactive for instruments). A hardware fault (lost connection, timeout, garbage, an error in an
instrument's queue, a protection trip) switches the output off, sends the node to unconfigured and starts
reconnecting with back-off; a reconnect leaves it inactive: the output is never switched on by itself.

Safety: commands are clamped to +-max_current, NaN/inf commands are refused (the last safe command stays,
but does not refresh the watchdog), `~/stop` zeroes the current until `~/resume`. When no command came
within command_timeout (steady clock) the simulator's current is zeroed; on instruments the node
deactivates (output off).

`~/freeze_time` (std_srvs/SetBool, the simulator only) stops the simulated stage where it is: no steps, no
/clock, nothing published, until it is called with false (the current held resumes; the watchdog counts
from then). A long computation on a machine shared with a fast simulated stage (a refit) then has the CPU.

Time: a timer ticks every 1/rate_hz wall seconds (steady clock). With use_sim_time each tick advances the
simulator by exactly time_scale/rate_hz simulated seconds, publishes `clock` from the stage's time and
stamps joint_states with it. `clock` is relative: /clock in the root namespace, /NS/clock for a stage in
namespace NS, so that stages side by side keep their own time; the other nodes of a namespaced stage follow
it with the remapping `/clock:=clock` (launch/stage.launch.py sets it). Otherwise the stamps come from the node clock and each tick advances the
simulator by the steady-clock time since the previous tick times time_scale (at most MAX_CATCH_UP_STEPS
periods). On instruments the stage's time is the host's steady clock times time_scale (1 for a real stage; a
loopback test rig may run faster).

Lockstep (`lockstep_timeout` > 0, the simulator on use_sim_time): after publishing a state the stage does not
step until a current_cmd has come (at most lockstep_timeout wall seconds, and only while commands are coming:
a stage nobody commands runs at its pace), and the command that came acts over that step. With a controller
that answers each state (the compensator's `control_trigger: joint_states`) every command then acts over the
step that starts at the position it answers, as in a loop run in one process, however loaded the machine: the
simulated time slows down instead.
"""

from __future__ import annotations

import math

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.qos import QoSProfile
from rclpy.time import Time
from rosgraph_msgs.msg import Clock as ClockMessage
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64
from std_srvs.srv import SetBool, Trigger

from sma_stage.errors import InputError
from sma_stage.nodes._common import (
    COMMAND_QOS,
    JOINT_NAME,
    STATE_PUBLISH_QOS,
    ThrottledWarnings,
    declare_all,
    exit_with,
    finite,
    note_started,
    quiet_on_shutdown,
    run_node,
)
from sma_stage.nodes.stage_settings import AUTOSTART, STAGE_PARAMS, StageSettings, check_choice, make_hardware
from sma_stage.plant.hardware import HardwareError, Reading, wire_commands

DIAGNOSTICS_PERIOD_S = 1.0
MAX_CATCH_UP_STEPS = 5
LATE_FACTOR = 1.5  # a cycle is late when it starts more than this many periods after the previous one
FIRST_RECONNECT_S = 1.0


class CycleTiming:
    """Start-to-start intervals of the control cycle and how long its I/O took [s, steady clock]."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self.cycles = self.late = 0
        self.longest_interval_s = self.longest_io_s = 0.0
        self._last_start_ns: int | None = None

    def started(self, now_ns: int) -> None:
        """Count a cycle starting at now_ns."""
        if self._last_start_ns is not None:
            interval_s = (now_ns - self._last_start_ns) * 1e-9
            self.late += interval_s > LATE_FACTOR * self.period_s
            self.longest_interval_s = max(self.longest_interval_s, interval_s)
        self.cycles += 1
        self._last_start_ns = now_ns

    def ended(self, io_s: float) -> None:
        """Note how long the cycle's hardware I/O took."""
        self.longest_io_s = max(self.longest_io_s, io_s)

    def values(self) -> dict[str, object]:
        """Diagnostic key values."""
        return {"cycles": self.cycles, "late_cycles": self.late,
                "late_cycles_percent": round(100.0 * self.late / max(self.cycles - 1, 1), 3),
                "longest_cycle_interval_ms": round(1e3 * self.longest_interval_s, 3),
                "longest_cycle_io_ms": round(1e3 * self.longest_io_s, 3)}


class StageNode(LifecycleNode):
    """The stage: a current command in, the stage position out, with clamping, a watchdog and the lifecycle."""

    NODE_NAME = "stage"

    def __init__(self, **node_options: object) -> None:
        super().__init__(self.NODE_NAME, **node_options)
        note_started(self)
        try:
            values = StageSettings.of(declare_all(self, STAGE_PARAMS))
            self.autostart = check_choice("autostart", values.autostart, AUTOSTART)
            self.lockstep_timeout_s = check_lockstep(values.lockstep_timeout, values.backend,
                                                     bool(self.get_parameter("use_sim_time").value))
            self.hardware = make_hardware(values)
        except InputError:
            self.destroy_node()
            raise
        self.backend = self.hardware.kind
        self.rate_hz = values.rate_hz
        self.time_scale = values.time_scale
        self.sim_dt_s = self.time_scale / self.rate_hz
        self.reconnect_max_s = values.reconnect_max_interval
        self.use_sim_time = bool(self.get_parameter("use_sim_time").value)
        self.steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.lifecycle = "unconfigured"
        self.identity: dict[str, str] = {}
        self.fault: str | None = None  # the fault that stands (cleared by a successful configure)
        self.last_fault = "none"
        self.command_a = 0.0
        self.applied_a = 0.0
        self.last_command: Time | None = None
        self.stopped = False
        self.frozen = False
        self.watchdog_tripped = False
        self.published_steps = 0  # steps published: one joint_states and one current_applied each
        self.clamped_count = 0
        self.rejected_count = 0
        self._reported_counts = (0, 0)  # (clamped, rejected) at the last /diagnostics
        self.faults = 0
        self.warnings = ThrottledWarnings(self)
        self.reading: Reading | None = None
        self.answered = True  # a command came since the last state published (lockstep)
        self.lockstep_timeouts = 0  # steps taken with no command after the state before (lockstep_timeout)
        self.timing = CycleTiming(1.0 / self.rate_hz)
        self._last_tick: Time | None = None
        self._reconnect_s = FIRST_RECONNECT_S
        self._reconnect_at_ns: int | None = None  # steady time of the next reconnect attempt

        self.joint_pub = self.create_publisher(JointState, "joint_states", STATE_PUBLISH_QOS)
        self.applied_pub = self.create_publisher(Float64, "current_applied", COMMAND_QOS)
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.clock_pub = self.create_publisher(ClockMessage, "clock", QoSProfile(depth=10)) \
            if self.use_sim_time else None
        self.create_subscription(Float64, "current_cmd", self.on_command, COMMAND_QOS)
        self.create_service(Trigger, "~/stop", self.on_stop)
        self.create_service(Trigger, "~/resume", self.on_resume)
        self.create_service(SetBool, "~/freeze_time", self.on_freeze_time)
        self.create_timer(1.0 / self.rate_hz, quiet_on_shutdown(self, self.on_tick), clock=self.steady)
        self.create_timer(DIAGNOSTICS_PERIOD_S, quiet_on_shutdown(self, self.publish_diagnostics), clock=self.steady)
        self.get_logger().info(f"stage ready: backend {self.backend}, {self.rate_hz:g} Hz, "
                               f"max_current {self.max_current:g} A, autostart {self.autostart}")
        try:
            self.start()
        except BaseException:  # Ctrl-C/SIGTERM during a long start: the output off before the interrupt goes on
            self.close()
            self.destroy_node()
            raise

    def start(self) -> None:
        """Go to the autostart state: configure (connect), then activate for the simulator or when asked."""
        target = self.autostart if self.autostart != "auto" else ("active" if self.backend == "sim" else "inactive")
        if target == "unconfigured":
            return
        if self.trigger_configure() != TransitionCallbackReturn.SUCCESS:
            self._schedule_reconnect()
            return
        if target == "active":
            self.trigger_activate()

    @property
    def max_current(self) -> float:
        """The current limit [A] in force (the parameter can change while running)."""
        return float(self.get_parameter("max_current").value)

    @property
    def command_timeout_s(self) -> float:
        """The watchdog timeout [s] in force."""
        return float(self.get_parameter("command_timeout").value)

    # -- lifecycle --------------------------------------------------------------------------------------
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Connect and set the hardware up with the output off."""
        try:
            self.identity = self.hardware.connect()
        except HardwareError as error:
            self.fault = self.last_fault = str(error)
            self.get_logger().error(f"configure failed, output off: {error}")
            return TransitionCallbackReturn.FAILURE
        self.fault = None
        self._reconnect_at_ns = None
        self._last_tick = None
        self.lifecycle = "inactive"
        self.get_logger().info("configured, output off: " + "; ".join(f"{k}: {v}" for k, v in self.identity.items()))
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Switch the output on at zero current and accept current_cmd."""
        try:
            self.hardware.enable()
        except HardwareError as error:
            self.fault = str(error)
            self.get_logger().error(f"activate failed: {error}")
            return TransitionCallbackReturn.ERROR
        self.command_a, self.last_command, self.watchdog_tripped = 0.0, None, False
        self.lifecycle = "active"
        self.get_logger().info("active: accepting current_cmd")
        return super().on_activate(state)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Zero the current, output off, relay open, confirmed by reading back."""
        self.lifecycle = "deactivating"
        self.command_a = self.applied_a = 0.0
        if not self._stop_hardware() or self.fault:
            return TransitionCallbackReturn.ERROR
        self.lifecycle = "inactive"
        self.get_logger().info("inactive: current zero, output off (confirmed)")
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Disconnect."""
        self._disconnect()
        self.get_logger().info("unconfigured: disconnected")
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Output off (best effort) and disconnect."""
        self._stop_hardware()
        self._disconnect()
        self._reconnect_at_ns = None
        self.lifecycle = "finalized"
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        """After a failed transition or a fault: output off (best effort), disconnect, reconnect later."""
        self._stop_hardware()
        self._disconnect()
        self.get_logger().error(f"unconfigured after an error: {self.fault or 'a transition failed'}; "
                                "the output was switched off")
        self._schedule_reconnect()
        return TransitionCallbackReturn.SUCCESS

    def _stop_hardware(self) -> bool:
        """Zero current and output off, confirmed; False (and the fault noted) when it is not."""
        try:
            self.hardware.stop()
        except HardwareError as error:
            self.fault = self.fault or str(error)
            self.get_logger().error(f"switching the output off: {error}")
            return False
        return True

    def _disconnect(self) -> None:
        self.hardware.close()
        self.lifecycle = "unconfigured"

    def on_fault(self, reason: str) -> None:
        """A hardware fault in a cycle: output off, to unconfigured (through error processing), reconnect."""
        self.fault, self.last_fault, self.faults = reason, reason, self.faults + 1
        self.get_logger().error(f"hardware fault: {reason}; switching the output off")
        if self.lifecycle == "active":
            self.trigger_deactivate()  # on_deactivate returns ERROR while a fault stands: on to on_error
        elif self.lifecycle == "inactive":
            self._stop_hardware()
            self.trigger_cleanup()
            self._schedule_reconnect()

    def _schedule_reconnect(self) -> None:
        if self.reconnect_max_s <= 0.0 or self._reconnect_at_ns is not None or self.lifecycle == "finalized":
            return
        self.get_logger().warning(f"reconnecting in {self._reconnect_s:g} s (the output stays off)")
        self._reconnect_at_ns = self.steady.now().nanoseconds + int(self._reconnect_s * 1e9)

    def _reconnect_when_due(self) -> None:
        """While unconfigured after a fault: try to configure when the back-off has passed (never activates)."""
        if self._reconnect_at_ns is None or self.steady.now().nanoseconds < self._reconnect_at_ns:
            return
        self._reconnect_at_ns = None
        if self.trigger_configure() == TransitionCallbackReturn.SUCCESS:
            self._reconnect_s = FIRST_RECONNECT_S
            self.get_logger().warning("reconnected; inactive with the output off until activated")
            return
        self._reconnect_s = min(2.0 * self._reconnect_s, self.reconnect_max_s)
        self._schedule_reconnect()

    # -- commands -----------------------------------------------------------------------------------------
    def on_command(self, message: Float64) -> None:
        """Store a command [A]: NaN/inf refused, out-of-range values clamped; ignored unless active."""
        value = float(message.data)
        if not finite(value):
            self.rejected_count += 1
            self.warnings.warn("rejected", f"refused a non-finite current command ({value}); keeping {self.command_a:g} A")
            return
        if self.stopped or self.lifecycle != "active":
            if self.lifecycle != "active":
                self.warnings.warn("inactive", f"current command ignored: the stage is {self.lifecycle}")
            return
        limit = self.max_current
        clamped = min(max(value, -limit), limit)
        if clamped != value:
            self.clamped_count += 1
            self.warnings.warn("clamped", f"current command {value:g} A clamped to {clamped:g} A (max_current)")
        self.command_a = clamped
        self.last_command = self.steady.now()
        self.answered = True

    def command_age_s(self) -> float:
        """Seconds [steady clock] since the last accepted command (inf when none came)."""
        if self.last_command is None:
            return math.inf
        return (self.steady.now() - self.last_command).nanoseconds * 1e-9

    def current_to_apply(self) -> float:
        """The current [A] for this step: zero unless active, when stopped or when the command is stale."""
        if self.lifecycle != "active":
            return 0.0
        stale = self.command_age_s() > self.command_timeout_s and not self.stopped  # stopped: zero for that reason
        if stale and not self.watchdog_tripped and self.last_command is not None:
            self.get_logger().warning(f"no current command for {self.command_timeout_s:g} s: current set to zero")
        self.watchdog_tripped = stale
        if self.stopped or stale:
            return 0.0
        limit = self.max_current
        return min(max(self.command_a, -limit), limit)

    def step_length_s(self) -> float:
        """Stage seconds for this tick: a fixed step on simulated time; on wall time the steady-clock time since
        the last tick times time_scale (at most MAX_CATCH_UP_STEPS steps), so a tick that came late does not
        leave the simulation behind the stamps."""
        if self.use_sim_time:
            return self.sim_dt_s
        now = self.steady.now()
        elapsed_s = 1.0 / self.rate_hz if self._last_tick is None else (now - self._last_tick).nanoseconds * 1e-9
        self._last_tick = now
        return min(max(elapsed_s, 0.0), MAX_CATCH_UP_STEPS / self.rate_hz) * self.time_scale

    def on_tick(self) -> None:
        """One cycle, in ros2_control's order: read the stage (the position at the end of the last period and
        the current applied over it), publish joint_states and current_applied (and /clock with
        use_sim_time), then write the current for the next period (in lockstep the command that came is written
first, so that it acts over this step). A hardware fault switches the output off.
        Unconfigured: reconnect when due."""
        if self.lifecycle not in ("active", "inactive"):
            self._reconnect_when_due()
            return
        if self.frozen or self.awaiting_command():
            return
        start_ns = self.steady.now().nanoseconds
        self.timing.started(start_ns)
        try:
            if self.lockstep_timeout_s:  # the command answering the last state acts over this step
                self.hardware.write(wire_commands(self.current_to_apply()))
            self.reading = self.hardware.read(self.step_length_s())
            self.publish_reading()
            current_a = self.current_to_apply()
            if self.watchdog_tripped and self.last_command is not None and self.backend != "sim" \
                    and self.lifecycle == "active":
                self.get_logger().warning("deactivating: no current command within command_timeout")
                self.trigger_deactivate()
                return
            self.hardware.write(wire_commands(current_a))
        except HardwareError as error:
            self.on_fault(str(error))
            return
        self.timing.ended((self.steady.now().nanoseconds - start_ns) * 1e-9)

    def awaiting_command(self) -> bool:
        """Lockstep: True while no command has come since the last state published, commands are coming, and the
        wait has lasted less than lockstep_timeout (a wait that ran out is counted in lockstep_timeouts)."""
        if not self.lockstep_timeout_s or self.answered or self.lifecycle != "active" or self.stopped \
                or self.command_age_s() > self.command_timeout_s:
            return False
        if (self.steady.now() - self._published_at).nanoseconds * 1e-9 < self.lockstep_timeout_s:
            return True
        self.lockstep_timeouts += 1
        return False

    def publish_reading(self) -> None:
        """Publish the last reading: /clock (with use_sim_time), current_applied, joint_states (the position and,
        as effort, the current applied over the period that ended at it, under one stamp)."""
        self.applied_a = self.reading.current_a
        stamp = self.stamp()
        if self.clock_pub is not None:
            self.clock_pub.publish(ClockMessage(clock=stamp))
        message = JointState()
        message.header.stamp = stamp
        message.name = [JOINT_NAME]
        message.position = [self.reading.position_m]
        message.velocity = [self.reading.states["stage/velocity"]]
        message.effort = [float(self.applied_a)]  # the heating current [A] applied over the period, + wire a
        self.applied_pub.publish(Float64(data=float(self.applied_a)))
        self.answered = False
        self._published_at = self.steady.now()
        self.joint_pub.publish(message)
        self.published_steps += 1

    def stamp(self):
        """The time of the current state: the stage's time with use_sim_time, else when the instruments were read
        (the SCPI bridge), else the node clock."""
        if self.use_sim_time:
            return Time(nanoseconds=round(self.reading.time_s * 1e9)).to_msg()
        if self.reading.read_ns is not None:
            return Time(nanoseconds=self.reading.read_ns).to_msg()
        return self.get_clock().now().to_msg()

    def on_stop(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Zero the current and ignore commands until ~/resume."""
        self.stopped = True
        self.command_a = 0.0
        response.success = True
        response.message = "stopped: current is zero until ~/resume"
        self.get_logger().warning(response.message)
        return response

    def on_resume(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Accept commands again (the current stays zero until a new command arrives)."""
        was_stopped, self.stopped = self.stopped, False
        self.command_a = 0.0
        self.last_command = None
        response.success = True
        response.message = "resumed: waiting for a new command" if was_stopped else "was not stopped"
        self.get_logger().info(response.message)
        return response

    def on_freeze_time(self, request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        """Freeze (data true) or run on (false) the simulated stage; refused on instruments, whose time runs."""
        if self.backend != "sim":
            response.success = False
            response.message = f"the {self.backend} stage's time cannot be frozen: only the simulator's"
            return response
        was_frozen, self.frozen = self.frozen, bool(request.data)
        if was_frozen and not self.frozen:
            self._last_tick = None
            if self.last_command is not None:
                self.last_command = self.steady.now()
        response.success = True
        response.message = ("simulated time frozen: no steps until ~/freeze_time false" if self.frozen
                            else "simulated time runs" + ("" if was_frozen else " (was not frozen)"))
        self.get_logger().info(response.message)
        return response

    def close(self) -> None:
        """At exit (Ctrl-C, SIGTERM): output off as far as possible, disconnect, and say how many steps were
        published (a soak counts them against a bag)."""
        self._reconnect_at_ns = None
        if self.lifecycle in ("active", "inactive"):
            if self._stop_hardware():
                self.get_logger().info("output off (confirmed)")
            self._disconnect()
        self.get_logger().info(f"published {self.published_steps} steps (joint_states and current_applied)")

    def diagnostic_status(self) -> DiagnosticStatus:
        """The stage's health as one DiagnosticStatus (lifecycle, hardware, command age, cycle timing): ERROR on a
        fault; WARN while stopped or frozen, or when commands were clamped or refused since the last status; OK
        running or idle (no recent command, the current at zero)."""
        clamped = self.clamped_count - self._reported_counts[0]
        rejected = self.rejected_count - self._reported_counts[1]
        level, text = DiagnosticStatus.OK, self.lifecycle
        if self.fault:
            level, text = DiagnosticStatus.ERROR, f"{self.lifecycle}: {self.fault}"
        elif self.stopped:
            level, text = DiagnosticStatus.WARN, "stopped (call ~/resume)"
        elif self.frozen:
            level, text = DiagnosticStatus.WARN, "simulated time frozen (call ~/freeze_time false)"
        elif clamped or rejected:
            level = DiagnosticStatus.WARN
            text = (f"{clamped} commands clamped to +-{self.max_current:g} A" if clamped else
                    f"{rejected} non-finite commands refused") + " since the last status"
        elif self.watchdog_tripped:
            text = "idle: no recent command, current at zero"
        elif self.lifecycle == "active":
            text = "running"
        values = {
            "lifecycle_state": self.lifecycle,
            **self.hardware.status(),
            "applied_current_a": self.applied_a,
            "position_m": self.reading.position_m if self.reading is not None else "none",
            "stage_time_s": self.reading.time_s if self.reading is not None else "none",
            "command_age_s": self.command_age_s(),
            "clamped_commands": self.clamped_count,
            "rejected_commands": self.rejected_count,
            "stopped": self.stopped,
            "frozen": self.frozen,
            "watchdog_tripped": self.watchdog_tripped,
            "faults": self.faults,
            "last_fault": self.last_fault,
            "published_steps": self.published_steps,
            "lockstep_timeouts": self.lockstep_timeouts,
            **self.timing.values(),
        }
        hardware_id = "; ".join(self.identity.values()) or f"sma_stage {self.backend}"
        return DiagnosticStatus(level=level, name=f"{self.get_fully_qualified_name()}: {self.backend} stage", message=text,
                                hardware_id=hardware_id,
                                values=[KeyValue(key=key, value=str(value)) for key, value in values.items()])

    def publish_diagnostics(self) -> None:
        """Publish the status on /diagnostics."""
        array = DiagnosticArray(status=[self.diagnostic_status()])
        self._reported_counts = (self.clamped_count, self.rejected_count)
        array.header.stamp = self.get_clock().now().to_msg()
        self.diagnostics_pub.publish(array)


def check_lockstep(timeout_s: float, backend: str, use_sim_time: bool) -> float:
    """lockstep_timeout [s], refused (InputError) unless the stage is the simulator on use_sim_time."""
    if timeout_s and (backend != "sim" or not use_sim_time):
        raise InputError("parameter 'lockstep_timeout': lockstep needs the simulator (backend sim) on use_sim_time; "
                         "set it to 0 here")
    return timeout_s


def main(args: list[str] | None = None) -> None:
    """Entry point `stage_node`."""
    exit_with(run_node(StageNode, args))


if __name__ == "__main__":
    main()
