"""The `compensator` node: turns `setpoint` [m] into `current_cmd` [A] through the inverse GPI model,
optionally with a PI loop on the measured position (`joint_states`) around it.

The model comes from `model_file` (a YAML file written by GPIParameters.to_yaml) or from the parameters
a1..a11 and operators, which can be set while running: a new set is validated whole (GPIParameters and
invertibility) and refused with the reason when bad. `~/reload` reads model_file again and keeps the old
model when the file is bad.

Control law (sma_stage.control.Compensator): target = setpoint + kp e + integral(ki e dt),
e = setpoint - measured position [m] (feedback only; target = setpoint otherwise), v = inverse(target)
within +-max_current, current = v + lag_tau_s dv/dt clipped to +-max_current (a lead that undoes the
wires' thermal lag; lag_tau_s = 0: current = v). The integral and dv/dt run on the node clock (simulated
time with use_sim_time); the integral stops while the command saturates in the direction of the error
(anti-windup). A command is published on each setpoint and, once a setpoint came, every 1/rate_hz s
(which also feeds the stage's watchdog): computed again in feedback mode or with the lead on, the last one
repeated otherwise.
"""

from __future__ import annotations

import math
import threading

from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64
from std_srvs.srv import Trigger

from sma_stage.control import Compensator
from sma_stage.control.compensator import GAIN_PARAMETERS, checked_gains
from sma_stage.errors import InputError
from sma_stage.model import PARAMETER_NAMES, GPIInverseStream, GPIParameters, load_model_file
from sma_stage.model.inverse import METHODS
from sma_stage.model.parameters import MAX_OPERATORS
from sma_stage.nodes._common import (
    COMMAND_QOS,
    JOINT_NAME,
    STATE_SUBSCRIBE_QOS,
    Param,
    ThrottledWarnings,
    declare_all,
    exit_with,
    finite,
    run_node,
)

# The hand-made starting model of config/model_default.yaml (a +-0.5 mm stage); replace it by a fit.
DEFAULT_MODEL = {"a1": 0.0005, "a2": 0.6, "a3": 0.1, "a4": 0.0, "a5": 0.0005, "a6": 0.6, "a7": -0.2,
                 "a8": 5.0e-05, "a9": 5.0e-05, "a10": 0.2, "a11": 5000.0}
DEFAULT_OPERATORS = 10
MODEL_PARAMETERS = (*PARAMETER_NAMES, "operators")
REBUILD_PARAMETERS = (*MODEL_PARAMETERS, "inverse_method", "max_current")
MODEL_LIMIT = 1e12

COMPENSATOR_PARAMS = [
    Param("model_file", "", "GPI model file (YAML from GPIParameters.to_yaml or ~/refit); empty: use a1..a11"),
    *[Param(name, DEFAULT_MODEL[name], f"GPI parameter {name} (the model's eqs 4-5; output in m, input in A)",
            -MODEL_LIMIT, MODEL_LIMIT) for name in PARAMETER_NAMES],
    Param("operators", DEFAULT_OPERATORS, "number of play operators of the GPI model", 1, MAX_OPERATORS),
    Param("inverse_method", "exact", f"inverse of the model: {' or '.join(METHODS)}"),
    Param("max_current", 5.0, "current limit [A]: the inverse searches within +-max_current", 0.001, 20.0),
    Param("feedback", False, "close a PI loop on the measured position from joint_states"),
    Param("kp", 1.0, "proportional gain on the position error [m/m] (feedback mode)", 0.0, 100.0),
    Param("ki", 0.1, "integral gain on the position error [1/s of node-clock time] (feedback mode)", 0.0, 10000.0),
    Param("lag_tau_s", 0.0, "thermal lag time constant [s of node-clock time] the lead undoes; 0: no lead",
          0.0, 1000.0),
    Param("heating_reference_a", 0.0, "0: the lag acts on the current; > 0: on the Joule heating u|u|/this [A] "
          "(thermal_lag's joule_reference_a)", 0.0, 100.0),
    Param("rate_hz", 50.0, "command republication and PI loop rate [Hz]", 0.1, 2000.0, read_only=True),
    Param("joint_name", JOINT_NAME, "joint of joint_states that carries the stage position", read_only=True),
]


def build_inverse(values: dict[str, object]) -> GPIInverseStream:
    """The inverse stream for a full parameter set; InputError with the reason when it is unusable."""
    params = GPIParameters.from_dict({name: values[name] for name in PARAMETER_NAMES})
    limit = float(values["max_current"])
    return GPIInverseStream(params, int(values["operators"]), str(values["inverse_method"]), input_range=(-limit, limit))


def model_values(path: str) -> dict[str, object]:
    """a1..a11 and operators from a model file whose output is in metres (InputError otherwise)."""
    model = load_model_file(path)
    if model.parameters.output_unit != "m":
        raise InputError(f"model file {path}: output unit is '{model.parameters.output_unit}', the setpoint is in m")
    return {**model.parameters.to_dict(), "operators": model.operators}


class CompensatorNode(Node):
    """Setpoint [m] in, current command [A] out, through the inverse GPI model (and a PI loop)."""

    def __init__(self, **node_options: object) -> None:
        super().__init__("compensator", **node_options)
        self._lock = threading.RLock()
        try:
            self.values = declare_all(self, COMPENSATOR_PARAMS)
            if self.values["model_file"]:
                self.values.update(model_values(str(self.values["model_file"])))
                result = self.set_parameters_atomically([Parameter(name, value=self.values[name])
                                                         for name in MODEL_PARAMETERS])
                if not result.successful:
                    raise InputError(f"model file {self.values['model_file']}: {result.reason}")
            self.core = Compensator(build_inverse(self.values), **self.gains(self.values))
        except InputError as error:
            self.destroy_node()
            raise InputError(f"node 'compensator': {error}") from None
        self.steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.setpoint_m: float | None = None
        self.measured_m: float | None = None
        self.clipped_count = 0
        self._last_step_ns: int | None = None
        self.warnings = ThrottledWarnings(self)
        self.add_on_set_parameters_callback(self.on_set_parameters)
        self.command_pub = self.create_publisher(Float64, "current_cmd", COMMAND_QOS)
        self.create_subscription(Float64, "setpoint", self.on_setpoint, COMMAND_QOS)
        self.create_subscription(JointState, "joint_states", self.on_joint_states, STATE_SUBSCRIBE_QOS)
        self.create_service(Trigger, "~/reload", self.on_reload)
        self.period_s = 1.0 / float(self.values["rate_hz"])
        self.create_timer(self.period_s, self.on_tick, clock=self.steady)
        self.get_logger().info(f"compensator ready: {self.describe_model()}")

    @staticmethod
    def gains(values: dict[str, object]) -> dict[str, float]:
        """The control core's gains from the node's parameter values (InputError when one is unusable)."""
        return checked_gains(**{name: values[name] for name in GAIN_PARAMETERS})

    @property
    def inverse(self) -> GPIInverseStream:
        """The streaming GPI inverse in force."""
        return self.core.inverse

    @property
    def integral_m(self) -> float:
        """The PI loop's integral term [m]."""
        return self.core.integral_m

    @property
    def command_a(self) -> float:
        """The last current command [A]."""
        return self.core.command_a

    def describe_model(self) -> str:
        """One line naming the model in force."""
        source = self.values["model_file"] or "parameters a1..a11"
        return (f"{self.inverse.method} inverse of a {self.inverse.operators}-operator GPI model from {source}, "
                f"feedback {'on' if self.values['feedback'] else 'off'}")

    def on_set_parameters(self, changes: list[Parameter]) -> SetParametersResult:
        """Validate a parameter change as a whole; swap in the new inverse when the model changed."""
        candidate = {**self.values, **{change.name: change.value for change in changes}}
        rebuild = any(change.name in REBUILD_PARAMETERS for change in changes)
        try:
            inverse = build_inverse(candidate) if rebuild else None
            gains = self.gains(candidate)
        except InputError as error:
            return SetParametersResult(successful=False, reason=str(error))
        with self._lock:
            self.values = candidate
            for name, value in gains.items():
                setattr(self.core, name, value)
            if inverse is not None:
                self.core.set_inverse(inverse)
        if rebuild:
            self.get_logger().info(f"model updated: {self.describe_model()}")
        return SetParametersResult(successful=True)

    def on_reload(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Read model_file again; a bad file leaves the model in force and answers why."""
        path = str(self.values["model_file"])
        response.success, response.message = False, "parameter model_file is empty: nothing to reload"
        if path:
            try:
                values = model_values(path)
            except InputError as error:
                response.message = str(error)
            else:
                result = self.set_parameters_atomically([Parameter(name, value=values[name])
                                                         for name in MODEL_PARAMETERS])
                response.success = result.successful
                response.message = f"reloaded {path}" if result.successful else f"model file {path}: {result.reason}"
        if response.success:
            self.get_logger().info(f"~/reload: {response.message}")
        else:
            self.get_logger().warning(f"~/reload: {response.message}")
        return response

    def on_setpoint(self, message: Float64) -> None:
        """A new position setpoint [m]: answer at once with a command."""
        value = float(message.data)
        if not finite(value):
            self.warnings.warn("setpoint", f"refused a non-finite setpoint ({value})")
            return
        with self._lock:
            self.setpoint_m = value
            self.publish_command(self.compute_command(self.elapsed_s()))

    def on_joint_states(self, message: JointState) -> None:
        """Keep the latest measured position [m]."""
        names = list(message.name)
        joint = str(self.values["joint_name"])
        index = names.index(joint) if joint in names else (0 if not names else None)
        if index is not None and index < len(message.position) and math.isfinite(message.position[index]):
            self.measured_m = float(message.position[index])

    def on_tick(self) -> None:
        """Fixed-rate step: the PI and lead update (feedback, or lag_tau_s > 0) or a repeat of the command."""
        with self._lock:
            if self.setpoint_m is None:
                return
            if self.values["feedback"] or self.core.lag_tau_s > 0.0:
                self.publish_command(self.compute_command(self.elapsed_s()))
            else:
                self.publish_command(self.command_a)

    def elapsed_s(self) -> float:
        """Node-clock seconds since the previous command computed, 0 for the first (simulated time with
        use_sim_time)."""
        now_ns = self.get_clock().now().nanoseconds
        previous_ns, self._last_step_ns = self._last_step_ns, now_ns
        if previous_ns is None:
            return 0.0
        return max((now_ns - previous_ns) * 1e-9, 0.0)

    def compute_command(self, dt_s: float) -> float:
        """Current [A] for the setpoint, dt_s [s] after the previous command (PI integral, lead's rate)."""
        measured = self.measured_m if self.values["feedback"] else None
        current = self.core.command(self.setpoint_m, measured, dt_s)
        if self.inverse.last_clipped:
            self.clipped_count += 1
            self.warnings.warn("clipped", f"target {self.core.target_m:.4g} m is beyond the model's reach within "
                                  f"+-{self.values['max_current']:g} A: current at its limit")
        return current

    def publish_command(self, current_a: float) -> None:
        """Publish a current command [A]."""
        self.command_pub.publish(Float64(data=float(current_a)))


def main(args: list[str] | None = None) -> None:
    """Entry point `compensator_node`."""
    exit_with(run_node(CompensatorNode, args))


if __name__ == "__main__":
    main()
