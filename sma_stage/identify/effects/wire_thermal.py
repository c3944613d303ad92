"""`wire_thermal`: the antagonistic stage's two wires. Wire a is heated only by u > 0, wire b only by u < 0
(the relay), each by its Joule heating u^2 / u_ref and each cooling with its own time constant (the idle
wire only cools); the hysteresis sees the difference of their temperatures [A of heating]. With equal
time constants it is the heating reading of `thermal_lag`.
"""

from __future__ import annotations

import math
import time

import numpy as np

from sma_stage.identify.effects.base import (
    FITTED_STARTS,
    SCREEN_SAMPLES,
    THOROUGH_STARTS,
    Candidate,
    EffectFit,
    InputTransformEffect,
    NotFitted,
    Progress,
    Refits,
    even_indices,
    finish_fit,
    fit_or_none,
    lag_range,
    pick,
    report,
    scalar_search,
)
from sma_stage.identify.fit import FitResult
from sma_stage.model.effects import Effect

SPREAD = 10.0  # each time constant is searched within SPREAD times either side of the common one
SWEEPS = 2  # coordinate sweeps over (tau_a, tau_b)
SWEEP_GRID_POINTS = 5


class WireThermalEffect(Candidate):
    """The common time constant first (a one-parameter search, the heating lag), then tau_a and tau_b in
    turn, each by a bounded search over its log with the GPI refitted (warm) at every value."""

    name = "wire_thermal"
    relative_cost = 11.5

    def fit(self, t: np.ndarray, u: np.ndarray, y: np.ndarray, base: FitResult, progress: Progress = None,
            starts: tuple[str, ...] = FITTED_STARTS) -> EffectFit:
        started = time.perf_counter()
        reference = float(np.max(np.abs(u)))
        if reference <= 0.0:
            raise NotFitted("wire_thermal: the current is zero throughout")
        common = InputTransformEffect(self.name, "tau_s", lambda tau: _wires(tau, tau, reference))
        first = common.fit(t, u, y, base, None, starts)
        taus = [first.parameters["tau_a_s"], first.parameters["tau_b_s"]]
        found = self._sweep(t, u, y, first, taus, reference)
        if found is None:
            raise NotFitted("wire_thermal: the GPI cannot be fitted at the time constants found")
        gpi, taus = found
        parameters = dict(_wires(*taus, reference).parameters)
        report(progress, f"wire_thermal: tau_a_s = {taus[0]:.4g}, tau_b_s = {taus[1]:.4g}, {gpi.operators} operators")
        return finished(self.name, parameters, gpi, y, base.parameter_count + 2, started, first.start)

    def recount(self, fit: EffectFit, t: np.ndarray, u: np.ndarray, y: np.ndarray,
                progress: Progress = None) -> EffectFit:
        """The operator count chosen again (fit_gpi's rule) at the time constants found, which are then
        searched again from the new count's fit; fit itself if the count stays."""
        started = time.perf_counter()
        spec = fit.spec
        counted = fit_or_none(spec.transform(t, u, spec.start_state(t, u, fit.start))[0], y, None, None,
                              fit.gpi_parameters.output_unit, starts=THOROUGH_STARTS)
        if counted is None or pick([fit, counted]) is fit:
            return fit
        taus = [fit.parameters["tau_a_s"], fit.parameters["tau_b_s"]]
        reference = fit.parameters["joule_reference_a"]
        first = finished(self.name, fit.parameters, counted, y, fit.parameter_count, started, fit.start)
        found = self._sweep(t, u, y, first, taus, reference)
        if found is None:
            return fit
        gpi, taus = found
        report(progress, f"wire_thermal: {gpi.operators} operators, tau_a_s = {taus[0]:.4g}, tau_b_s = {taus[1]:.4g}")
        return finished(self.name, dict(_wires(*taus, reference).parameters), gpi, y, fit.parameter_count, started,
                        fit.start)

    @staticmethod
    def _sweep(t: np.ndarray, u: np.ndarray, y: np.ndarray, first: EffectFit, taus: list[float],
               reference: float) -> tuple[FitResult, list[float]] | None:
        """The sweeps on a copy thinned to SCREEN_SAMPLES, then the GPI refitted on all samples (thorough)."""
        low, high = lag_range(t)
        screen = even_indices(t.size, SCREEN_SAMPLES)
        t_s, u_s, y_s = t[screen], u[screen], y[screen]

        def inputs(pair: list[float], t: np.ndarray, u: np.ndarray) -> np.ndarray:
            spec = _wires(*pair, reference)
            return spec.transform(t, u, spec.start_state(t, u, first.start))[0]

        unit = first.gpi_parameters.output_unit
        gpi = fit_or_none(inputs(taus, t_s, u_s), y_s, first.operators, first.gpi_parameters, unit)
        if gpi is None:
            return None
        for _ in range(SWEEPS):
            for wire in (0, 1):
                def transform(value: float, wire: int = wire) -> np.ndarray:
                    pair = list(taus)
                    pair[wire] = value
                    return inputs(pair, t_s, u_s)

                fits = Refits(transform, y_s, gpi)
                search = (max(taus[wire] / SPREAD, low), min(taus[wire] * SPREAD, high))
                taus[wire] = math.exp(scalar_search(fits.cost, *search, SWEEP_GRID_POINTS, thorough=False))
                gpi = fits.fit(taus[wire], thorough=screen.size == t.size)
                if gpi is None:
                    return None
        if screen.size < t.size:
            whole = Refits(lambda value: inputs(taus, t, u), y, gpi)
            gpi = whole.fit(taus[0], thorough=True)
        return (gpi, taus) if gpi is not None else None


def _wires(tau_a_s: float, tau_b_s: float, reference_a: float) -> Effect:
    return Effect("wire_thermal", {"tau_a_s": tau_a_s, "tau_b_s": tau_b_s, "joule_reference_a": reference_a})


def finished(name: str, parameters: dict[str, float], gpi: FitResult, y: np.ndarray, parameter_count: int,
             started: float, start: str) -> EffectFit:
    return finish_fit(name, parameters, gpi.parameters, gpi.operators, y, gpi.predicted, parameter_count,
                      started, start)


EFFECT = WireThermalEffect()
