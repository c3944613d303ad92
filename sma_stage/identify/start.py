"""How a record starts, found from its data for a given model: from rest, held at its first current long
enough to settle, or a free state (the GPI's last turning point and each effect's state values, fitted).

The choice is by the Bayesian information criterion over the whole record, the free values counted as
parameters: a free start is taken only when it explains the record's first seconds better than its
extra parameters cost. Nothing is trimmed: the errors of every sample count.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import OptimizeResult, least_squares
from scipy.stats import qmc

from sma_stage.identify.fit import information_criterion
from sma_stage.model.effects import FREE_VALUES, START_KINDS, joule_heating
from sma_stage.model.identified import IdentifiedModel, Start

TURNING_GRID_POINTS = 9  # turning points tried (the other free values held) before the values are polished
SCATTERED_STARTS = 32  # and points spread over every free value's range (a scrambled Sobol sequence)
FREE_POLISHED = 8  # a short polish runs from this many of the best of those,
FREE_SURVEY_EVALUATIONS = 3  # of this many evaluations,
FREE_FINISHED = 2  # and the best few of those polishes go on, up to FREE_MAX_EVALUATIONS in all
FREE_MAX_EVALUATIONS = 60
FREE_SAMPLES = 3000  # the free values are fitted on the record's first samples (where a start shows), at most this many
ELAPSED_LIMIT_FACTOR = 10.0  # a drift's elapsed time before the record: at most this many record lengths


@dataclass(frozen=True)
class StartFit:
    """The start found for a record: the start, the model's output from it [output unit], its SSR
    [output unit^2] and BIC, and the BIC of every kind tried."""

    start: Start
    predicted: np.ndarray = field(repr=False)
    cost: float
    bic: float
    tried: dict[str, float]

    def to_dict(self, model: IdentifiedModel) -> dict[str, object]:
        """Plain values for the JSON report: the kind, the free values by name, the BIC of each kind."""
        found: dict[str, object] = {"kind": self.start.kind, "bic": dict(self.tried)}
        if self.start.kind == "free":
            found["values"] = dict(zip(model.free_start_names, self.start.values, strict=True))
        return found


def start_fit(model: IdentifiedModel, t: np.ndarray, u: np.ndarray, y: np.ndarray, start: Start,
              free_count: int = 0) -> StartFit:
    """The model's output from a given start, its SSR and its BIC (free_count: the start's own parameters)."""
    predicted = model.predict_from(t, u, start)
    residual = y - predicted
    cost = float(residual @ residual)
    return StartFit(start, predicted, cost, information_criterion(cost, y.size, free_count), {})


def estimate_start(model: IdentifiedModel, t: np.ndarray, u: np.ndarray, y: np.ndarray,
                   kinds: tuple[str, ...] = START_KINDS) -> StartFit:
    """The start of least BIC among `kinds` for the record (t [s], u [A], y [output unit]) under the model."""
    found = {kind: (_free(model, t, u, y) if kind == "free" else start_fit(model, t, u, y, Start(kind)))
             for kind in kinds}
    best = min(found.values(), key=lambda fit: fit.bic)
    return StartFit(best.start, best.predicted, best.cost, best.bic, {kind: fit.bic for kind, fit in found.items()})


def _free(model: IdentifiedModel, t: np.ndarray, u: np.ndarray, y: np.ndarray) -> StartFit:
    """The free start of least SSR, on the first FREE_SAMPLES samples: candidates are the turning point over
    a grid (the other values held) and SCATTERED_STARTS points spread over every free value's range; every
    value is polished together by bounded least squares from the FREE_POLISHED best (a short polish each,
    then the FREE_FINISHED best go on), the least SSR kept. Several polishes, because the SSR is flat in
    the turning point wherever the record's first sample wipes the operators out, so one polish from the
    wrong side stays there. Its BIC on the whole record."""
    low, high = _bounds(model, t, u)
    held = model.start_state(t, u, Start("held"))
    held_values = np.clip(_held_values(model, held), low, high)
    head = slice(0, min(y.size, FREE_SAMPLES))
    t_head, u_head, y_head = t[head], u[head], y[head]
    scale = max(float(np.ptp(y)), np.finfo(float).tiny)

    def residual(values: np.ndarray) -> np.ndarray:
        return (model.predict_from(t_head, u_head, Start("free", tuple(values))) - y_head) / scale

    turnings = np.linspace(low[0], high[0], TURNING_GRID_POINTS)
    grid = [np.concatenate([[turning], held_values[1:]]) for turning in turnings]
    scattered = qmc.scale(qmc.Sobol(low.size, seed=0).random(SCATTERED_STARTS), low, high) if np.all(high > low) else []
    candidates = sorted((float(np.sum(residual(values) ** 2)), tuple(values)) for values in [*grid, *scattered])
    inner_low, inner_high = low + 1e-9 * (high - low), high - 1e-9 * (high - low)

    def polish(values: np.ndarray, evaluations: int) -> OptimizeResult:
        return least_squares(residual, np.clip(values, inner_low, inner_high), bounds=(low, high), method="trf",
                             x_scale="jac", diff_step=1e-4, max_nfev=evaluations)

    surveyed = sorted((polish(np.array(values), FREE_SURVEY_EVALUATIONS) for _, values in candidates[:FREE_POLISHED]),
                      key=lambda solution: solution.cost)
    finished = [polish(solution.x, FREE_MAX_EVALUATIONS - FREE_SURVEY_EVALUATIONS) if solution.status == 0 else solution
                for solution in surveyed[:FREE_FINISHED]]
    best = min(finished, key=lambda solution: solution.cost)
    return start_fit(model, t, u, y, Start("free", tuple(float(v) for v in best.x)), low.size)


def _held_values(model: IdentifiedModel, held: object) -> np.ndarray:
    """The free values that reproduce the held start (the start of the polish)."""
    values = [0.0]
    for effect, state in zip(model.effects, held.effects if held is not None else [None] * len(model.effects),
                            strict=True):
        names = FREE_VALUES[effect.kind]
        if not names:
            continue
        if state is None:
            values.extend([0.0] * len(names))
        elif effect.kind == "wire_thermal":
            values.extend([state.values[0], state.values[2]])
        elif effect.kind == "delay":
            values.append(state.values[1])
        else:
            values.append(state.values[0])
    return np.array(values, dtype=float)


def _bounds(model: IdentifiedModel, t: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of the free values: the turning point and each state within what the record's own input
    could make (the GPI input's range, with half of it again on either side)."""
    v = model.gpi_input(t, u, model.start_state(t, u, Start("held")))
    margin = 0.5 * max(float(np.ptp(v)), 1e-12)
    low, high = [float(np.min(v)) - margin], [float(np.max(v)) + margin]
    current = (float(np.min(u)), float(np.max(u)))
    for effect in model.effects:
        reference = effect.parameters.get("joule_reference_a", 0.0)
        heating = [float(joule_heating(value, reference)) for value in current]
        if effect.kind == "thermal_lag":
            low.append(min(heating[0], 0.0))
            high.append(max(heating[1], 0.0))
        elif effect.kind == "wire_thermal":
            low.extend([0.0, 0.0])
            high.extend([max(heating[1], 1e-12), max(-heating[0], 1e-12)])
        elif effect.kind == "delay":
            low.append(min(current[0], 0.0))
            high.append(max(current[1], 0.0) + (1e-12 if current[1] <= 0.0 else 0.0))
        elif effect.kind == "drift":
            low.append(0.0)
            high.append(ELAPSED_LIMIT_FACTOR * max(float(t[-1] - t[0]), 1e-12))
    return np.array(low), np.array(high)

