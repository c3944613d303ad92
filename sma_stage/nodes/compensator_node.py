"""The `compensator` node: turns `setpoint` [m] into `current_cmd` [A] through the inverse of the
identified model (sma_stage.control.Compensator), optionally with a PI loop on the measured position
(`joint_states`) around it. `setpoint_stamped` (sensor_msgs/JointState, the position of joint_name) takes
setpoints that act from their header stamp on: a generator may send them ahead, and each acts at the first
control step at or after its time however the transport delays it.

The model in force is the last one given: `model_file` (a model file from `gpi_tool fit/diagnose` or
`~/refit`; read at start, when the parameter changes and on `~/reload`) or `model` (the whole model as
the same YAML text, what `~/refit` pushes in one atomic change); with both empty, the shipped
config/model_default.yaml. A new model is checked whole and refused whole (the old one stays in force).

Control law: target = setpoint + kp e + integral(ki e dt), e = setpoint - measured position [m]
(feedback only, the default; target = setpoint otherwise), through a play of half-width deadband; the
model's inverse gives the current, with the lead that undoes a thermal lag (its gain at most
lead_limit in the loop; without it feedforward_lead_limit while the setpoint moves and
feedforward_step_lead_limit after a step) and the drift's offset taken off, rate-limited to max_current_rate (see
sma_stage.control.compensator). With tuning `imc` (the default) kp and ki are derived from the model in
force (its lag, lead_limit, the control period 1/rate_hz and the time max_current_rate takes to move the
current over half of max_current: control.compensator.imc_gains) and follow every new model; with `manual` the kp and ki parameters are used. The integral
and the lead run on the node clock (simulated time with use_sim_time); the integral stops while the
command saturates in the direction of the error (anti-windup). With setpoints stamped ahead and `preview` (the default), the inverse
is driven towards the setpoint due the lag the lead leaves later (Compensator.preview_s: tau / lead_limit),
the loop's error against the setpoint now. With `learning_period` (a setpoint that repeats with that period) and
feedback, a correction learnt from the errors of the periods before is added to the setpoint
(Compensator.learning_period_s; /diagnostics says how it goes). A command is published on each setpoint
and, once a setpoint came, every 1/rate_hz s (which also feeds the stage's watchdog): computed again in
feedback mode or with a lag or drift in the model, the last one repeated otherwise. The control period
1/rate_hz is counted on the node clock with use_sim_time (simulated seconds: the loop acts on the period
a real stage would have, however fast the simulation runs), else on the steady clock. Every time the control
law sees is stage time: simulated seconds with use_sim_time, else node-clock seconds times `time_scale` (the
stage's time_scale when a simulated stage runs faster than the wall clock without use_sim_time: the model's
time constants are the stage's).

Health: /diagnostics at 1 Hz (steady clock); WARN, and a warning in the log, when feedback is on and
joint_states never came (the command is then the model's alone) or is older than measurement_timeout (the
command is held), or when targets were beyond the model's reach.
"""

from __future__ import annotations

import bisect
import math
import threading

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.time import Time
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64, String
from std_srvs.srv import Trigger

from sma_stage.control import Compensator
from sma_stage.control.compensator import (
    DEFAULT_DEADBAND_M,
    DEFAULT_FEEDFORWARD_LEAD_LIMIT,
    DEFAULT_FEEDFORWARD_STEP_LEAD_LIMIT,
    DEFAULT_LEAD_LIMIT,
    DEFAULT_MAX_RATE_A_PER_S,
    checked_gains,
    imc_gains,
    slew_time_s,
)
from sma_stage.control.learning import checked_period_s
from sma_stage.errors import InputError
from sma_stage.io.rosbag_io import joint_index
from sma_stage.model.inverse import METHODS
from sma_stage.model.kinds import AnyModel, any_model_from_yaml_text, load_any_model_file
from sma_stage.nodes._common import (
    COMMAND_QOS,
    JOINT_NAME,
    REPORT_QOS,
    STATE_SUBSCRIBE_QOS,
    Param,
    ThrottledWarnings,
    declare_all,
    exit_with,
    finite,
    note_started,
    quiet_on_shutdown,
    run_node,
    settings_type,
)
from sma_stage.nodes.launch import DEFAULT_MODEL_FILE
from sma_stage.nodes.model_watch import model_message

MODEL_SOURCES = ("model_file", "model")
REBUILD_PARAMETERS = (*MODEL_SOURCES, "inverse_method", "max_current")
TUNINGS = ("imc", "manual")
PERIOD_SMOOTHING = 0.1  # weight of a new interval in the running mean of the control period
PERIOD_TOLERANCE = 0.2  # the imc gains are derived again when the period moved by more than this fraction
PERIOD_LOG_INTERVAL_S = 60.0  # .. and logged at most once in this many wall s: at a simulated stage's 40-50x the
# period swings from 0.1 to 0.45 s between ticks and was logged 1,500 times in a two-minute demo

DIAGNOSTICS_PERIOD_S = 1.0

COMPENSATOR_PARAMS = [
    Param("model_file", "", "model file (YAML from gpi_tool fit/diagnose or ~/refit); empty: the shipped default "
          "model unless `model` is set"),
    Param("model", "", "the whole identified model as model-file YAML text (what ~/refit pushes); empty: none"),
    Param("inverse_method", "exact", f"inverse of the model's GPI: {' or '.join(METHODS)}"),
    Param("max_current", 5.0, "current limit [A]: the inverse searches within +-max_current", 0.001, 20.0),
    Param("enabled", True, "publish current_cmd; false: silent, another node owns the stage's command (the "
          "identification node sets it while ~/excite drives the stage); a new setpoint is awaited when set true"),
    Param("feedback", True, "close a PI loop on the measured position from joint_states"),
    Param("tuning", "imc", "PI gains: 'imc' (derived from the model in force and rate_hz) or 'manual' (kp, ki)"),
    Param("kp", 1.0, "proportional gain on the position error [m/m] (tuning manual)", 0.0, 100.0),
    Param("ki", 0.1, "integral gain on the position error [1/s of stage time] (tuning manual)", 0.0, 10000.0),
    Param("lead_limit", DEFAULT_LEAD_LIMIT, "largest gain of the thermal-lag lead in the PI loop [A/A]", 1.0, 1e6),
    Param("feedforward_lead_limit", DEFAULT_FEEDFORWARD_LEAD_LIMIT, "largest gain of the thermal-lag lead in "
          "feedforward (feedback false) while the setpoint moves continuously [A/A]", 1.0, 1e6),
    Param("feedforward_step_lead_limit", DEFAULT_FEEDFORWARD_STEP_LEAD_LIMIT, "the same after a step of the "
          "setpoint and while it holds [A/A] (1: no overshoot of the current)", 1.0, 1e6),
    Param("deadband", DEFAULT_DEADBAND_M, "half-width of the play on the loop's target [m] (a few sensor noise "
          "sigmas)", 0.0, 1e-2),
    Param("max_current_rate", DEFAULT_MAX_RATE_A_PER_S, "largest change of the current [A/s of stage time]; a "
          "switch of the relay crosses the model's dead band (the currents near 0 A where no wire moves the stage) "
          "at once, and so does a held or stepped setpoint's current within it; 0: no limit",
          0.0, 1e6),
    Param("measurement_timeout", 1.0, "feedback: hold current_cmd while the latest joint_states is older than this "
          "[s, steady clock] (the stage stopped publishing)", 0.001, 3600.0),
    Param("rate_hz", 50.0, "command republication and PI loop rate [Hz; of simulated time with use_sim_time]", 0.1, 2000.0, read_only=True),
    Param("time_scale", 1.0, "stage seconds per node-clock second: the stage's time_scale when it runs faster than "
          "the wall clock without use_sim_time (not applied with use_sim_time); the model, the lead, the PI loop "
          "and the rate limit count stage seconds", 0.001, 10000.0, read_only=True),
    Param("joint_name", JOINT_NAME, "joint of joint_states that carries the stage position", read_only=True),
    Param("preview", True, "with setpoints stamped ahead (setpoint_stamped), drive the inverse towards the one due "
          "the lag the lead leaves later (Compensator.preview_s), the loop's error against the setpoint now; false: "
          "the setpoint now only"),
    Param("learning_period", 0.0, "the setpoint repeats with this period [s of stage time]: with feedback, a correction "
          "learnt from each period's error is added to the next (iterative learning; it begins when the setpoint first "
          "moves after this or the model changed, or enabled turned true); 0: off", 0.0, 1e6),
    Param("control_trigger", "timer", "when the loop computes a command: 'timer' (rate_hz, and at once on a new "
          "setpoint) or 'joint_states' (once for each position the stage publishes, at its stamp: the loop in step "
          "with the stage, as a simulated stage many times faster than the wall clock needs)", read_only=True),
]
TRIGGERS = ("timer", "joint_states")
CompensatorSettings = settings_type("CompensatorSettings", COMPENSATOR_PARAMS)


def model_from(values: CompensatorSettings, changed: str | None = None) -> tuple[AnyModel, str]:
    """(the model the parameter values name, a one-line description of where it came from): `changed`
    (a model source just set) first, else model, else model_file, else the shipped default."""
    order = [changed] if changed in MODEL_SOURCES and getattr(values, changed) else []
    order += [name for name in ("model", "model_file") if getattr(values, name) and name not in order]
    source = order[0] if order else None
    if source == "model":
        try:
            return any_model_from_yaml_text(values.model), "the pushed model"
        except InputError as error:
            raise InputError(f"parameter model: {error}") from None
    path = values.model_file if source == "model_file" else str(DEFAULT_MODEL_FILE)
    return load_any_model_file(path), path


MAX_SCHEDULED = 10_000  # stamped setpoints kept ahead of their time (the earliest dropped beyond)


def loop_settings(model: AnyModel, values: CompensatorSettings, period_s: float) -> dict[str, float]:
    """The control core's loop settings from the node's parameter values, the model and the control period [s of
    stage time] (InputError when one is unusable): kp and ki (derived or manual), lead limits, deadband, rate
    limit, learning period."""
    if values.tuning not in TUNINGS:
        raise InputError(f"tuning must be one of {', '.join(TUNINGS)}, got {values.tuning!r}")
    if values.tuning == "imc":
        gains = imc_gains(model, period_s, values.lead_limit, slew_time_s(values.max_current, values.max_current_rate))
    else:
        gains = checked_gains(values.kp, values.ki)
    return {**gains, "lead_limit": values.lead_limit,
            "feedforward_lead_limit": values.feedforward_lead_limit,
            "feedforward_step_lead_limit": values.feedforward_step_lead_limit,
            "deadband_m": values.deadband,
            "max_rate_a_per_s": values.max_current_rate,
            "learning_period_s": checked_period_s(values.learning_period, name="learning_period")}


def unexpected(error: Exception) -> str:
    """One line for an error no check foresaw while taking a new model (the model in force stays)."""
    return f"model refused after an unexpected {type(error).__name__}: {' '.join(str(error).split())[:200]}"


class CompensatorNode(Node):
    """Setpoint [m] in, current command [A] out, through the identified model's inverse (and a PI loop)."""

    NODE_NAME = "compensator"

    def __init__(self, **node_options: object) -> None:
        super().__init__(self.NODE_NAME, **node_options)
        note_started(self)
        self._lock = threading.RLock()
        try:
            self.settings = CompensatorSettings.of(declare_all(self, COMPENSATOR_PARAMS))
            # with use_sim_time the node clock is the stage's: time_scale (shared with the stage in
            # stage_and_compensator) is not applied
            self.time_scale = 1.0 if self.get_parameter("use_sim_time").value else self.settings.time_scale
            self.period_estimate_s = self.tuned_period_s = self.time_scale / self.settings.rate_hz
            if self.settings.control_trigger not in TRIGGERS:
                raise InputError(f"control_trigger must be one of {', '.join(TRIGGERS)}, "
                                 f"got {self.settings.control_trigger!r}")
            model, self.model_source = model_from(self.settings)
            self.core = self.build_core(model, self.settings)
        except InputError:
            self.destroy_node()
            raise
        self.steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.setpoint_m: float | None = None
        self.scheduled: list[tuple[int, float]] = []  # stamped setpoints not yet due: (stamp [ns], position [m])
        self.measured_m: float | None = None
        self._measured_at: Time | None = None
        self.clipped_count = 0
        self._last_step_ns: int | None = None
        self._last_applied_ns: int | None = None
        self._last_tick_ns: int | None = None
        self.warnings = ThrottledWarnings(self)
        self.add_on_set_parameters_callback(self.on_set_parameters)
        self.command_pub = self.create_publisher(Float64, "current_cmd", COMMAND_QOS)
        self.create_subscription(Float64, "setpoint", self.on_setpoint, COMMAND_QOS)
        self.create_subscription(JointState, "setpoint_stamped", self.on_setpoint_stamped, COMMAND_QOS)
        self.create_subscription(JointState, "joint_states", self.on_joint_states, STATE_SUBSCRIBE_QOS)
        self.create_subscription(Float64, "current_applied", self.on_current_applied, COMMAND_QOS)
        self.create_service(Trigger, "~/reload", self.on_reload)
        self.model_pub = self.create_publisher(String, "~/model", REPORT_QOS)
        self.publish_model()
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._reported_clipped = 0
        self.create_timer(DIAGNOSTICS_PERIOD_S, quiet_on_shutdown(self, self.publish_diagnostics), clock=self.steady)
        self.period_s = 1.0 / self.settings.rate_hz
        if self.settings.control_trigger == "timer":
            self.create_timer(self.period_s, quiet_on_shutdown(self, self.on_tick), clock=self.control_clock())
        self.get_logger().info(f"compensator ready: {self.describe_model()}")

    def build_core(self, model: AnyModel, values: CompensatorSettings) -> Compensator:
        """A control core for the model with the node's settings (InputError when either is unusable)."""
        return Compensator(model, values.max_current, values.inverse_method,
                           **loop_settings(model, values, self.tuned_period_s))

    @property
    def model(self) -> AnyModel:
        """The identified model in force."""
        return self.core.model

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
        loop = (f"PI kp {self.core.kp:.3g} ki {self.core.ki:.3g}/s ({self.settings.tuning})"
                if self.settings.feedback else "feedforward")
        return f"{self.core.drive.describe()} from {self.model_source}, {loop}"

    def on_set_parameters(self, changes: list[Parameter]) -> SetParametersResult:
        """Validate a parameter change as a whole; swap in the new model when it changed."""
        candidate = self.settings.changed({change.name: change.value for change in changes})
        names = {change.name for change in changes}
        rebuild = bool(names & set(REBUILD_PARAMETERS))
        try:
            if rebuild:
                changed = next((name for name in MODEL_SOURCES if name in names), None)
                model, source = model_from(candidate, changed)
                core = self.build_core(model, candidate)
            else:
                loop = loop_settings(self.model, candidate, self.tuned_period_s)
        except InputError as error:
            return SetParametersResult(successful=False, reason=str(error))
        except Exception as error:  # noqa: BLE001 -- a bug met by a new model is a refusal, not a dead node
            return SetParametersResult(successful=False, reason=unexpected(error))
        with self._lock:
            if candidate.enabled != self.settings.enabled:
                self.setpoint_m = None
                self.scheduled.clear()
                self.core.reset()
            self.settings = candidate
            if rebuild:
                self.swap_core(core)
                self.model_source = source
                self.publish_model()
            else:
                for name, value in loop.items():
                    setattr(self.core, name, value)
        if rebuild:
            self.get_logger().info(f"model updated: {self.describe_model()}")
        return SetParametersResult(successful=True)

    def on_reload(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Read model_file again; a bad file leaves the model in force and answers why."""
        path = self.settings.model_file
        response.success, response.message = False, "parameter model_file is empty: nothing to reload"
        if path:
            try:
                core = self.build_core(load_any_model_file(path), self.settings)
            except InputError as error:
                response.message = str(error)
            except Exception as error:  # noqa: BLE001 -- as in on_set_parameters
                response.message = unexpected(error)
            else:
                with self._lock:
                    self.swap_core(core)
                    self.model_source = path
                self.publish_model()
                response.success, response.message = True, f"reloaded {path}"
        if response.success:
            self.get_logger().info(f"~/reload: {response.message}")
        else:
            self.get_logger().warning(f"~/reload: {response.message}")
        return response

    def swap_core(self, core: Compensator) -> None:
        """Put a new core in force (call with the lock held): while commanding, bumplessly (its loop continues the
        old one's: the current moves from the last command at most max_current_rate)."""
        if self.setpoint_m is not None and self.settings.enabled:
            core.continue_from(self.core)
        self.core = core

    def on_setpoint(self, message: Float64) -> None:
        """A new position setpoint [m]: answer at once with a command (with control_trigger timer; else the next
        joint_states does)."""
        value = float(message.data)
        if not finite(value):
            self.warnings.warn("setpoint", f"refused a non-finite setpoint ({value})")
            return
        with self._lock:
            if not self.takes_setpoints():
                return
            self.setpoint_m = value
            if self.settings.control_trigger == "timer":
                self.publish_command(self.compute_command(self.elapsed_s()))

    def on_setpoint_stamped(self, message: JointState) -> None:
        """A position setpoint [m] of joint_name that acts from its header stamp on (node clock): the first step of
        the loop at or after the stamp takes it, however early or late the message came."""
        index = joint_index(message, self.settings.joint_name)
        if index is None or not math.isfinite(message.position[index]):
            self.warnings.warn("setpoint", f"refused a stamped setpoint without a finite position of "
                               f"{self.settings.joint_name}")
            return
        with self._lock:
            if not self.takes_setpoints():
                return
            bisect.insort(self.scheduled, (Time.from_msg(message.header.stamp).nanoseconds,
                                           float(message.position[index])))
            del self.scheduled[:-MAX_SCHEDULED]

    def takes_setpoints(self) -> bool:
        """Whether a setpoint is taken now: not while enabled is false (said, at most once a while)."""
        if not self.settings.enabled:
            self.warnings.warn("disabled", "setpoint ignored: enabled is false (another node owns current_cmd)")
        return self.settings.enabled

    def take_due_setpoint(self, now_ns: int) -> None:
        """The latest stamped setpoint due at now_ns [ns] becomes the setpoint; those before it are dropped."""
        due = bisect.bisect_right(self.scheduled, (now_ns, math.inf))
        if due:
            self.setpoint_m = self.scheduled[due - 1][1]
            del self.scheduled[:due]

    def on_current_applied(self, message: Float64) -> None:
        """The current [A] the stage applied over its last step: while this node does not command the stage
        (no setpoint, or enabled false), the model's states follow it (Compensator.follow_applied)."""
        value = float(message.data)
        with self._lock:
            now_ns = self.get_clock().now().nanoseconds
            previous_ns, self._last_applied_ns = self._last_applied_ns, now_ns
            if self.setpoint_m is not None and self.settings.enabled or not math.isfinite(value):
                return
            dt_s = max((now_ns - previous_ns) * 1e-9, 0.0) * self.time_scale if previous_ns is not None else 0.0
            self.core.follow_applied(value, dt_s)
            self._last_step_ns = now_ns

    def on_joint_states(self, message: JointState) -> None:
        """Keep the latest measured position [m]; with control_trigger joint_states, step the loop at its stamp."""
        index = joint_index(message, self.settings.joint_name)
        if index is None or not math.isfinite(message.position[index]):
            return
        self.measured_m = float(message.position[index])
        self._measured_at = self.steady.now()
        if self.settings.control_trigger == "joint_states":
            self.step_control(Time.from_msg(message.header.stamp).nanoseconds)

    def control_clock(self) -> Clock:
        """The clock the control period runs on: the node clock with use_sim_time (1/rate_hz simulated s,
        whatever the simulation's pace), else the steady clock."""
        return self.get_clock() if self.get_parameter("use_sim_time").value else self.steady

    def on_tick(self) -> None:
        """Fixed-rate step (control_trigger timer)."""
        self.step_control(self.get_clock().now().nanoseconds)

    def step_control(self, now_ns: int) -> None:
        """One step of the loop at now_ns [ns of the node clock, or a joint_states stamp]: the PI, lead and drift
        update (feedback, or a lag or drift in the model) or a repeat of the command."""
        with self._lock:
            previous_ns, self._last_tick_ns = self._last_tick_ns, now_ns
            if previous_ns is not None and now_ns > previous_ns:
                self.follow_control_period((now_ns - previous_ns) * 1e-9 * self.time_scale)
            self.take_due_setpoint(now_ns)
            if self.setpoint_m is None or not self.settings.enabled:
                return
            if self.settings.feedback or self.core.drive.evolves:
                self.publish_command(self.compute_command(self.elapsed_s(now_ns), self.setpoint_ahead(now_ns)))
            else:
                self.publish_command(self.command_a)

    def follow_control_period(self, dt_s: float) -> None:
        """Keep a running mean of the stage time between ticks [s] (simulated seconds with use_sim_time, else
        node-clock seconds times time_scale); with tuning imc, derive the gains
        again when it has moved by more than PERIOD_TOLERANCE from the period they were derived for."""
        self.period_estimate_s += PERIOD_SMOOTHING * (min(dt_s, 10.0 * self.period_estimate_s) - self.period_estimate_s)
        if self.settings.tuning != "imc" or abs(self.period_estimate_s / self.tuned_period_s - 1.0) <= PERIOD_TOLERANCE:
            return
        self.tuned_period_s = self.period_estimate_s
        slew_s = slew_time_s(self.core.max_current_a, self.core.max_rate_a_per_s)
        for name, value in imc_gains(self.model, self.tuned_period_s, self.core.lead_limit, slew_s).items():
            setattr(self.core, name, value)
        self.get_logger().info(f"control period {self.tuned_period_s:.3g} s of stage time: "
                               f"PI kp {self.core.kp:.3g} ki {self.core.ki:.3g}/s (imc)",
                               throttle_duration_sec=PERIOD_LOG_INTERVAL_S)

    def elapsed_s(self, now_ns: int | None = None) -> float:
        """Stage seconds from the previous command computed to now_ns [ns; default the node clock's now], 0 for the
        first (simulated time with use_sim_time, else node-clock seconds times time_scale)."""
        now_ns = self.get_clock().now().nanoseconds if now_ns is None else now_ns
        previous_ns, self._last_step_ns = self._last_step_ns, now_ns
        if previous_ns is None:
            return 0.0
        return max((now_ns - previous_ns) * 1e-9, 0.0) * self.time_scale

    def measurement_age_s(self) -> float:
        """Steady-clock seconds since the latest usable joint_states (inf before the first)."""
        if self._measured_at is None:
            return math.inf
        return (self.steady.now() - self._measured_at).nanoseconds * 1e-9

    def setpoint_ahead(self, now_ns: int) -> float | None:
        """The latest stamped setpoint [m] due by preview_s of stage time after now_ns [ns]; None when none is
        scheduled by then or preview is false."""
        if not self.settings.preview or not self.scheduled:
            return None
        horizon_ns = now_ns + round(self.core.preview_s(self.settings.feedback) / self.time_scale * 1e9)
        due = bisect.bisect_right(self.scheduled, (horizon_ns, math.inf))
        return self.scheduled[due - 1][1] if due else None

    def compute_command(self, dt_s: float, ahead_m: float | None = None) -> float:
        """Current [A] for the setpoint, dt_s [s] after the previous command (PI integral), held for one control
        period (the lead's step); ahead_m [m]: the setpoint preview_s ahead, when one is known."""
        measured = self.measured_m if self.settings.feedback else None
        age_s = self.measurement_age_s()
        if self.settings.feedback and measured is None:
            self.warnings.warn("no_measurement", "feedback is on but no joint_states has come: current_cmd "
                               f"{self.command_a:g} A from the model alone (feedforward)")
        if measured is not None and age_s > self.settings.measurement_timeout:
            self.warnings.warn("stale", f"no joint_states for {age_s:.3g} s (measurement_timeout "
                               f"{self.settings.measurement_timeout:g} s): current_cmd held at {self.command_a:g} A")
            return self.command_a
        try:
            current = self.core.command(self.setpoint_m, measured, dt_s, hold_s=self.period_estimate_s,
                                        ahead_m=ahead_m)
        except InputError as error:  # a core that cannot command (e.g. manual gains too large) keeps the last one
            self.warnings.warn("command", f"current_cmd held at {self.command_a:g} A: {error}")
            return self.command_a
        if self.core.drive.out_of_reach:
            self.clipped_count += 1
            self.warnings.warn("clipped", f"target {self.core.target_m:.4g} m is beyond the model's reach within "
                                  f"+-{self.settings.max_current:g} A: current at its limit")
        return current

    def diagnostic_status(self) -> DiagnosticStatus:
        """The loop's health as one DiagnosticStatus: WARN when feedback is on and joint_states is missing or
        older than measurement_timeout, or when targets were beyond the model's reach since the last status;
        else OK (running, waiting for a setpoint, or paused while another node owns current_cmd)."""
        age_s, timeout = self.measurement_age_s(), self.settings.measurement_timeout
        clipped = self.clipped_count - self._reported_clipped
        level, text = DiagnosticStatus.OK, "running"
        if not self.settings.enabled:
            text = "paused: enabled is false (another node owns current_cmd)"
        elif self.setpoint_m is None:
            text = "waiting for a setpoint"
        elif self.settings.feedback and self.measured_m is None:
            level, text = DiagnosticStatus.WARN, "feedback is on but no joint_states has come: feedforward only"
        elif self.settings.feedback and age_s > timeout:
            level, text = DiagnosticStatus.WARN, f"no joint_states for {age_s:.3g} s: current_cmd held"
        elif clipped:
            level, text = DiagnosticStatus.WARN, f"{clipped} targets beyond the model's reach: current at its limit"
        values = {
            "model": self.describe_model(),
            "setpoint_m": self.setpoint_m if self.setpoint_m is not None else "none",
            "measured_m": self.measured_m if self.measured_m is not None else "none",
            "measurement_age_s": round(age_s, 3) if math.isfinite(age_s) else "never",
            "current_cmd_a": self.command_a,
            "integral_m": self.core.integral_m,
            "kp": self.core.kp,
            "ki_per_s": self.core.ki,
            "control_period_s": round(self.period_estimate_s, 4),
            "targets_beyond_reach": self.clipped_count,
            "learning": self.describe_learning(),
            "feedback": self.settings.feedback,
            "enabled": self.settings.enabled,
        }
        return DiagnosticStatus(level=level, name=f"{self.get_fully_qualified_name()}: compensator", message=text,
                                hardware_id="sma_stage compensator",
                                values=[KeyValue(key=key, value=str(value)) for key, value in values.items()])

    def describe_learning(self) -> str:
        """The learning in force, in a few words: off, or its period, the periods learnt and the last one's RMS
        error."""
        learning = self.core.learning
        if self.core.learning_period_s == 0.0:
            return "off"
        if learning is None or learning.periods == 0:
            return f"period {self.core.learning_period_s:g} s, in its first period"
        return (f"period {learning.period_s:g} s, {learning.periods} learnt, the last one's RMS error "
                f"{learning.last_rms_m:.3g} m")

    def publish_diagnostics(self) -> None:
        """Publish the status on /diagnostics."""
        with self._lock:
            array = DiagnosticArray(status=[self.diagnostic_status()])
            self._reported_clipped = self.clipped_count
        array.header.stamp = self.get_clock().now().to_msg()
        self.diagnostics_pub.publish(array)

    def publish_model(self) -> None:
        """Publish the model in force and its source on ~/model (transient local: the model watch reads it)."""
        self.model_pub.publish(model_message(self.model.to_yaml_text(), self.model_source))

    def publish_command(self, current_a: float) -> None:
        """Publish a current command [A]."""
        self.command_pub.publish(Float64(data=float(current_a)))


def main(args: list[str] | None = None) -> None:
    """Entry point `compensator_node`."""
    exit_with(run_node(CompensatorNode, args))


if __name__ == "__main__":
    main()
