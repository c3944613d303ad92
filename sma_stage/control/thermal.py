"""The thermal state the compensator steps and leads, one sample at a time: none (the GPI sees the current's
drive), `thermal_lag` (one lagging state) or `wire_thermal` (two wires, each heated by its own sign of the
current). All in heating units [A]: the drive u |u| / u_ref in the heating reading, the current itself
otherwise (see sma_stage.model.effects).

For held commands each is stepped exactly, and the lead is exact too: the current to wire_thermal's
temperature difference over one held step is monotone (a positive current heats wire a alone and raises
the difference, a negative one heats wire b and lowers it, both wires cooling meanwhile), so the drive
that brings the difference to a target is found in closed form.
"""

from __future__ import annotations

import math

from sma_stage.model.effects import (
    Effect,
    EffectState,
    current_for_heating,
    joule_heating,
    lag_drive_for,
    lag_step,
)


class ThermalState:
    """What the GPI sees [A] and how a held drive moves it; `effect` thermal_lag, wire_thermal or None."""

    def __init__(self, effect: Effect | None, carried: EffectState | None = None) -> None:
        self.effect = effect
        self.reference_a = effect.parameters.get("joule_reference_a", 0.0) if effect is not None else 0.0
        values = tuple(carried.values) if carried is not None else ()
        if effect is not None and effect.kind == "wire_thermal":
            self.taus = (effect.parameters["tau_a_s"], effect.parameters["tau_b_s"])
            self.wires = [values[0], values[2]] if len(values) == 4 else [0.0, 0.0]
            self.last_drive = values[1] - values[3] if len(values) == 4 else 0.0
        else:
            self.taus = (effect.parameters["tau_s"],) if effect is not None else (0.0,)
            self.wires = [values[0] if len(values) == 2 else 0.0]
            self.last_drive = values[1] if len(values) == 2 else 0.0

    @property
    def two_wires(self) -> bool:
        return len(self.taus) == 2

    @property
    def tau_s(self) -> float:
        """The slowest time constant [s] (0: no thermal effect): what the PI loop's tuning takes as the lag."""
        return max(self.taus) if self.effect is not None else 0.0

    @property
    def seen(self) -> float:
        """What the GPI sees now [A]: the lag's state, the wires' difference, or the last drive."""
        if self.effect is None:
            return self.last_drive
        return self.wires[0] - self.wires[1] if self.two_wires else self.wires[0]

    def drive(self, current_a: float) -> float:
        """The drive [A of heating] of a current [A]."""
        return float(joule_heating(current_a, self.reference_a))

    def current(self, drive: float) -> float:
        """The current [A] whose drive is `drive`."""
        return current_for_heating(drive, self.reference_a)

    def advance(self, current_a: float, dt_s: float) -> None:
        """Step the states with the current held for dt_s [s]."""
        drive = self.drive(current_a)
        self.last_drive = drive
        if self.effect is None or dt_s <= 0.0:
            return
        if self.two_wires:
            shares = (max(drive, 0.0), max(-drive, 0.0))
            self.wires = [lag_step(state, share, share, dt_s, tau)
                          for state, share, tau in zip(self.wires, shares, self.taus, strict=True)]
        else:
            self.wires[0] = lag_step(self.wires[0], drive, drive, dt_s, self.taus[0])

    def lead(self, target: float, hold_s: float, lead_limit: float) -> float:
        """The drive [A of heating] to hold for hold_s [s] that brings what the GPI sees to `target`, its
        change from what it sees now at most lead_limit times the target's (the exact lead when within)."""
        if self.effect is None or hold_s <= 0.0:
            return target
        seen = self.seen
        exact = self._exact(target, hold_s)
        gap = target - seen
        if gap == 0.0 or abs(exact - seen) <= lead_limit * abs(gap):
            return exact
        return seen + lead_limit * gap

    def _exact(self, target: float, hold_s: float) -> float:
        if not self.two_wires:
            return lag_drive_for(self.wires[0], target, hold_s, self.taus[0])
        kept = [math.exp(-hold_s / tau) if tau > 0.0 else 0.0 for tau in self.taus]
        cooled = self.wires[0] * kept[0] - self.wires[1] * kept[1]
        wire = 0 if target >= cooled else 1
        closed = 1.0 - kept[wire]
        if closed <= 0.0:
            return math.copysign(math.inf, target - cooled)
        return (target - cooled) / closed
