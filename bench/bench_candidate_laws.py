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
  against the dead time of the wire taking over;
- model-predictive (horizon): the current, held over the horizon (a fraction of the model's tau, in control periods),
  whose run of the two-wire model from its state now, plus the measured position's offset from the model (through
  a first-order filter of 1 s), comes nearest the setpoints due over that horizon (the least sum of squares; 41
  currents over the limit, then 11 around the best), then the package's rate limit and relay hold; no PI loop.

Prints the table and writes it to bench/results/candidate_laws.md (--out); 14-17 minutes on two cores.

    .venv/bin/python bench/bench_candidate_laws.py [--plants simulator,nominal,...] [--seed 0] [--out FILE]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))

import bench_positioning as positioning  # noqa: E402

from sma_stage.control import Compensator  # noqa: E402
from sma_stage.control.compensator import _wire, _within  # noqa: E402
from sma_stage.control.drives import lead_horizon_s, reach_span_m  # noqa: E402
from sma_stage.model.two_wire import TwoWireStream, _advance  # noqa: E402

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


class HandOverLead(Compensator):
    """The inverse driven towards the setpoint lead_s beyond the preview while that one wants the other wire (see the
    module's docstring); bench_positioning.drive tells it the setpoints ahead through `foresee`."""

    lead_s = 0.6

    def reset(self) -> None:
        super().reset()
        self._setpoint_at: Callable[[float], float] | None = None
        self._early = False
        self._further: float | None = None

    def foresee(self, setpoint_at: Callable[[float], float]) -> None:
        """setpoint_at(s): the setpoint [m] s seconds beyond the preview's."""
        self._setpoint_at = setpoint_at

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


class ModelPredictive(Compensator):
    """A move-blocked model-predictive law over a two-wire model (see the module's docstring); another model, or no
    measurement, runs the package's law. bench_positioning.drive tells it the setpoints ahead through `foresee`."""

    horizon_taus = 1.0  # the horizon, in the model's tau
    offset_filter_s = 1.0  # the time constant [s] of the filter on the measured minus the model's output

    def reset(self) -> None:
        super().reset()
        self._setpoint_at: Callable[[float], float] | None = None
        self._offset_m: float | None = None

    def foresee(self, setpoint_at: Callable[[float], float]) -> None:
        """setpoint_at(s): the setpoint [m] s seconds beyond the preview's."""
        self._setpoint_at = setpoint_at

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
        miss = measured_m - self.drive.predicted_m
        if self._offset_m is None:
            self._offset_m = miss
        elif dt_s > 0.0:
            self._offset_m += (1.0 - math.exp(-dt_s / self.offset_filter_s)) * (miss - self._offset_m)
        step = positioning.PERIOD_S
        count = max(1, round(self.horizon_taus * self.tau_s / step))
        preview = self.preview_s(True)
        future = np.array([setpoint_m if self._setpoint_at is None else self._setpoint_at(j * step - preview)
                           for j in range(1, count + 1)])
        limit = self._limit
        grid = np.linspace(-limit, limit, MPC_GRID)
        best = min(grid, key=lambda current: self._cost(current, future, step))
        spacing = grid[1] - grid[0]
        fine = np.clip(np.linspace(best - spacing, best + spacing, MPC_REFINE), -limit, limit)
        best = float(min(fine, key=lambda current: self._cost(current, future, step)))
        moving = self._setpoint.moves(setpoint_m, dt_s)
        self.command_a = self._relay_held(self._rate_limited(best, dt_s, moving), dt_s)
        return self.command_a


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
    positioning.Mode(f"model-predictive, {horizon:g} tau", True, True, core=variant(ModelPredictive,
                                                                                   horizon_taus=horizon))
    for horizon in (0.2, 0.3)]


def cell(run: positioning.Tracked) -> str:
    settled = f", settled max {run.settled_max_pct:.2f}" if run.settled_max_pct is not None else ""
    return f"{run.rms_pct:.2f} / {run.max_pct:.1f} ({run.change_p99_pct:.1f}{settled})"


def summary(found: dict[str, dict[str, list[positioning.Tracked]]]) -> list[str]:
    """Per shape and law, over the plants: the mean RMS and the plants within issue 49's 1 % (moving shapes), or the
    worst settled hold and the plants whose every hold is within 0.2 % (held levels); the largest p99 change."""
    lines = ["| setpoint | " + " | ".join(law.name for law in LAWS) + " |", "|---" * (len(LAWS) + 1) + "|"]
    for shape in SHAPES:
        cells = []
        for index in range(len(LAWS)):
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
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "candidate_laws.md")
    args = parser.parse_args()
    names = positioning.plant_names(parser, args.plants)
    started = time.perf_counter()
    forms = positioning.shapes(args.seed)
    header = ("| plant | setpoint | " + " | ".join(law.name for law in LAWS) + " |\n" + "|---" * (len(LAWS) + 2) + "|")
    print(header, flush=True)
    lines, found = [header], {}
    for name in names:
        identified = positioning.identify(name, args.seed)
        found[name] = {}
        for shape in SHAPES:
            runs = found[name][shape] = [positioning.track(identified, shape, forms[shape], law) for law in LAWS]
            line = f"| {name} | {shape} | " + " | ".join(cell(run) for run in runs) + " |"
            print(line, flush=True)
            lines.append(line)
    over = summary(found)
    print("\n" + "\n".join(over))
    body = ("Each cell: RMS / max error [% of the stroke] (the current's p99 change, % of the limit; held levels: the "
            "worst hold's settled error, %).\n\n" + "\n".join(lines) + "\n\nOver the plants: the mean RMS and the "
            "plants within 1 % (held levels: the worst settled hold and the plants with every hold within 0.2 %), and "
            "the largest p99 change:\n\n" + "\n".join(over) + "\n\n"
            + positioning.run_note(f"--plants {args.plants} --seed {args.seed}", started,
                                   "bench_candidate_laws.py"))
    positioning.write(args.out, "Issue 49's candidate laws against the PI loop with the preview", body)


if __name__ == "__main__":
    main()
