"""Issue 49's candidate control laws against the package's default (the PI loop with the preview), on the plants and
setpoints of bench/bench_positioning.py: each plant identified from the paper's record as that bench does, then
driven through the moving shapes (sines of 50, 100 and 250 s, the paper's validation shape, the slow ramp) and the
three draws of held levels by each law. The candidates are written here, as subclasses of the package's
Compensator, and none is in the package: each lost somewhere (bench/README.md, positioning, says where).

- disturbance observer (tf): the loop's target less d, the measured position minus the inverse's model's own
  prediction on its currents, through a first-order filter of tf seconds: the model's miss corrected without
  waiting for the PI loop's lag;
- two degrees of freedom (lambda): the feedforward's current (its model run on it alone, its own preview) plus a PI
  on the error in amperes, tuned by IMC on the model's mean slope and tau (lambda = the fraction times tau);
- hand-over lead (s): when the setpoint that many seconds beyond the preview wants the other wire, the inverse is
  driven towards it until the preview's setpoint wants that wire too (not on a step: between the two setpoints it
  moves no faster than the model's lag lets the stage follow, the preview's own rule): the relay switches earlier,
  against the dead time of the wire taking over; with the model's dead time, the lead is the time the two-wire
  model's wire taking over needs at the full current to heat from its temperature now to its transformation's onset
  (2 widths below its centre, 1.5 with the compact onset, shifted by the position's and the other wire's pulls), at
  most its tau: the lead from the model instead of a number;
- model-predictive (horizon): the current, held over the horizon (a fraction of the model's tau, in control periods),
  whose run of the two-wire model from its state now, plus the measured position's offset from the model (through
  a first-order filter of 1 s), comes nearest the setpoints due over that horizon (the least sum of squares; 41
  currents over the limit, then 11 around the best), then the package's rate limit and relay hold; no PI loop;
- two-move planner (horizon): while the setpoint moves, no faster than the model's lag lets the stage follow, the
  current path with the least squared error between the setpoints due over the horizon and the two-wire model's
  run plus the measured offset (through a first-order filter of 0.5 s): a first target for the current, then after
  0.4, 1 or 2 s a second one, each reached at the package's rate limit (the dead band crossed at once; the other
  wire only after the relay's hold, then up to the package's hand-over jump at once), 41 targets over the limit for
  each; its first step is commanded as planned (the relay's hold kept); with a switch cost, each relay switch in a
  path costs four relay holds' worth of an error of 1 % of the model's reach span; while the setpoint holds or
  steps, the package's law, its integral taken from the planner's offset when the planner lets go;
- loop gains scaled (factor): the PI loop's kp and ki from `imc_gains` times the factor, all else the default;
- setpoint shaped (taus): the setpoint moved towards the one commanded at most the model's reach span in that many
  of its taus per second (a step becomes a ramp; no preview while it ramps, the shaped setpoint being unknown ahead);
- preview longer (factor): the setpoint that many times `preview_s()` ahead, all else the default;
- lag inverted on the preview: the preview plus the central difference's inverse of the lag the lead leaves (its
  docstring);
- wire state estimated (tf): the default law, its inverse's two-wire model kept on the measured position by the
  wires' temperatures (a state estimator on the model's hidden states, the estimator of issue 49's EKF-MPC
  anchor without the MPC): after each step, the wire whose temperature moves the model's output towards the
  measurement the most (the slope from a trial change of 0.01 A of heating) has it moved by 1 - exp(-dt / tf) of
  the miss over that slope, at most 0.2 A of heating a step, the wire's plays following.

Prints the table and writes it to bench/results/candidate_laws.md (--out); one process. `--only TEXT` runs the default
and the laws whose name holds TEXT alone: 4-5 minutes for `--only "loop gains"` or `"setpoint shaped"` (two laws each), 20-27 minutes for one
planner (`--only "planner, 5 s"`).

    .venv/bin/python bench/bench_candidate_laws.py [--plants simulator,nominal,...] [--seed 0] [--only TEXT]
        [--out FILE]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path

import numba
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))

import bench_positioning as positioning  # noqa: E402

from sma_stage.control import Compensator  # noqa: E402
from sma_stage.control.compensator import RELAY_HOLD_S, _wire, _within  # noqa: E402
from sma_stage.control.drives import lead_horizon_s, reach_span_m  # noqa: E402
from sma_stage.model.two_wire import COMPACT_ONSET, TENSION_COUPLING, TwoWireStream, _advance, _shares  # noqa: E402

MPC_GRID, MPC_REFINE = 41, 11  # the currents the model-predictive law tries, over the limit and then around the best
SHAPES = ("sine 50 s", "sine 100 s", "sine 250 s", "paper's validation", "slow ramp",
          "held levels 1", "held levels 2", "held levels 3")


class DisturbanceObserver(Compensator):
    """The PI loop's target less the filtered model miss (see the module's docstring)."""

    filter_s = 1.0  # the filter's time constant [s]

    def reset(self) -> None:
        super().reset()
        self.disturbance_m = 0.0

    def _pi_target(self, setpoint: float, measured: float, dt: float, holding: bool, now: float,
                   speed: float = 1.0) -> float:
        if dt > 0.0:
            share = 1.0 - math.exp(-dt / self.filter_s)
            self.disturbance_m += share * (measured - self.drive.predicted_m - self.disturbance_m)
        return super()._pi_target(setpoint, measured, dt, holding, now, speed) - self.disturbance_m


class TwoDegreesOfFreedom(Compensator):
    """The feedforward's current plus a PI in amperes on the error (see the module's docstring)."""

    lambda_fraction = 0.7  # the IMC closed loop's time constant as a fraction of the model's tau

    def reset(self) -> None:
        super().reset()
        self.feedback_integral_a = 0.0

    def preview_s(self, feedback: bool = True) -> float:
        return super().preview_s(False)

    def command(self, setpoint_m: float, measured_m: float | None = None, dt_s: float = 0.0,
                hold_s: float | None = None, ahead_m: float | None = None) -> float:
        feedforward = super().command(setpoint_m, None, dt_s, hold_s, ahead_m)
        if measured_m is None:
            return feedforward
        tau = max(self.tau_s, positioning.PERIOD_S)
        closed_loop = self.lambda_fraction * tau
        kp, ki = self._amps_per_m * tau / closed_loop, self._amps_per_m / closed_loop
        error = setpoint_m - measured_m
        before = feedforward + kp * error + self.feedback_integral_a
        if abs(before) < self._limit or before * error < 0.0:  # anti-windup: not while it saturates with the error
            self.feedback_integral_a += ki * error * dt_s
        return _within(feedforward + kp * error + self.feedback_integral_a, 0.0, self._limit)


class Foreseeing(Compensator):
    """A candidate law that bench_positioning.drive tells the setpoints ahead through `foresee`, and that follows the
    measured position's offset from its model's."""

    offset_filter_s = 1.0  # the time constant [s] of the filter on the measured minus the model's position

    def reset(self) -> None:
        super().reset()
        self._setpoint_at: Callable[[float], float] | None = None
        self._offset_m: float | None = None

    def foresee(self, setpoint_at: Callable[[float], float]) -> None:
        """setpoint_at(s): the setpoint [m] s seconds beyond the preview's."""
        self._setpoint_at = setpoint_at

    def _future_m(self, setpoint_m: float, count: int, step_s: float) -> np.ndarray:
        """The setpoints [m] due at the end of each of the next `count` periods of step_s [s] (the one now when no
        setpoint ahead is told)."""
        preview = self.preview_s(True)
        return np.array([setpoint_m if self._setpoint_at is None else self._setpoint_at(j * step_s - preview)
                         for j in range(1, count + 1)])

    def _follow_offset(self, measured_m: float, dt_s: float) -> None:
        """The measured position [m] less the model's, through a first-order filter of offset_filter_s."""
        miss = float(measured_m) - self.drive.predicted_m
        if self._offset_m is None:
            self._offset_m = miss
        elif dt_s > 0.0:
            self._offset_m += (1.0 - math.exp(-dt_s / self.offset_filter_s)) * (miss - self._offset_m)


class HandOverLead(Foreseeing):
    """The inverse driven towards the setpoint lead_s beyond the preview while that one wants the other wire (see the
    module's docstring); bench_positioning.drive tells it the setpoints ahead through `foresee`."""

    lead_s = 0.6

    def reset(self) -> None:
        super().reset()
        self._early = False
        self._further: float | None = None

    def _side_for(self, target_m: float) -> int:
        horizon = lead_horizon_s(self.tau_s, self._lead_limit)
        return _wire(self.drive.stream.current_for(target_m, horizon))

    def command(self, setpoint_m: float, measured_m: float | None = None, dt_s: float = 0.0,
                hold_s: float | None = None, ahead_m: float | None = None) -> float:
        self._further = None
        if self._setpoint_at is not None and ahead_m is not None and hasattr(self.drive, "stream"):
            further = float(self._setpoint_at(self.lead_s))
            side = _wire(self.command_a) or self._relay_side
            if not self._early and abs(further - ahead_m) * self.tau_s <= self.lead_s * reach_span_m(self.drive):
                wanted = self._side_for(further)  # a setpoint the stage can follow (not a step): the preview's rule
                self._early = wanted != 0 and side != 0 and wanted != side
            elif self._early and self._side_for(ahead_m) == side:
                self._early = False
            self._further = further if self._early else None
        return super().command(setpoint_m, measured_m, dt_s, hold_s, ahead_m)

    def _previewed(self, now: float, ahead: float | None, dt: float) -> float:
        chosen = super()._previewed(now, ahead, dt)  # its step rule on the preview's own setpoint
        return self._further if self._further is not None and ahead is not None and chosen == ahead else chosen


class HandOverDeadTime(HandOverLead):
    """The hand-over lead with, as its lead, the model's dead time of the wire taking over (see the module's
    docstring)."""

    onset_widths = {0.0: 2.0, 1.0: 1.5}  # below its centre, the widths where a wire starts to transform: tanh, compact

    @property
    def lead_s(self) -> float:  # type: ignore[override]
        stream = getattr(self.drive, "stream", None)
        if not isinstance(stream, TwoWireStream):
            return HandOverLead.lead_s
        p, state = stream._p, stream._state
        wire = 1 if (_wire(self.command_a) or self._relay_side) > 0 else 0  # the one taking over
        shares = _shares(state, p, stream._n)
        sign = 1.0 if wire == 0 else -1.0
        onset = (p[5 + wire] - self.onset_widths[p[COMPACT_ONSET]] * p[7 + wire] + sign * p[3 + wire] * state[-1]
                 + p[TENSION_COUPLING] * shares[1 - wire])
        full = self.max_current_a ** 2 / p[2]
        now = state[wire]
        if onset <= now:
            return 0.0
        if full <= onset:
            return p[wire]
        return min(p[wire], -p[wire] * math.log((full - onset) / (full - now)))


class ModelPredictive(Foreseeing):
    """A move-blocked model-predictive law over a two-wire model (see the module's docstring); another model, or no
    measurement, runs the package's law. bench_positioning.drive tells it the setpoints ahead through `foresee`."""

    horizon_taus = 1.0  # the horizon, in the model's tau

    def _cost(self, current_a: float, future_m: np.ndarray, step_s: float) -> float:
        stream = self.drive.stream
        state = stream._state.copy()
        offset, cost = self._offset_m, 0.0
        for wanted in future_m:
            cost += (_advance(state, stream._p, stream._n, stream._m, current_a, step_s) + offset - wanted) ** 2
        return cost

    def command(self, setpoint_m: float, measured_m: float | None = None, dt_s: float = 0.0,
                hold_s: float | None = None, ahead_m: float | None = None) -> float:
        if measured_m is None or not isinstance(getattr(self.drive, "stream", None), TwoWireStream):
            return super().command(setpoint_m, measured_m, dt_s, hold_s, ahead_m)
        self.drive.advance(self.command_a, dt_s)
        self._looped = True
        self._follow_offset(measured_m, dt_s)
        step = positioning.PERIOD_S
        future = self._future_m(setpoint_m, max(1, round(self.horizon_taus * self.tau_s / step)), step)
        limit = self._limit
        grid = np.linspace(-limit, limit, MPC_GRID)
        best = min(grid, key=lambda current: self._cost(current, future, step))
        spacing = grid[1] - grid[0]
        fine = np.clip(np.linspace(best - spacing, best + spacing, MPC_REFINE), -limit, limit)
        best = float(min(fine, key=lambda current: self._cost(current, future, step)))
        moving = self._setpoint.moves(setpoint_m, dt_s)
        self.command_a = self._relay_held(self._rate_limited(best, dt_s, moving), dt_s)
        return self.command_a


@numba.njit(cache=True)
def _toward(current: float, target: float, side: int, step_a: float, jump_a: float, low: float, high: float,
            may_switch: bool) -> float:
    """The current [A] one control period after `current` on its way to `target`: beyond the dead band (low, high)
    [A] at most step_a per period, the band crossed at once; to the wire other than `side` (the relay's, +1 or -1)
    only when may_switch, then at once up to jump_a beyond the band (the package's hand-over jump), else held at
    the band's edge."""
    start = current - high if current > high else (current - low if current < low else 0.0)
    end = target - high if target > high else (target - low if target < low else 0.0)
    wanted = 1 if end > 0.0 else (-1 if end < 0.0 else 0)
    if wanted != 0 and wanted != side:
        if not may_switch:
            end = 0.0
        else:
            moved = min(end, jump_a) if end > 0.0 else max(end, -jump_a)
            return high + moved if moved > 0.0 else low + moved
    if end == start and end != 0.0:
        return current
    moved = end if end == start else (min(start + step_a, end) if end > start else max(start - step_a, end))
    if moved != 0.0:
        return high + moved if moved > 0.0 else low + moved
    return min(high, max(low, target)) if wanted == 0 else (high if side > 0 else low)


@numba.njit(cache=True)
def _run_path(state: np.ndarray, p: np.ndarray, n: int, m: int, current: float, side: int, held: int, target: float,
              steps: range, limits: np.ndarray, future: np.ndarray, offset: float, period_s: float,
              bound: float) -> tuple[float, float, int, int]:
    """Run the model (state, changed in place) along the path towards `target` over `steps` (indices of `future`
    [m], the setpoints due); (the squared error summed, the current at the end [A], the relay's side, the periods
    since its last switch); stops once the sum passes `bound`. limits: (step_a, jump_a, low, high, hold periods,
    a switch's cost [m^2])."""
    cost = 0.0
    for k in steps:
        current = _toward(current, target, side, limits[0], limits[1], limits[2], limits[3], held >= limits[4])
        wire = 1 if current > limits[3] else (-1 if current < limits[2] else 0)
        held += 1
        if wire != 0 and wire != side:
            side, held = wire, 0
            cost += limits[5]
        cost += (_advance(state, p, n, m, current, period_s) + offset - future[k]) ** 2
        if cost >= bound:
            break
    return cost, current, side, held


@numba.njit(cache=True)
def _planned_current(state: np.ndarray, p: np.ndarray, n: int, m: int, current: float, side: int, held: int,
                     limits: np.ndarray, targets: np.ndarray, switches: np.ndarray, future: np.ndarray, offset: float,
                     period_s: float) -> float:
    """The next period's current [A] of the two-move path (see the module's docstring) with the least squared error
    against `future` [m] (the setpoints due at the end of each period), the model run from `state` plus `offset`;
    side and held: the relay's wire and the periods since it switched."""
    best, first = np.inf, current
    middle, trial = np.empty_like(state), np.empty_like(state)
    for target in targets:
        step = _toward(current, target, side, limits[0], limits[1], limits[2], limits[3], held >= limits[4])
        for switch in switches:
            middle[:] = state
            before, now, now_side, now_held = _run_path(middle, p, n, m, current, side, held, target, range(switch),
                                                        limits, future, offset, period_s, best)
            if before >= best:
                continue
            for second in targets:
                trial[:] = middle
                cost = before + _run_path(trial, p, n, m, now, now_side, now_held, second,
                                          range(switch, future.size), limits, future, offset, period_s,
                                          best - before)[0]
                if cost < best:
                    best, first = cost, step
    return first


class TwoMovePlanner(Foreseeing):
    """The two-move planner while the setpoint moves, the package's law otherwise (see the module's docstring); a
    model other than the two-wire one, or no measurement, runs the package's law. bench_positioning.drive tells it
    the setpoints ahead through `foresee`."""

    horizon_s = 5.0
    offset_filter_s = 0.5  # the time constant [s] of the filter on the measured minus the model's position
    switch_s = (0.4, 1.0, 2.0)  # when the second move may start [s]
    targets = 41  # the current targets tried over the limit, for each move
    switch_weight = 0.0  # a relay switch in a path costs this many relay holds of 1 % of the reach span's error

    def reset(self) -> None:
        super().reset()
        self._last_setpoint_m: float | None = None
        self._planning = False

    def _follows(self, setpoint_m: float, dt_s: float) -> bool:
        """Whether the setpoint [m] moved since the previous command no faster than the model's lag lets the stage
        follow (the preview's rule): the planner's turn; a held or stepped setpoint is the package law's."""
        previous, self._last_setpoint_m = self._last_setpoint_m, setpoint_m
        change = 0.0 if previous is None else abs(setpoint_m - previous)
        return change > 0.0 and dt_s > 0.0 and change * self.tau_s <= dt_s * reach_span_m(self.drive)

    def command(self, setpoint_m: float, measured_m: float | None = None, dt_s: float = 0.0,
                hold_s: float | None = None, ahead_m: float | None = None) -> float:
        if measured_m is None or not isinstance(getattr(self.drive, "stream", None), TwoWireStream):
            return super().command(setpoint_m, measured_m, dt_s, hold_s, ahead_m)
        if not self._follows(setpoint_m, dt_s):
            if self._planning:  # the loop's integral takes over the planner's offset
                self._planning = False
                self._release_inverse()
                self.integral_m = -(self._offset_m or 0.0) - self.kp * float(setpoint_m - measured_m)
            current = super().command(setpoint_m, measured_m, dt_s, hold_s, ahead_m)
            self._follow_offset(measured_m, dt_s)
            return current
        self._planning = True
        self.drive.advance(self.command_a, dt_s)
        self._looped = True
        self._follow_offset(measured_m, dt_s)
        step = positioning.PERIOD_S
        count = max(2, round(self.horizon_s / step))
        future = self._future_m(setpoint_m, count, step)
        stream = self.drive.stream
        low, high = self._dead_band
        rate = self._max_rate_a_per_s
        hold_periods = round(RELAY_HOLD_S / step)
        switch_cost = self.switch_weight * hold_periods * (0.01 * reach_span_m(self.drive)) ** 2
        limits = np.array([rate * step, rate * RELAY_HOLD_S, low, high, hold_periods, switch_cost])
        switches = np.array([min(count - 1, max(1, round(s / step))) for s in self.switch_s])
        side = self._relay_side or _wire(self.command_a) or 1
        planned = _planned_current(stream._state, stream._p, stream._n, stream._m, self.command_a, side,
                                   round(self._relay_held_s / step), limits,
                                   np.linspace(-self._limit, self._limit, self.targets), switches, future,
                                   self._offset_m, step)
        self._setpoint.moves(setpoint_m, dt_s)
        self.command_a = self._relay_held(planned, dt_s)
        return self.command_a


class ScaledGains(Compensator):
    """The package's law with its PI gains times gain_factor."""

    gain_factor = 1.5

    def __init__(self, model: object, max_current_a: float = 5.0, kp: float = 0.0, ki: float = 0.0,
                 **settings: object) -> None:
        super().__init__(model, max_current_a, kp=kp * self.gain_factor, ki=ki * self.gain_factor, **settings)


class ShapedSetpoint(Compensator):
    """The package's law on a setpoint rate-limited to the model's reach span per `taus` of its tau."""

    taus = 4.0

    def reset(self) -> None:
        super().reset()
        self._shaped_m: float | None = None

    def command(self, setpoint_m: float, measured_m: float | None = None, dt_s: float = 0.0,
                hold_s: float | None = None, ahead_m: float | None = None) -> float:
        rate = reach_span_m(self.drive) / (self.taus * max(self.tau_s, positioning.PERIOD_S))
        previous = setpoint_m if self._shaped_m is None else self._shaped_m
        self._shaped_m = min(previous + rate * dt_s, max(previous - rate * dt_s, setpoint_m))
        if ahead_m is not None and self._shaped_m != setpoint_m:
            ahead_m = self._shaped_m
        return super().command(self._shaped_m, measured_m, dt_s, hold_s, ahead_m)


class LongerPreview(Compensator):
    """The package's law told the setpoint `factor` times its preview_s() ahead."""

    factor = 1.5

    def preview_s(self, feedback: bool = True) -> float:
        return self.factor * super().preview_s(feedback)


class LagInverted(Compensator):
    """The package's law driven towards the preview plus `weight` (2 now - ahead - past) / 2, past the setpoint
    preview_s() ago: with the preview, the central difference's inverse of the first-order lag tau / g the lead
    leaves, whose gain 1 / sqrt(1 + (w tau / g)^2) the preview alone keeps; weight = 1 - the largest step of the
    setpoint over the last two previews / its total variation there (0 on a step, near 1 on a smooth setpoint)."""

    def reset(self) -> None:
        super().reset()
        self._aheads: deque[tuple[float, float]] = deque()  # (the setpoint's clock [s], the setpoint ahead [m])

    def _previewed(self, now: float, ahead: float | None, dt: float) -> float:
        chosen = super()._previewed(now, ahead, dt)
        if ahead is None:
            self._aheads.clear()
            return chosen
        clock = self._setpoint.now_s + dt  # the setpoint's motion is told this dt after the preview
        self._aheads.append((clock, ahead))
        window = 2.0 * self.preview_s()
        while self._aheads[0][0] < clock - window - 1e-9:
            self._aheads.popleft()
        if chosen != ahead or self._aheads[0][0] > clock - window + dt:
            return chosen
        jumps = np.abs(np.diff([value for _, value in self._aheads]))
        if jumps.sum() == 0.0:
            return chosen
        weight = 1.0 - float(jumps.max() / jumps.sum())
        return self._bounded(ahead + weight * (2.0 * now - ahead - self._aheads[0][1]) / 2.0)


class WireStateEstimated(Compensator):
    """The inverse's two-wire model kept on the measured position by its wires' temperatures (see the module's
    docstring)."""

    filter_s = 1.0  # the estimator's time constant [s]
    probe = 0.01  # the temperature's trial change for the slope [A of heating]
    most = 0.2  # the largest correction of a temperature in one step [A of heating]

    def _advance_models(self, held: bool, measured: float | None, dt: float) -> None:
        super()._advance_models(held, measured, dt)
        stream = self.drive.stream
        if measured is None or dt <= 0.0 or not isinstance(stream, TwoWireStream):
            return
        miss = measured - stream.output
        best_slope, best_wire = 0.0, -1
        for wire in (0, 1):
            for sign in (1.0, -1.0):
                trial = stream._state.copy()
                trial[wire] += sign * self.probe
                slope = (_advance(trial, stream._p, stream._n, stream._m, 0.0, 0.0) - stream.output) / (sign * self.probe)
                if slope * miss * sign > 0.0 and abs(slope) > abs(best_slope):
                    best_slope, best_wire = slope, wire
        if best_wire < 0:
            return
        share = 1.0 - math.exp(-dt / self.filter_s)
        stream._state[best_wire] += _within(share * miss / best_slope, 0.0, self.most)
        _advance(stream._state, stream._p, stream._n, stream._m, 0.0, 0.0)


def variant(base: type[Compensator], **settings: float) -> type[Compensator]:
    """A subclass of base with its class settings changed."""
    return type(base.__name__, (base,), dict(settings))


LAWS = [positioning.LOOP_PREVIEW] + [
    positioning.Mode(f"disturbance observer, {tf:g} s", True, True, core=variant(DisturbanceObserver, filter_s=tf))
    for tf in (0.5, 2.0)] + [
    positioning.Mode(f"two degrees of freedom, lambda {fraction:g} tau", True, True,
                     core=variant(TwoDegreesOfFreedom, lambda_fraction=fraction)) for fraction in (0.35, 0.7)] + [
    positioning.Mode(f"hand-over lead, {lead:g} s", True, True, core=variant(HandOverLead, lead_s=lead))
    for lead in (0.6, 1.2)] + [
    positioning.Mode("hand-over lead, the model's dead time", True, True, core=HandOverDeadTime)] + [
    positioning.Mode(f"model-predictive, {horizon:g} tau", True, True, core=variant(ModelPredictive,
                                                                                   horizon_taus=horizon))
    for horizon in (0.2, 0.3)] + [
    positioning.Mode(f"two-move planner{' with switch cost' if weight else ''}, {horizon:g} s", True, True,
                     core=variant(TwoMovePlanner, horizon_s=horizon, switch_weight=weight))
    for horizon, weight in ((4.0, 0.0), (5.0, 0.0), (5.0, 4.0))] + [
    positioning.Mode(f"loop gains scaled, {factor:g} times", True, True, core=variant(ScaledGains, gain_factor=factor))
    for factor in (1.5, 2.0)] + [
    positioning.Mode(f"setpoint shaped, {taus:g} tau", True, True, core=variant(ShapedSetpoint, taus=taus))
    for taus in (4.0, 8.0)] + [
    positioning.Mode(f"preview longer, {factor:g} times", True, True, core=variant(LongerPreview, factor=factor))
    for factor in (1.5, 2.0)] + [
    positioning.Mode("lag inverted on the preview", True, True, core=LagInverted)] + [
    positioning.Mode(f"wire state estimated, {tf:g} s", True, True, core=variant(WireStateEstimated, filter_s=tf))
    for tf in (1.0, 3.0)]


def cell(run: positioning.Tracked) -> str:
    settled = f", settled max {run.settled_max_pct:.2f}" if run.settled_max_pct is not None else ""
    return f"{run.rms_pct:.2f} / {run.max_pct:.1f} ({run.change_p99_pct:.1f}{settled})"


def summary(found: dict[str, dict[str, list[positioning.Tracked]]], laws: list[positioning.Mode]) -> list[str]:
    """Per shape and law, over the plants: the mean RMS and the plants within issue 49's 1 % (moving shapes), or the
    worst settled hold and the plants whose every hold is within 0.2 % (held levels); the largest p99 change."""
    lines = ["| setpoint | " + " | ".join(law.name for law in laws) + " |", "|---" * (len(laws) + 1) + "|"]
    for shape in SHAPES:
        cells = []
        for index in range(len(laws)):
            runs = [by_shape[shape][index] for by_shape in found.values()]
            chatter = max(run.change_p99_pct for run in runs)
            if shape.startswith("held levels"):
                worst = [run.settled_max_pct for run in runs]
                cells.append(f"worst {max(worst):.2f}; {sum(w <= positioning.HELD_TARGET_PCT for w in worst)} of "
                             f"{len(runs)}; p99 {chatter:.1f}")
            else:
                rms = [run.rms_pct for run in runs]
                cells.append(f"{np.mean(rms):.2f}; {sum(r <= positioning.LOOP_TARGET_PCT for r in rms)} of "
                             f"{len(runs)}; p99 {chatter:.1f}")
        lines.append(f"| {shape} | " + " | ".join(cells) + " |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--plants", default=",".join(positioning.PLANTS))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--only", default="", help="run only the laws whose name holds this text, beside the default")
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "candidate_laws.md")
    args = parser.parse_args()
    names = positioning.plant_names(parser, args.plants)
    laws = [LAWS[0]] + [law for law in LAWS[1:] if args.only in law.name]
    if len(laws) == 1:
        parser.error(f"no candidate law's name holds {args.only!r}")
    started = time.perf_counter()
    forms = positioning.shapes(args.seed)
    header = ("| plant | setpoint | " + " | ".join(law.name for law in laws) + " |\n" + "|---" * (len(laws) + 2) + "|")
    print(header, flush=True)
    lines, found = [header], {}
    for name in names:
        identified = positioning.identify(name, args.seed)
        found[name] = {}
        for shape in SHAPES:
            runs = found[name][shape] = [positioning.track(identified, shape, forms[shape], law) for law in laws]
            line = f"| {name} | {shape} | " + " | ".join(cell(run) for run in runs) + " |"
            print(line, flush=True)
            lines.append(line)
    over = summary(found, laws)
    print("\n" + "\n".join(over))
    body = ("Each cell: RMS / max error [% of the stroke] (the current's p99 change, % of the limit; held levels: the "
            "worst hold's settled error, %).\n\n" + "\n".join(lines) + "\n\nOver the plants: the mean RMS and the "
            "plants within 1 % (held levels: the worst settled hold and the plants with every hold within 0.2 %), and "
            "the largest p99 change:\n\n" + "\n".join(over) + "\n\n"
            + positioning.run_note(f"--plants {args.plants} --seed {args.seed} --only {args.only!r}", started,
                                   "bench_candidate_laws.py"))
    positioning.write(args.out, "Issue 49's candidate laws against the PI loop with the preview", body)


if __name__ == "__main__":
    main()
