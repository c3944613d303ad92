"""`thermal_lag`: the hysteresis sees the first-order lag v of the current (or of its Joule heating),
the current held between samples (the forward model: sma_stage.model.effects).
"""

from __future__ import annotations

import numpy as np

from sma_stage.identify.effects.base import (
    FITTED_STARTS,
    Candidate,
    EffectFit,
    InputTransformEffect,
    NotFitted,
    Progress,
    attempt,
    lowest_cost,
)
from sma_stage.identify.fit import (
    FitResult,
)
from sma_stage.model.effects import Effect


def lagged_input(t: np.ndarray, u: np.ndarray, tau_s: float, joule_reference_a: float = 0.0) -> np.ndarray:
    """The lag v [A] of the current (of its Joule heating u |u| / joule_reference_a when that is above 0)
    from an idle stage: the thermal_lag effect's input transform."""
    parameters = {"tau_s": tau_s, **({"joule_reference_a": joule_reference_a} if joule_reference_a > 0.0 else {})}
    return Effect("thermal_lag", parameters).transform(t, u)[0]



class ThermalLagEffect(Candidate):
    """The GPI driven by a first-order lag (tau [s]) of either the current or of the Joule heating
    u |u| / u_ref (u_ref [A]: the record's largest |u|), whichever fits the identification data better
    (the wires heat as i^2 R, so the second is the physical reading; the first is exact for a plant whose
    drive is filtered linearly). The heating reading reports joule_reference_a = u_ref."""

    name = "thermal_lag"
    relative_cost = 6.4

    def fit(self, t: np.ndarray, u: np.ndarray, y: np.ndarray, base: FitResult, progress: Progress = None,
            starts: tuple[str, ...] = FITTED_STARTS) -> EffectFit:
        reference = float(np.max(np.abs(u)))
        readings = [self._reading(None)]
        if reference > 0.0:
            readings.append(self._reading(reference))
        outcomes = [attempt(self.name, lambda reading=reading: reading.fit(t, u, y, base, progress, starts))
                    for reading in readings]
        best = lowest_cost(outcome for outcome in outcomes if not isinstance(outcome, NotFitted))
        if best is None:
            raise NotFitted("thermal_lag: the GPI cannot be fitted on the lagged current nor on the lagged "
                            f"heating ({'; '.join(str(outcome) for outcome in outcomes)})")
        return best

    def recount(self, fit: EffectFit, t: np.ndarray, u: np.ndarray, y: np.ndarray,
                progress: Progress = None) -> EffectFit:
        return self._reading(fit.parameters.get("joule_reference_a")).recount(fit, t, u, y, progress)

    def refit(self, fit: EffectFit, t: np.ndarray, u: np.ndarray, y: np.ndarray, base: FitResult,
              progress: Progress = None) -> EffectFit:
        return self._reading(fit.parameters.get("joule_reference_a")).refit(fit, t, u, y, base, progress)

    def _reading(self, reference_a: float | None) -> InputTransformEffect:
        fixed = {} if reference_a is None else {"joule_reference_a": reference_a}
        return InputTransformEffect(self.name, "tau_s", lambda tau: Effect(self.name, {"tau_s": tau, **fixed}))


EFFECT = ThermalLagEffect()
