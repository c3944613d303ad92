"""The compensator's control law (no ROS): the identified model run backwards, one sample at a time, and a
PI loop around it.

Per call, dt seconds after the previous one, with e = setpoint - measured position [m] when a
measurement is given (feedback):

    integral += ki e dt, except while the command saturates in the direction of e (anti-windup), and
                while a held setpoint's error is one the model still expects to close: the setpoint holds and
                is not moving (see below), and the inverse's model is further from the inverse's target than
                the stage from the setpoint (conditional integration); REVERSAL_SPEED ki e dt while a held
                setpoint's reversal goes through the linear path (see below)
    target    = setpoint + kp e + integral                      (target = setpoint without feedback)
    target    = a play of half-width deadband_m on it: the target reverses only once it has come back by
                more than 2 deadband_m (feedback only; measurement noise no longer reverses it)
    v*        = GPI inverse(target - drift offset now)          within the current limit [A]
    current   = the lead: the drive that brings the thermal lag's state s to v* over one step,
                s + g (v* - s) with g = 1 / (1 - exp(-dt / tau)), g at most lead_limit with a
                measurement; without one, feedforward_lead_limit while the setpoint moves and
                feedforward_step_lead_limit otherwise (drive = v* without a lag), clipped to the
                current limit, and changed by at most max_rate_a_per_s * dt from the previous
                command (0: no rate limit), the model's dead band crossed at once (below)

The dead band (`dead_band_a`): the currents around zero where, in the model, neither wire moves the stage (a
wire heated below its transformation). The rate limit counts a change of the current only outside it, so the
hand-over from one wire to the other crosses it in one step: where the wires move only beyond +-0.75 A, a 1 A/s
rate limit took 1.5 s to cross to the other wire at each reversal, the stage standing still meanwhile
(bench/bench_positioning.py's plants; the table and the commit that added this have the figures). While the
setpoint moves, a change of the current on one wire's side (or to or from 0 A) is rate-limited within the band as
well, and only the relay's switch crosses it at once: before a hand-over the wanted current wandered in the band
(on `nominal`'s 100 s sine 22 of 2000 steps changed by more than the rate limit, each a jump the stage does not
need). A held or stepped setpoint's current still moves freely within the band: the linear path that settles a
held level near the hand-over needs it (rate-limited there, one of `nominal`'s holds settled 2.96 % off).
In the loop, while the setpoint moves at least HANDOVER_SPEED_FRACTION (1 %) of the model's reach span per
RELAY_HOLD_S, the relay's switch takes the new wire up to max_rate_a_per_s * RELAY_HOLD_S (2 A at the default)
beyond the band (beyond 0 A for a model without one) at once, then the rate limit again: at 1 A/s the new wire's
current otherwise climbs through currents that barely move it, the stage stalls past the setpoint and then snaps
beyond it (`hot_alloy`'s 100 s sine: 2.2 % RMS in the 5 % of the period around each hand-over, 0.5 % elsewhere).
The jump is what the rate limit would have added over the relay's hold; the speed guard keeps it from a setpoint
wandering about the hand-over, where a jump at each crossing made the relay cycle (`fast_wires`' paper's shape:
20 -> 62 switches). Figures over three seeds: bench/README.md, positioning.

Why the play, the lead limit and the rate limit: the exact inverse of a hysteretic model jumps across
the loop's width at every reversal of its target, and the exact lead multiplies a change of v* by
tau / dt (about 100 at 10 Hz for the wires' 11 s). Together they turned sensor noise in the PI loop
into a current switching from rail to rail (bench/bench_tracking.py: 157 % of the limit RMS from one
command to the next). With lead_limit g, the lag's state follows v* with the time constant tau / g at
most, the plant the PI loop sees; `imc_gains` tunes the loop for it (IMC, lambda = 0.7 tau / g). The rate
limit spreads the jump across the loop over a few steps, which the lag's own time constant makes
harmless. Without a measurement (feedforward) no noise enters, and the lead has its own limits, for
a trade the loop does not have: on the simulator a strong lead tracks a continuous signal better, and a
lead on a step overshoots the current, which holds the setpoint worse (the faster the wires are heated,
the further the stage ends from the model's static position at the same final current). So the
feedforward lead tells the two apart: the setpoint *moves* while its change over the last MOTION_WINDOW_S
(1 s) and its change over the second before agree in sign and within a factor MOVING_RATE_RATIO (2);
then feedforward_lead_limit (10) applies. The windows make it indifferent to when each setpoint message
arrives (a stream published slower than the loop, or in bursts, still moves), as long as it comes at
least every half second. After a step, at a reversal and while the setpoint holds,
feedforward_step_lead_limit (1: no overshoot; the lag's state approaches v* with tau) applies.
The defaults (3 in the loop, 10 and 1 in feedforward, 1 A/s) come from scans with bench/bench_tracking.py
(their tables: bench/README.md at commit b315809): in the loop a limit of 10 made the stage limit-cycle around a held setpoint (9-14 um RMS
against 0.8-1.4 um at 3), and 5 did at a rate limit of 0.5 A/s.

While the setpoint holds (the same value as in the previous call) the loop's target may still move on with
the error, but it does not reverse through the inverse: the inverse keeps the target it had, and the part of
the loop's target that reverses goes through a linear path instead (metres to amperes at the model's mean
slope, its span over twice the current limit, with the same lead on a first-order lag of the model's tau).
Why: the exact inverse answers a reversal of its target, however small, with a jump across the model's
loop, and where the stage's minor loops are narrower than the model's that jump moves the stage further
than the error that caused it: a held setpoint limit-cycled (the simulator with the shipped model, 0.4 s
control period: 2-5 um peak to peak, the current swinging 1.2-3.5 A at the rate limit). The linear path has
no jump; a change of the setpoint, or a target beyond the model's reach, frees the inverse again. While the linear
path acts, a copy of the model runs on the whole command (the inverse's model sees only its own share); when the
setpoint changes after a hold of at least RESYNC_HOLD_S, that copy becomes the model and the integral is set so
that the loop's target for the setpoint before is what the copy predicts: the current does not jump. After a
shorter hold the linear path's part fades out as before: a setpoint streamed at the loop's rate is "held" for
single steps now and then, and taking over there (where the model's prediction lags its target) cost the demo's
PI loop 0.34 -> 1.75 % RMS. Without the copy the inverse resumed from a state that had
not seen the linear path's current: on the second physical stage (bench/bench_positioning.py's `nominal`) that state
was 5 % of the stroke from the stage after a 60 s hold, and the 250 s sine that followed began 10 % of the stroke off.

The linear path's slope is the model's mean one, but a held setpoint's reversal first crosses the width of the stage's
own loop, where the current changes and the stage does not move (the heated wire cooled back through its hysteresis,
the other heated up to where it transforms): at ki the integral took 30-50 s to carry the current across it, and a
level reached with an overshoot was still up to 1.9 % of the stroke off after 40 s. So once the linear path has acted
in a hold, the integral runs REVERSAL_SPEED (3) times faster, but not while the last command was saturated or held
back by the rate limit: there a faster integral only winds up ahead of a current that cannot follow (without that
exception a speed of 4 already limit-cycled on two plants of bench/bench_positioning.py); and not without
proportional action (kp 0: the gains of a model without a heating lag, pure integral action for a stage whose lag
the model does not know): the shipped GPI without its lag held levels on the simulator 92-331 um peak to peak at 3x,
0.2-1.9 um at 1x (test_control.py -k without_a_lag). Its scan over the held
levels of that bench's nine plants (`--reversal-speeds 1,2,3,4,6`, bench/results/reversal_speed.md; the PI loop with
and without the preview, 54 draws of eight holds): the worst hold 2.12, 1.41, 0.76, 2.35 and 2.90 % of the stroke at
speeds 1, 2, 3, 4 and 6, the mean settled error 0.136, 0.062, 0.049, 0.055 and 0.068 %; at 4 a hold of `prestrained`
settles 2.35 % off, at 6 it and `upper_band` limit-cycle (the current switching wires, p99 change 4.9-8.0 % of the
limit against the rate limit's 4 %). 3: the least worst hold and mean error of the five.

While the linear path carries a held level's reversal, the inverse keeps its target but is solved again at every
command, and where a two-wire model's output is flat in the current (the heated wire cooled back through its
hysteresis, the other not yet transforming) an output a few nanometres off that target asked for amperes: on
bench/bench_positioning.py's `slow_wires` (seed 1, draw 2) the rate limit held back 0.04 A of the inverse's share,
its model ended 3 nm above the target, the share went from -1.1 to -3.6 A in 2 s and the stage fell 4 % of the
stroke (that hold settled 1.36 % off). So the two-wire inverse keeps its last current within KEEP_TOLERANCE
(sma_stage.model.two_wire); what that does to the held levels of three seeds: bench/README.md, positioning.

A preview (`ahead_m`, the setpoint `preview_s()` from now, for a caller that knows the setpoint ahead: a
stamped stream sent early, a planned trajectory): the lead limit leaves the stage a first-order lag of tau / g
(g = lead_limit in the loop, 3: 3.3 s for the shipped model's 9.9 s), which the PI loop closes only as fast as
its own time constant. Driving the inverse towards the setpoint that lag ahead undoes it without the noise a
stronger lead would amplify; the loop's error stays against the setpoint now. A step is not taken early: when
the setpoint ahead moves faster than the model's lag lets the stage follow (its reach span in tau), the inverse
is driven towards the setpoint now until that has caught up with the one ahead (a step taken early only leaves
the level early, and in the loop the error against the level it left winds the integral the wrong way).
bench/bench_positioning.py measures it on every plant, beside the loop without it.

With a model that has a dead band, the relay (the current's sign: which wire is heated) does not switch back
within RELAY_HOLD_S of a switch; the current stays within the dead band meanwhile. Where the loop's target sits at the hand-over between the
wires, the wanted current crossed back and forth two to four times in 0.6 s at every hand-over (the `nominal`
plant of bench/bench_positioning.py, a 100 s sine), each crossing a change of 1.5 A and a switch of the relay.
Why 2 s and not 1: with 1 s, hand-overs of `slow_wires`' and `prestrained`'s 50 s sines still switched back once
more after the hold (p99 current change 26 and 142 % of the limit); with 2 s every row of that bench but the 20 s
sine's changes the current by at most the rate limit's 4 % per step, `prestrained`'s 50 s sine is tracked at
6.80 % against 7.70 %, and a held level near the hand-over settles better on one draw and worse on another
(`hot_alloy`, PI loop with the preview: the worst hold of draw 2 2.26 -> 0.83 %, of draw 3 0.22 -> 1.38 %).

A setpoint that repeats (`learning_period_s` above 0, with a measurement): the setpoint now and the one ahead get
a correction learnt from the errors at the same phase of the periods before (iterative learning:
sma_stage.control.learning.PeriodicLearning, its lag a third of the model's tau, its bins 0.2 s or the control
period's hold when longer, its correction within LEARNING_LIMIT_FRACTION of the reach span), and the inverse and
the loop follow the corrected setpoint. What the model misses at each hand-over between the wires repeats period
after period (bench/README.md, positioning), and the loop corrects it only once it has happened; the learning
corrects it ahead. A setpoint that holds keeps the correction it had (a held level's loop below sees a held
setpoint). The learning begins when the setpoint first moves (a command with a measurement and a hold, a dt or
hold_s above 0, whose setpoint differs from the one before) after its period was set or the compensator reset (a
new model, `set_model`): a setpoint held before the repeated one starts is not taken for part of its period.
Figures: bench/bench_learning.py and bench/bench_learning_nodes.py (bench/README.md, learning).

Each effect of the IdentifiedModel is stepped with the code identification fitted it with
(sma_stage.model.effects):
- thermal_lag: its state is advanced with the command sent, held over each step (`lag_step` with equal
  ends: exact for a held current), and the lead sends the held drive that brings it to v* over one step
  (`lag_drive_for`, that step solved for its drive); in the heating reading the lead works in heating
  units and sends the current whose Joule heating it wants.
- wire_thermal: the two wires' temperatures are advanced with the command sent (each wire heated by its
  own sign of the current, both cooling); the lead sends the held current that brings their difference to
  v* over one step, in closed form (sma_stage.control.thermal), within the same lead limit.
- drift: its offset follows the model's time (from where the model's state left it, else 0) and is
  taken off the target.
- rate: compensated quasi-statically: the inverse of the rate model's GPI at zero input rate (the
  thresholds' stretch with the rate is left uncompensated).
- delay: a dead time cannot be led causally: left uncompensated in feedforward (the position follows the
  setpoint delay_s late); the PI loop sees it in the measurement.
The model's state at the end of the identification record, when it carries one, is where the inverse,
the lag and the drift start.

A TwoWireModel or a BoucWenModel is run backwards by its own exact inverse (sma_stage.control.drives.StreamDrive):
its heating states are advanced with the command sent, and the current is the one that, held over the horizon a
lead of gain g needs (-tau ln(1 - 1/g), tau the slower wire's), brings the model's output to the target;
the same lead limits, rate limit, play and PI loop apply around it.
"""

from __future__ import annotations

import bisect
import copy
import math

from sma_stage.control.drives import Drive, dead_band_a, drive_for, model_tau_s, reach_span_m
from sma_stage.control.learning import RESOLUTION_S, PeriodicLearning, checked_period_s, learning_lag_s
from sma_stage.errors import InputError, finite_number, non_negative_number
from sma_stage.model.effects import lag_drive_for, lag_step
from sma_stage.model.kinds import AnyModel, StreamModel

COMPENSATION = {
    "thermal_lag": "inverted: the lead brings the lag's state to the inverse's output over each step",
    "delay": "left uncompensated: a dead time cannot be led causally, the position follows the setpoint delay_s "
             "late (the PI loop sees it in the measurement)",
    "rate": "compensated quasi-statically: the inverse of the rate model's GPI at zero input rate",
    "drift": "taken off the target as the model's time runs on",
    "wire_thermal": "inverted: the lead's held current brings the wires' temperature difference to the inverse's "
                    "output over each step (closed form: one wire heats, both cool)",
}


def compensation_notes(model: AnyModel) -> dict[str, str]:
    """How the compensator treats each of the model's effects (effect kind -> one line)."""
    if isinstance(model, StreamModel):
        return {model.kind: "inverted exactly: the current that, held over the lead limit's horizon, brings the "
                            "model's output to the target through its heating lag"}
    return {kind: COMPENSATION[kind] for kind in model.effect_names}


DEFAULT_LEAD_LIMIT = 3.0
DEFAULT_FEEDFORWARD_LEAD_LIMIT = 10.0  # feedforward, while the setpoint moves
DEFAULT_FEEDFORWARD_STEP_LEAD_LIMIT = 1.0  # feedforward, after a step and while the setpoint holds
MOTION_WINDOW_S = 1.0  # a moving setpoint's change is compared over two windows this long [s]
MOVING_RATE_RATIO = 2.0  # and agrees within this factor
RELAY_HOLD_S = 2.0  # the relay switches back to the other wire no sooner than this after a switch [s]
HANDOVER_SPEED_FRACTION = 0.01  # the hand-over's jump needs a setpoint moving this much of the reach per RELAY_HOLD_S
RESYNC_HOLD_S = 2.0  # the true model takes over after a hold of at least this long [s]
DEFAULT_DEADBAND_M = 1e-6  # five times the default simulator's sensor noise (0.2 um RMS)
DEFAULT_MAX_RATE_A_PER_S = 1.0
REVERSAL_SPEED = 3.0  # the integral's gain, in ki, while a held setpoint's reversals go through the linear path
LEARNING_LIMIT_FRACTION = 0.2  # the learnt correction at most this share of the model's reach span
LAMBDA_FRACTION = 0.7  # the loop's closed-loop time constant, as a fraction of the lag the lead leaves (scan: bench/README.md at b315809)


def _within(value: float, centre: float, half_width: float) -> float:
    """value clipped to centre +- half_width."""
    return min(centre + half_width, max(centre - half_width, value))

def _wire(current_a: float) -> int:
    """The wire a current [A] heats, by its sign: +1, -1, or 0 for none."""
    return (current_a > 0.0) - (current_a < 0.0)


def checked_gains(kp: float, ki: float) -> dict[str, float]:
    """The loop's gains (kp [m/m], ki [1/s]) as floats; InputError unless each is finite and >= 0."""
    return {name: non_negative_number(name, value) for name, value in {"kp": kp, "ki": ki}.items()}


def slew_time_s(max_current_a: float, max_rate_a_per_s: float) -> float:
    """The time [s] the rate limit takes to move the current over half its range, max_current / (2 max_rate);
    0 without a rate limit (max_rate 0)."""
    return 0.0 if max_rate_a_per_s == 0.0 else max_current_a / (2.0 * max_rate_a_per_s)


DEFAULT_SLEW_S = slew_time_s(5.0, DEFAULT_MAX_RATE_A_PER_S)  # the compensator's defaults: 5 A at 1 A/s, 2.5 s


def imc_gains(model: AnyModel, control_period_s: float, lead_limit: float = DEFAULT_LEAD_LIMIT,
              slew_s: float = DEFAULT_SLEW_S) -> dict[str, float]:
    """PI gains (kp [m/m], ki [1/s]) by IMC (lambda) tuning for what the loop sees around the compensated
    model: a first-order lag of tau_c = tau / lead_limit (tau the model's thermal lag, 0 without one) and
    one control period of dead time theta; lambda = LAMBDA_FRACTION tau_c, but at least slew_s (slew_time_s:
    a loop asked to close faster than the rate limit lets the current move winds its integral up against the
    slew; bench/results/positioning.md: on a stage whose model has a 0.25 s lag the loop was 2.6 times worse
    than feedforward); kp = tau_c / (lambda + theta), ki = 1 / (lambda + theta)."""
    period = non_negative_number("control_period_s", control_period_s)
    if period == 0.0:
        raise InputError("control_period_s must be above 0")
    lag_left = model_tau_s(model) / max(lead_limit, 1.0)
    closed_loop = max(LAMBDA_FRACTION * lag_left, non_negative_number("slew_s", slew_s))
    return {"kp": lag_left / (closed_loop + period), "ki": 1.0 / (closed_loop + period)}


class _AtLeast:
    """A float setting of the Compensator, kept as `_<name>`; setting it to anything but a finite number
    >= minimum raises InputError naming it."""

    def __init__(self, minimum: float = 0.0) -> None:
        self.minimum = minimum

    def __set_name__(self, owner: type, name: str) -> None:
        self.name, self.slot = name, f"_{name}"

    def __get__(self, instance: object, owner: type | None = None) -> float:
        return self if instance is None else getattr(instance, self.slot)

    def __set__(self, instance: object, value: float) -> None:
        number = finite_number(self.name, value)
        if number < self.minimum:
            raise InputError(f"{self.name} must be at least {self.minimum:g}, got {value!r}")
        setattr(instance, self.slot, number)


class _SetpointMotion:
    """Whether a setpoint moves continuously (see the module's docstring): its changes over the last two
    MOTION_WINDOW_S windows agree in sign and within a factor MOVING_RATE_RATIO."""

    def __init__(self) -> None:
        self.now_s = 0.0
        self.times_s: list[float] = []  # when the setpoint took each of `values` [s]
        self.values: list[float] = []

    def moves(self, setpoint: float, dt_s: float) -> bool:
        """Take the setpoint [m] dt_s [s] after the previous one; whether it moves now."""
        self.now_s += dt_s
        if not self.values or setpoint != self.values[-1]:
            self.times_s.append(self.now_s)
            self.values.append(setpoint)
        oldest = self.now_s - 2.0 * MOTION_WINDOW_S
        kept_from = bisect.bisect_right(self.times_s, oldest) - 1
        if kept_from < 0:
            return False
        del self.times_s[:kept_from], self.values[:kept_from]
        middle = self._at(self.now_s - MOTION_WINDOW_S)
        before = middle - self.values[0]
        ratio = (setpoint - middle) / before if before != 0.0 else math.nan
        return 1.0 / MOVING_RATE_RATIO <= ratio <= MOVING_RATE_RATIO  # False for NaN

    def speed_m_per_s(self) -> float:
        """How fast [m/s] the setpoint moved over the last MOTION_WINDOW_S (0 before it has that much history)."""
        if not self.times_s or self.times_s[0] > self.now_s - MOTION_WINDOW_S:
            return 0.0
        return abs(self.values[-1] - self._at(self.now_s - MOTION_WINDOW_S)) / MOTION_WINDOW_S

    def _at(self, time_s: float) -> float:
        return self.values[bisect.bisect_right(self.times_s, time_s) - 1]


class Compensator:
    """Setpoint [m] (and measured position [m]) in, current [A] out; see the module's docstring.

    model: the identified model (a GPI or a two-wire model, output in m); max_current_a: the current limit
    [A]; method: the GPI inverse, "exact" or "analytic" (a two-wire model's is exact only); kp [m/m] and
    ki [1/s]: the PI gains (used only when a measurement is given); learning_period_s [s]: the period of a setpoint
    that repeats, learnt with the PI loop (PeriodicLearning; 0: none).
    """

    kp = _AtLeast()  # proportional gain [m of target per m of error]
    ki = _AtLeast()  # integral gain [1/s]
    deadband_m = _AtLeast()  # half-width of the play on the loop's target [m]
    max_rate_a_per_s = _AtLeast()  # largest change of the current per second [A/s]; 0: no limit
    lead_limit = _AtLeast(1.0)  # the lead's largest gain on a change of v* with a measurement (PI loop) [A/A]
    feedforward_lead_limit = _AtLeast(1.0)  # the same without a measurement, while the setpoint moves [A/A]
    feedforward_step_lead_limit = _AtLeast(1.0)  # without a measurement, while the setpoint does not move [A/A]

    def __init__(self, model: AnyModel, max_current_a: float = 5.0, method: str = "exact",
                 kp: float = 0.0, ki: float = 0.0, lead_limit: float = DEFAULT_LEAD_LIMIT,
                 deadband_m: float = DEFAULT_DEADBAND_M, max_rate_a_per_s: float = DEFAULT_MAX_RATE_A_PER_S,
                 feedforward_lead_limit: float = DEFAULT_FEEDFORWARD_LEAD_LIMIT,
                 feedforward_step_lead_limit: float = DEFAULT_FEEDFORWARD_STEP_LEAD_LIMIT,
                 learning_period_s: float = 0.0) -> None:
        self.kp = kp
        self.ki = ki
        self.lead_limit = lead_limit
        self.feedforward_lead_limit = feedforward_lead_limit
        self.feedforward_step_lead_limit = feedforward_step_lead_limit
        self.deadband_m = deadband_m
        self.max_rate_a_per_s = max_rate_a_per_s
        self._limit, self._method = 0.0, "exact"
        self._learning_period_s = 0.0
        self.set_model(model, max_current_a, method)
        self.learning_period_s = learning_period_s


    @property
    def model(self) -> AnyModel:
        """The identified model in force."""
        return self.drive.model

    @property
    def max_current_a(self) -> float:
        """The current limit [A]."""
        return self._limit

    def set_model(self, model: AnyModel, max_current_a: float | None = None, method: str | None = None) -> None:
        """Use another model (checked whole: InputError and nothing changed when it cannot be inverted);
        the integral and every state start again, from the model's carried state when it has one."""
        if not isinstance(model, AnyModel):
            raise InputError(f"model must be a GPI, a two-wire or a Bouc-Wen model, got {type(model).__name__}")
        if model.output_unit != "m":
            raise InputError(f"the model's output unit is '{model.output_unit}'; the setpoint is in m")
        limit = non_negative_number("max_current_a", self._limit if max_current_a is None else max_current_a)
        if limit == 0.0:
            raise InputError("max_current_a must be above 0")
        method = self._method if method is None else method
        drive_for(model, limit, method)  # checked whole before anything changes
        self._model, self._limit, self._method = model, limit, method
        self._dead_band = dead_band_a(model, limit)  # the model's and the limit's only: not again on each reset
        self.reset()

    def reset(self) -> None:
        """Integral to 0; the model's states (and the last command) from its carried state, else an idle stage
        at 0 A."""
        self.drive: Drive = drive_for(self._model, self._limit, self._method)
        self.integral_m = 0.0
        self.target_m = 0.0
        self._played_m: float | None = None
        self._commanded = False
        self._looped = False  # whether the last command ran the PI loop (had a measurement)
        self.saturated = 0
        self._slewing = False  # whether the rate limit held the last command back
        self.command_a = self.drive.initial_current()
        self._relay_side = _wire(self.command_a)  # the wire the relay feeds: +1, -1, 0
        self._relay_held_s = RELAY_HOLD_S  # since its last switch [s]
        self._hold_s = 0.0
        self._setpoint = _SetpointMotion()
        self._ahead_m: float | None = None  # the last setpoint ahead given [m]
        self._ahead_held_s = 0.0  # how long it has held [s]
        self._previewing = True
        self._reach_span_m = reach_span_m(self.drive)
        self._amps_per_m = 2.0 * self._limit / self._reach_span_m
        self._restart_learning()
        self._release_inverse()

    @property
    def learning_period_s(self) -> float:
        """The period [s] of a setpoint that repeats, learnt with the PI loop (0: no learning); setting another one
        starts the learning again."""
        return self._learning_period_s

    @learning_period_s.setter
    def learning_period_s(self, value: float) -> None:
        period = checked_period_s(value, name="learning_period_s")
        if period != self._learning_period_s:
            self._learning_period_s = period
            self._restart_learning()

    @property
    def learning(self) -> PeriodicLearning | None:
        """The learning in force (None: none, or before the setpoint first moved with a measurement)."""
        return self._learning

    def _restart_learning(self) -> None:
        """No correction learnt; the learning's period begins when the setpoint next moves (see `_corrected`)."""
        self._learning: PeriodicLearning | None = None
        self._learning_s = 0.0  # since the learning began [s]
        self._learnt: tuple[float, float, float, float] | None = None  # (setpoint, its correction, ahead, its) [m]

    def _release_inverse(self) -> None:
        """The inverse free to follow the loop's target both ways; the linear path at rest."""
        self._previous_setpoint: float | None = None
        self._inverse_target: float | None = None
        self._inverse_direction = 0
        self._linear_a = 0.0  # the linear path's share of the last command [A]
        self._linear_lag_a = 0.0  # that share through a first-order lag of the model's tau [A]
        self._true_drive: Drive | None = None  # the model run on the whole command while the linear path acts
        self._held_s = 0.0  # how long the setpoint has held [s]

    def continue_from(self, previous: Compensator) -> None:
        """Take over the loop of another core (the one this replaces, with another model): the last command, so
        that the rate limit moves the current from there; the played target and the setpoint's motion; and the
        integral, less what this model predicts beyond the other at their states now. The integral holds what
        the other model got wrong: a model fitted since (after a load step) has most of it in its prediction,
        and carrying the integral whole would count it twice, an error the loop then takes its integral time to
        undo. A held setpoint's inverse target (shifted the same) and the linear path carry over. The model's
        states stay this core's own (from its carried state)."""
        low, high = self.drive.target_bounds
        reach = high - low
        shift = self.drive.predicted_m - previous.drive.predicted_m if previous._looped else 0.0
        self.command_a = previous.command_a
        self._relay_side, self._relay_held_s = previous._relay_side, previous._relay_held_s
        self._commanded = previous._commanded
        self._looped = previous._looped
        self.integral_m = min(reach, max(-reach, previous.integral_m + shift))
        self._played_m = None if previous._played_m is None else previous._played_m + shift
        self.target_m = previous.target_m + shift
        self._hold_s = previous._hold_s
        self._setpoint = previous._setpoint
        self._ahead_m, self._ahead_held_s = previous._ahead_m, previous._ahead_held_s
        self._previewing = previous._previewing
        self._previous_setpoint = previous._previous_setpoint
        self._inverse_target = None if previous._inverse_target is None else previous._inverse_target + shift
        self._inverse_direction = previous._inverse_direction
        self._linear_a, self._linear_lag_a = previous._linear_a, previous._linear_lag_a

    @property
    def tau_s(self) -> float:
        """The model's (slowest) thermal time constant [s] the lead undoes (0: none)."""
        return self.drive.tau_s

    def preview_s(self, feedback: bool = True) -> float:
        """How far ahead [s] a setpoint is worth knowing: the lag tau / g the lead leaves, g the lead limit in
        force while the setpoint moves (lead_limit with a measurement, else feedforward_lead_limit)."""
        return self.tau_s / (self._lead_limit if feedback else self._feedforward_lead_limit)

    def command(self, setpoint_m: float, measured_m: float | None = None, dt_s: float = 0.0,
                hold_s: float | None = None, ahead_m: float | None = None) -> float:
        """The current [A] for setpoint_m [m]; with measured_m [m] the PI loop acts, integrating the error
        over dt_s [s], the time since the previous call (0 for a call at the same instant). hold_s [s]: how
        long this command will be held, the step the lead brings the lag's state to v* over (default: dt_s
        when above 0, else the previous hold; no lead before any). ahead_m [m]: the setpoint preview_s(...)
        from now, when the caller knows it: the inverse is driven towards it, the loop's error stays against
        setpoint_m (see the module's docstring)."""
        now = self._bounded(finite_number("setpoint_m", setpoint_m))
        dt = non_negative_number("dt_s", dt_s)
        measured = None if measured_m is None else self._bounded(finite_number("measured_m", measured_m))
        if hold_s is not None:
            self._hold_s = non_negative_number("hold_s", hold_s)
        elif dt > 0.0:
            self._hold_s = dt
        ahead = None if ahead_m is None else self._bounded(finite_number("ahead_m", ahead_m))
        if measured is not None and self._learning_period_s > 0.0 and self._hold_s > 0.0:
            now, ahead = self._corrected(now, ahead, measured, dt)
        setpoint = self._previewed(now, ahead, dt)
        moving = self._setpoint.moves(setpoint, dt)
        held = measured is not None and setpoint == self._previous_setpoint
        self._advance_models(held, measured, dt)
        self._held_s = self._held_s + dt if held else 0.0
        self.target_m = setpoint
        self._looped = measured is not None
        if measured is not None:
            speed = REVERSAL_SPEED if held and self._reversing() else 1.0
            self.target_m = self._pi_target(setpoint, measured, dt, held and not moving, now, speed)
        limit = self._lead_limit
        if measured is None:
            limit = self._feedforward_lead_limit if moving else self._feedforward_step_lead_limit
        self._previous_setpoint = setpoint
        inverse_target, reversal_m = self._split_reversal(self.target_m, held)
        if reversal_m != 0.0 and self._true_drive is None:
            self._true_drive = copy.deepcopy(self.drive)  # its state is the stage's: the linear path was at rest
        current, self.saturated = self.drive.current_for(inverse_target, self._hold_s, limit)
        if self.saturated or self.drive.out_of_reach:
            self._inverse_direction = 0
        linear = self._linear_path(reversal_m * self._amps_per_m, dt)
        total = current + linear
        bounded = min(self._limit, max(-self._limit, total))
        if bounded != total:
            self.saturated = 1 if total > bounded else -1
        self._linear_a = bounded - min(self._limit, max(-self._limit, current))
        limited = self._rate_limited(bounded, dt, moving)
        self._slewing = limited != bounded
        self.command_a = self._relay_held(limited, dt)
        return self.command_a

    def _corrected(self, now: float, ahead: float | None, measured: float, dt: float) -> tuple[float, float | None]:
        """(the setpoint now, the one ahead) [m] with the learnt correction added (each bounded), after the error of
        the setpoint now is recorded; a setpoint that holds keeps the correction it had (see the module's
        docstring)."""
        if self._learning is None:
            if self._learnt is None or self._learnt[0] == now:  # not before the setpoint moves
                self._learnt = (now, 0.0, math.nan, 0.0)
                return now, ahead
            period = self._learning_period_s
            self._learning = PeriodicLearning(period, learning_lag_s(self.drive.tau_s),
                                              LEARNING_LIMIT_FRACTION * self._reach_span_m,
                                              resolution_s=min(max(RESOLUTION_S, self._hold_s), 0.25 * period))
        else:
            self._learning_s += dt
        learning, time_s = self._learning, self._learning_s
        learning.record(time_s, measured - now)
        before = self._learnt
        now_correction = before[1] if before is not None and before[0] == now else learning.correction_m(time_s)
        ahead_correction = 0.0
        if ahead is not None:
            held = before is not None and before[2] == ahead
            ahead_correction = before[3] if held else learning.correction_m(time_s + self.preview_s())
        self._learnt = (now, now_correction, math.nan if ahead is None else ahead, ahead_correction)
        corrected_ahead = None if ahead is None else self._bounded(ahead + ahead_correction)
        return self._bounded(now + now_correction), corrected_ahead

    def _previewed(self, now: float, ahead: float | None, dt: float) -> float:
        """The setpoint [m] the inverse is driven towards: ahead, while the setpoint ahead moves no faster than the
        model's lag lets the stage follow (reach span / tau per second); else now, from such a jump (a step) until
        the setpoint now has caught up with the one ahead (see the module's docstring)."""
        if ahead is None:
            self._ahead_m = None
            return now
        self._ahead_held_s += dt
        if self._ahead_m is not None and ahead != self._ahead_m:
            tau = self.drive.tau_s
            speed = abs(ahead - self._ahead_m) / max(min(self._ahead_held_s, 0.5 * MOTION_WINDOW_S), dt, 1e-9)
            if tau > 0.0 and speed * tau > reach_span_m(self.drive):
                self._previewing = False
            self._ahead_held_s = 0.0
        self._ahead_m = ahead
        if ahead == now:
            self._previewing = True
        return ahead if self._previewing else now

    def _advance_models(self, held: bool, measured: float | None, dt: float) -> None:
        """Step the model over the dt [s] the last command was held: the inverse's model with its share of it, and
        while the linear path carries a part, the true model with all of it. When the setpoint no longer holds, the
        true model takes over after a hold of RESYNC_HOLD_S or more, and the integral is set so that the loop's
        target for the setpoint before is what it predicts: no jump of the current (see the module's docstring)."""
        self.drive.advance(self.command_a - self._linear_a, dt)
        if self._true_drive is None:
            return
        self._true_drive.advance(self.command_a, dt)
        if held:
            return
        true, self._true_drive = self._true_drive, None
        if self._held_s < RESYNC_HOLD_S:
            return  # a short hold: the linear path's part fades out as the inverse takes the target again
        before = self._previous_setpoint
        self.drive = true
        if measured is not None and before is not None:
            low, high = self.drive.target_bounds
            reach = high - low
            bumpless = self.drive.predicted_m - before - self._kp * (before - measured)
            self.integral_m = min(reach, max(-reach, bumpless))
            self._played_m = None
        self._release_inverse()

    def _split_reversal(self, target_m: float, held: bool) -> tuple[float, float]:
        """(the target [m] the inverse gets, the part [m] of target_m that goes through the linear path): on a
        held setpoint a reversal of the loop's target stays out of the inverse (see the module's docstring)."""
        previous = self._inverse_target
        inverse_target, reversal = target_m, 0.0
        if held and previous is not None and self._inverse_direction * (target_m - previous) < 0.0:
            inverse_target, reversal = previous, target_m - previous
        if previous is not None and inverse_target != previous:
            self._inverse_direction = 1 if inverse_target > previous else -1
        self._inverse_target = inverse_target
        return inverse_target, reversal

    def _linear_path(self, wanted_a: float, dt: float) -> float:
        """The linear path's current [A] for wanted_a [A]: the lead (lag_drive_for, its change at most lead_limit
        times the wanted one) on a first-order lag of the model's tau, whose state follows the path's share of
        what was sent."""
        tau = self.drive.tau_s
        if dt > 0.0:
            self._linear_lag_a = lag_step(self._linear_lag_a, self._linear_a, self._linear_a, dt, tau)
        seen = self._linear_lag_a
        exact = lag_drive_for(seen, wanted_a, self._hold_s, tau)
        if abs(exact - seen) <= self._lead_limit * abs(wanted_a - seen):
            return exact
        return seen + self._lead_limit * (wanted_a - seen)

    def _bounded(self, position_m: float) -> float:
        """A position [m] within the inverse's target bounds (the model's reach and ten spans beyond): a finite
        but absurd setpoint or measurement (1e308) gives the same command as one just beyond reach, and the
        loop's arithmetic cannot overflow."""
        low, high = self.drive.target_bounds
        return min(high, max(low, position_m))

    def _rate_limited(self, current: float, dt: float, moving: bool) -> float:
        """The current moved from the previous command by at most max_rate_a_per_s * dt (dt 0: not at all) beyond
        the dead band, the band itself crossed at once; while the setpoint moves, within the band too but where the
        relay switches to the other wire, and further at a decisive hand-over in the loop (`_decisive_handover`);
        except for the first command after a reset. See the module's docstring."""
        first, self._commanded = not self._commanded, True
        rate = self._max_rate_a_per_s
        if rate == 0.0 or first:
            return current
        if moving and _wire(current) * _wire(self.command_a) >= 0:
            return _within(current, self.command_a, rate * dt)
        wanted, previous = self._beyond_band(current), self._beyond_band(self.command_a)
        allowed = _within(wanted, previous, rate * dt)
        if allowed != wanted and self._decisive_handover(current, dt, moving):
            allowed = _within(wanted, 0.0, rate * RELAY_HOLD_S)
        if allowed == wanted:
            return current
        low, high = self._dead_band
        return high + allowed if allowed > 0.0 or (allowed == 0.0 and wanted > 0.0) else low + allowed

    def _decisive_handover(self, current: float, dt: float, moving: bool) -> bool:
        """Whether this command switches the relay to the other wire in the loop while the setpoint moves at least
        HANDOVER_SPEED_FRACTION of the reach span per RELAY_HOLD_S (see the module's docstring)."""
        side = _wire(current)
        return (self._looped and moving and dt > 0.0 and side != 0 and side != _wire(self.command_a)
                and side != self._relay_side and self._relay_held_s + dt >= RELAY_HOLD_S
                and self._setpoint.speed_m_per_s() * RELAY_HOLD_S >= HANDOVER_SPEED_FRACTION * self._reach_span_m)

    def _relay_held(self, current: float, dt: float) -> float:
        """The current [A]; but within RELAY_HOLD_S [s] of the relay's last switch (a change of the current's sign:
        the other wire), rather than switching it back, the last command within the model's dead band (where no
        wire moves the stage); a model without a dead band: the current as it is. See the module's docstring."""
        self._relay_held_s += dt
        side = _wire(current)
        if side == 0 or side == self._relay_side:
            return current
        low, high = self._dead_band
        if self._relay_side != 0 and self._relay_held_s < RELAY_HOLD_S and low < high:
            return min(high, max(low, self.command_a))
        self._relay_side, self._relay_held_s = side, 0.0
        return current

    def _beyond_band(self, current: float) -> float:
        """How far [A] a current lies beyond the dead band (negative below it, 0 within it)."""
        low, high = self._dead_band
        return current - high if current > high else current - low if current < low else 0.0

    def follow_applied(self, current_a: float, dt_s: float) -> None:
        """Step the model's states with a current [A] the stage applied for dt_s [s] that this compensator
        did not command (an excitation, another node, the watchdog): the lag with it held, the operators
        with the lag's new state, the drift's time; so that the next command starts where the stage is.
        The loop starts again (integral 0)."""
        current = finite_number("current_a", current_a)
        dt = non_negative_number("dt_s", dt_s)
        self.drive.follow_applied(current, dt)
        self.command_a = current
        self._relay_side = _wire(current) or self._relay_side
        self._relay_held_s = RELAY_HOLD_S
        self.integral_m = 0.0
        self._played_m = None
        self._commanded = False
        self._release_inverse()

    def _in_transit_m(self) -> float:
        """How far [m] the inverse's model still is from the inverse's target: the part of a step the model
        expects the stage to cover yet (0 before any target, and for a target beyond the model's reach)."""
        if self._inverse_target is None or self.drive.out_of_reach:
            return 0.0
        return abs(self._inverse_target - self.drive.predicted_m)

    def _reversing(self) -> bool:
        """Whether a held setpoint's loop reverses through the linear path, the last command followed it (neither
        saturated nor held back by the rate limit) and the loop has proportional action (see the module's
        docstring)."""
        return self._true_drive is not None and not self.saturated and not self._slewing and self._kp > 0.0

    def _pi_target(self, setpoint: float, measured: float, dt: float, holding: bool, now: float,
                   speed: float = 1.0) -> float:
        """The loop's target [m] for setpoint [m] (the one ahead, with a preview), the error against now [m];
        holding: the setpoint holds and has not been moving (a step, then a hold); speed: the integral's gain as a
        multiple of ki."""
        error = now - measured
        if self.saturated * error <= 0.0 and not (holding and self._in_transit_m() > abs(error)):
            low, high = self.drive.target_bounds  # beyond them the integral changes no command: a bound
            reach = high - low
            self.integral_m = min(reach, max(-reach, self.integral_m + speed * self._ki * error * dt))
        target = setpoint + self._kp * error + self.integral_m
        if not math.isfinite(target):
            raise InputError(f"the loop's target is not finite (setpoint {setpoint!r}, measured {measured!r})")
        played = self._played_m
        width = self._deadband_m
        self._played_m = target if played is None else _within(played, target, width)
        return self._played_m
