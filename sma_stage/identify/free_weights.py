"""The GPI with free density weights (no ROS): the density a10 exp(-a11 r_i) of a fitted model replaced by one
non-negative weight per operator. The output is linear in the weights once the envelopes and thresholds are
fixed, so they are fitted by variable projection: scipy's least_squares searches the envelopes and the threshold
step (a2..a9, a1 held: the scale is the weights'), each evaluation solving the weights by bounded linear least
squares on the operators' outputs. The effects stay as the GPI's fit found them.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.optimize import least_squares, lsq_linear

from sma_stage.errors import InputError
from sma_stage.model import _kernels
from sma_stage.model.forward import shape_arrays
from sma_stage.model.identified import IdentifiedModel, Start

FROM_REST = Start("rest")
FIRST_WEIGHT_FLOOR = 1e-3  # the first weight stays above this fraction of the largest (the inverse divides by it)
SEARCH_SAMPLES = 4000  # the envelopes are searched on a copy thinned to about this many samples
SEARCH_EVALUATIONS = 200
REFUSED_RESIDUAL_FACTOR = 10.0  # a refused trial's residual: this many times the start's, each sample


def operator_outputs(model: IdentifiedModel, t: np.ndarray, u: np.ndarray, start: Start) -> np.ndarray:
    """Each operator's output along a record (rows: samples, columns: operators) [output unit], the record
    starting as `start` says."""
    state = model.start_state(t, u, start)
    v = model.gpi_input(t, u, state)
    theta, thresholds = shape_arrays(model.parameters, model.operators)  # the free weights replace the density
    columns = np.empty((v.size, model.operators))
    for index in range(model.operators):
        unit = np.zeros(model.operators)
        unit[index] = 1.0
        states = np.array(state.operators) if state is not None else np.zeros(model.operators)
        _kernels.play_forward(np.ascontiguousarray(v), theta, thresholds, unit, states, columns[:, index])
    return columns


def output_offset(model: IdentifiedModel, t: np.ndarray, start: Start, u: np.ndarray) -> np.ndarray:
    """What the model's output effects (drift) add to the GPI's output along the record [output unit]."""
    state = model.start_state(t, u, start)
    offset = np.zeros(np.size(t))
    for index, effect in enumerate(model.effects):
        if effect.role == "output":
            offset = offset + effect.offset(np.asarray(t, dtype=float), None if state is None else
                                            state.effects[index])[0]
    return offset


def fit_free_weights(model: IdentifiedModel, t: np.ndarray, u: np.ndarray, y: np.ndarray,
                     start: Start = FROM_REST) -> IdentifiedModel:
    """The model with free non-negative density weights fitted to y [output unit] on the record (t [s], u [A])
    that starts as `start` says, its envelopes and threshold step searched again with them; InputError when the
    model has the rate effect (its thresholds use the density)."""
    if model.effect("rate") is not None:
        raise InputError("free weights do not go with the rate effect")
    t, u, y = (np.asarray(a, dtype=float) for a in (t, u, y))
    thin = max(1, t.size // SEARCH_SAMPLES)
    scale = float(np.max(model.parameters.densities(model.operators)))

    def weighted(x: np.ndarray, rows: slice) -> tuple[IdentifiedModel, np.ndarray, np.ndarray]:
        """The trial model, its best weights and its residual on the rows."""
        trial = replace(model, parameters=model.parameters.replace(**dict(zip(SEARCHED, x, strict=True))))
        columns = operator_outputs(trial, t[rows], u[rows], start)
        target = _target(trial, t[rows], u[rows], y[rows], start)
        weights = _weights(columns, target, scale)
        return trial, weights, columns @ weights - target

    x0 = np.array([getattr(model.parameters, name) for name in SEARCHED])
    at_start = weighted(x0, slice(None, None, thin))[2]
    refused = REFUSED_RESIDUAL_FACTOR * (np.abs(at_start) + float(np.sqrt(np.mean(at_start**2))))

    def residual(x: np.ndarray) -> np.ndarray:
        try:
            return weighted(x, slice(None, None, thin))[2]
        except InputError:  # a trial the model refuses (a threshold step <= 0): worse than the start, the search goes on
            return refused

    try:
        found = least_squares(residual, x0, x_scale="jac", max_nfev=SEARCH_EVALUATIONS)
        x = found.x if found.cost <= 0.5 * float(at_start @ at_start) else x0
    except ValueError:  # scipy refusing a step (residuals not finite): keep the fit's
        x = x0
    trial, weights, _ = weighted(x, slice(None))
    return replace(trial, parameters=trial.parameters.replace(weights=tuple(weights)), state=None)


SEARCHED = ("a2", "a3", "a4", "a5", "a6", "a7", "a8", "a9")


def _target(model: IdentifiedModel, t: np.ndarray, u: np.ndarray, y: np.ndarray, start: Start) -> np.ndarray:
    return y - output_offset(model, t, start, u)


def _weights(columns: np.ndarray, target: np.ndarray, scale: float) -> np.ndarray:
    """The non-negative weights (the first at least FIRST_WEIGHT_FLOOR scale) whose sum of the operators' outputs
    (columns, operator_outputs) fits target best."""
    lower = np.zeros(columns.shape[1])
    lower[0] = FIRST_WEIGHT_FLOOR * scale
    solution = lsq_linear(columns, target, bounds=(lower, np.inf), method="bvls")
    return np.maximum(solution.x, lower)
