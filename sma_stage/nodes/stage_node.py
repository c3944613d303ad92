"""The `stage` node: applies `current_cmd` [A] to the stage (the simulator backend) and publishes
`joint_states` (stage_x position [m], velocity [m/s]) and `current_applied` (the current applied over the
step, clamped, zero while stopped or after the watchdog [A]; reliable) at rate_hz, with /diagnostics at
1 Hz.

Safety: commands are clamped to +-max_current, NaN/inf commands are refused (the last safe command
stays, but does not refresh the watchdog), the current is zeroed when no command came within
command_timeout on the steady clock, and `~/stop` zeroes it until `~/resume`.

Time: a timer ticks every 1/rate_hz wall seconds (steady clock). With use_sim_time each tick advances
the simulator by exactly time_scale/rate_hz simulated seconds, publishes /clock from the simulated time
and stamps joint_states with it. Otherwise the stamps come from the node clock and each tick advances
the simulator by the steady-clock time since the previous tick times time_scale (at most
MAX_CATCH_UP_STEPS periods), so simulated time keeps pace with the stamps when the machine is busy.
"""

from __future__ import annotations

import math
from dataclasses import fields

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import QoSProfile
from rclpy.time import Time
from rosgraph_msgs.msg import Clock as ClockMessage
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64
from std_srvs.srv import Trigger

from sma_stage.errors import InputError
from sma_stage.nodes._common import (
    COMMAND_QOS,
    JOINT_NAME,
    STATE_PUBLISH_QOS,
    Param,
    ThrottledWarnings,
    declare_all,
    exit_with,
    finite,
    quiet_on_shutdown,
    run_node,
)
from sma_stage.plant import Effects, StageConfig, StageSimulator

BACKENDS = ("sim",)
DIAGNOSTICS_PERIOD_S = 1.0

_EFFECT_UNITS = {"ambient_drift_k_per_s": "K/s", "sensor_delay_s": "s", "creep_amplitude_m": "m",
                 "creep_time_constant_s": "s", "creep_reference_m": "m", "load_change_n": "N",
                 "load_change_time_s": "s (simulated)"}


def effect_params() -> list[Param]:
    """One read-only parameter per simulator effect (Effects' fields, defaults and ranges)."""
    ranges = Effects._RANGES
    return [Param(item.name, float(item.default), f"simulator effect {item.name} [{_EFFECT_UNITS.get(item.name, '')}]",
                  *ranges[item.name], read_only=True) for item in fields(Effects)]


STAGE_PARAMS = [
    Param("backend", "sim", "stage backend: 'sim' (the embedded physics simulator)", read_only=True),
    Param("rate_hz", 50.0, "joint_states publication and simulation step rate [Hz, wall clock]", 1.0, 2000.0,
          read_only=True),
    Param("max_current", 5.0, "current limit [A]: commands are clamped to +-max_current", 0.0, 20.0),
    Param("command_timeout", 1.0, "zero the current when no command came within this time [s, steady clock]",
          0.001, 3600.0),
    Param("seed", 0, "random seed of the simulated sensor noise", 0, 2**31 - 1, read_only=True),
    Param("time_scale", 1.0, "simulated seconds per wall second", 0.001, 10000.0, read_only=True),
    *effect_params(),
]


def check_backend(name: str) -> str:
    """The backend name, refused unless it is one this node knows."""
    if name not in BACKENDS:
        raise InputError(f"parameter 'backend': unknown backend {name!r} (known: {', '.join(BACKENDS)})")
    return name


MAX_CATCH_UP_STEPS = 5


class StageNode(Node):
    """The stage: a current command in, the stage position out, with clamping and a watchdog."""

    NODE_NAME = "stage"

    def __init__(self, **node_options: object) -> None:
        super().__init__(self.NODE_NAME, **node_options)
        try:
            values = declare_all(self, STAGE_PARAMS)
            check_backend(values["backend"])
        except InputError:
            self.destroy_node()
            raise
        effects = Effects(**{item.name: values[item.name] for item in fields(Effects)})
        self.simulator = StageSimulator(StageConfig(), effects, seed=int(values["seed"]))
        self.rate_hz = float(values["rate_hz"])
        self.time_scale = float(values["time_scale"])
        self.sim_dt_s = self.time_scale / self.rate_hz
        self.use_sim_time = bool(self.get_parameter("use_sim_time").value)
        self.steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.command_a = 0.0
        self.applied_a = 0.0
        self.last_command: Time | None = None
        self.stopped = False
        self.watchdog_tripped = False
        self.published_steps = 0  # steps published: one joint_states and one current_applied each
        self.clamped_count = 0
        self.rejected_count = 0
        self.warnings = ThrottledWarnings(self)
        self.state = self.simulator.state
        self._last_tick: Time | None = None

        self.joint_pub = self.create_publisher(JointState, "joint_states", STATE_PUBLISH_QOS)
        self.applied_pub = self.create_publisher(Float64, "current_applied", COMMAND_QOS)
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.clock_pub = self.create_publisher(ClockMessage, "/clock", QoSProfile(depth=10)) \
            if self.use_sim_time else None
        self.create_subscription(Float64, "current_cmd", self.on_command, COMMAND_QOS)
        self.create_service(Trigger, "~/stop", self.on_stop)
        self.create_service(Trigger, "~/resume", self.on_resume)
        self.create_timer(1.0 / self.rate_hz, quiet_on_shutdown(self, self.on_tick), clock=self.steady)
        self.create_timer(DIAGNOSTICS_PERIOD_S, quiet_on_shutdown(self, self.publish_diagnostics), clock=self.steady)
        self.get_logger().info(f"stage ready: backend sim, {self.rate_hz:g} Hz, "
                               f"{self.sim_dt_s:g} s simulated per step, max_current {self.max_current:g} A")

    @property
    def max_current(self) -> float:
        """The current limit [A] in force (the parameter can change while running)."""
        return float(self.get_parameter("max_current").value)

    @property
    def command_timeout_s(self) -> float:
        """The watchdog timeout [s] in force."""
        return float(self.get_parameter("command_timeout").value)

    def on_command(self, message: Float64) -> None:
        """Store a command [A]: NaN/inf refused, out-of-range values clamped."""
        value = float(message.data)
        if not finite(value):
            self.rejected_count += 1
            self.warnings.warn("rejected", f"refused a non-finite current command ({value}); keeping {self.command_a:g} A")
            return
        if self.stopped:
            return
        limit = self.max_current
        clamped = min(max(value, -limit), limit)
        if clamped != value:
            self.clamped_count += 1
            self.warnings.warn("clamped", f"current command {value:g} A clamped to {clamped:g} A (max_current)")
        self.command_a = clamped
        self.last_command = self.steady.now()

    def command_age_s(self) -> float:
        """Seconds [steady clock] since the last accepted command (inf when none came)."""
        if self.last_command is None:
            return math.inf
        return (self.steady.now() - self.last_command).nanoseconds * 1e-9

    def current_to_apply(self) -> float:
        """The current [A] for this step: zero when stopped or when the command is stale."""
        stale = self.command_age_s() > self.command_timeout_s and not self.stopped  # stopped: zero for that reason
        if stale and not self.watchdog_tripped and self.last_command is not None:
            self.get_logger().warning(f"no current command for {self.command_timeout_s:g} s: current set to zero")
        self.watchdog_tripped = stale
        if self.stopped or stale:
            return 0.0
        limit = self.max_current
        return min(max(self.command_a, -limit), limit)

    def step_length_s(self) -> float:
        """Simulated seconds for this tick: a fixed step on simulated time; on wall time the steady-clock
        time since the last tick times time_scale (at most MAX_CATCH_UP_STEPS steps), so a tick that came
        late does not leave the simulation behind the stamps."""
        if self.use_sim_time:
            return self.sim_dt_s
        now = self.steady.now()
        elapsed_s = 1.0 / self.rate_hz if self._last_tick is None else (now - self._last_tick).nanoseconds * 1e-9
        self._last_tick = now
        return min(max(elapsed_s, 0.0), MAX_CATCH_UP_STEPS / self.rate_hz) * self.time_scale

    def on_tick(self) -> None:
        """Advance the simulator one step and publish current_applied and joint_states (and /clock with
        use_sim_time)."""
        self.applied_a = self.current_to_apply()
        step_s = self.step_length_s()
        if step_s > 0.0:
            self.state = self.simulator.step(self.applied_a, step_s)
        stamp = self.stamp()
        if self.clock_pub is not None:
            self.clock_pub.publish(ClockMessage(clock=stamp))
        message = JointState()
        message.header.stamp = stamp
        message.name = [JOINT_NAME]
        message.position = [self.state.measured_position_m]
        message.velocity = [self.state.velocity_m_s]
        self.applied_pub.publish(Float64(data=float(self.applied_a)))
        self.joint_pub.publish(message)
        self.published_steps += 1

    def stamp(self):
        """The time of the current state: simulated time with use_sim_time, else the node clock."""
        if self.use_sim_time:
            return Time(nanoseconds=round(self.state.time_s * 1e9)).to_msg()
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

    def close(self) -> None:
        """Say how many steps were published (a soak counts them against a bag), before the node goes."""
        self.get_logger().info(f"published {self.published_steps} steps (joint_states and current_applied)")

    def diagnostic_status(self) -> DiagnosticStatus:
        """The stage's health as one DiagnosticStatus (wires, command age, clamping, stop flag)."""
        state = self.state
        level, text = DiagnosticStatus.OK, "running"
        if self.stopped:
            level, text = DiagnosticStatus.WARN, "stopped (call ~/resume)"
        elif self.watchdog_tripped:
            level, text = DiagnosticStatus.WARN, "no recent command: current held at zero"
        values = {
            "wire_a_temperature_k": state.wire_temperatures_k[0],
            "wire_b_temperature_k": state.wire_temperatures_k[1],
            "wire_a_martensite_fraction": state.martensite_fractions[0],
            "wire_b_martensite_fraction": state.martensite_fractions[1],
            "applied_current_a": self.applied_a,
            "position_m": state.measured_position_m,
            "simulated_time_s": state.time_s,
            "command_age_s": self.command_age_s(),
            "clamped_commands": self.clamped_count,
            "rejected_commands": self.rejected_count,
            "stopped": self.stopped,
            "watchdog_tripped": self.watchdog_tripped,
            "published_steps": self.published_steps,
        }
        return DiagnosticStatus(level=level, name=f"{self.get_name()}: sim stage", message=text,
                                hardware_id="sma_stage_sim",
                                values=[KeyValue(key=key, value=str(value)) for key, value in values.items()])

    def publish_diagnostics(self) -> None:
        """Publish the status on /diagnostics."""
        array = DiagnosticArray(status=[self.diagnostic_status()])
        array.header.stamp = self.get_clock().now().to_msg()
        self.diagnostics_pub.publish(array)


def main(args: list[str] | None = None) -> None:
    """Entry point `stage_node`."""
    exit_with(run_node(StageNode, args))


if __name__ == "__main__":
    main()
