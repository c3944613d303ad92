"""Fitting the Bouc-Wen baseline (sma_stage.model.bouc_wen; no ROS): the output is linear in k_x, k_w and the
offset once the lag and the hysteresis's shape (tau, beta, gamma / beta, n) are fixed, so the shape is searched
by scipy's least_squares from a few starts on a thinned copy, each evaluation solving the linear part by bounded
least squares (k_x, k_w >= 0); the best start is polished on every sample.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares, lsq_linear

from sma_stage.errors import InputError
from sma_stage.identify.cancel import check_cancelled
from sma_stage.identify.checks import check_data
from sma_stage.identify.fit import information_criterion
from sma_stage.identify.metrics import ErrorMetrics, error_metrics
from sma_stage.model.bouc_wen import BoucWenModel, BoucWenParameters
from sma_stage.model.checks import checked_record

SEARCH_SAMPLES = 2500
STARTS = ((2.0, 0.3), (10.0, 0.3), (2.0, 1.5), (10.0, 1.5), (40.0, 0.8))  # (tau_s, beta)
BOUNDS = (np.array([np.log(0.05), np.log(1e-3), -1.0, 1.0]), np.array([np.log(500.0), np.log(50.0), 1.0, 3.0]))
EVALUATIONS = 300


@dataclass(frozen=True)
class BoucWenFit:
    """A fitted Bouc-Wen model, its prediction of the record, its errors, the residual sum of squares [output
    unit^2], the BIC and the seconds taken."""

    model: BoucWenModel
    predicted: np.ndarray
    errors: ErrorMetrics
    cost: float
    bic: float
    seconds: float
    parameter_count: int


class _Problem:
    """The search over the shape z = (ln tau, ln beta, gamma / beta, n) on one record."""

    def __init__(self, t: np.ndarray, u: np.ndarray, y: np.ndarray) -> None:
        self.t, self.u, self.y = t, u, y

    def parameters(self, z: np.ndarray, linear: tuple[float, float, float] = (1.0, 0.0, 0.0)) -> BoucWenParameters:
        beta = float(np.exp(z[1]))
        return BoucWenParameters({"tau_s": float(np.exp(z[0])), "k_x": linear[0], "k_w": linear[1],
                                  "offset": linear[2], "beta": beta, "gamma": float(z[2]) * beta, "n": float(z[3])})

    def columns(self, z: np.ndarray) -> np.ndarray:
        """The heating state x, the hysteretic state w and 1, at each sample."""
        x = BoucWenModel(self.parameters(z, (1.0, 0.0, 0.0))).predict(self.t, self.u)
        w = BoucWenModel(self.parameters(z, (0.0, 1.0, 0.0))).predict(self.t, self.u)
        return np.column_stack([x, w, np.ones_like(x)])

    def linear(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(k_x, k_w, offset) fitting y best for the shape z, and the residual."""
        columns = self.columns(z)
        solution = lsq_linear(columns, self.y, bounds=([0.0, 0.0, -np.inf], np.inf), method="bvls")
        return solution.x, columns @ solution.x - self.y

    def residual(self, z: np.ndarray) -> np.ndarray:
        check_cancelled()
        return self.linear(z)[1]


def fit_bouc_wen(t: np.ndarray, u: np.ndarray, y: np.ndarray, output_unit: str = "m") -> BoucWenFit:
    """The Bouc-Wen model that best predicts y [output unit] from u [A] at times t [s], from a stage at rest;
    InputError (one line) when the record cannot identify it."""
    started = time.perf_counter()
    t, u = checked_record(t, u)
    u, y = check_data(u, y)
    thin = max(1, t.size // SEARCH_SAMPLES)
    search, problem = _Problem(t[::thin], u[::thin], y[::thin]), _Problem(t, u, y)
    found = []
    for tau_s, beta in STARTS:
        z0 = np.array([np.log(tau_s), np.log(beta), 0.0, 1.0])
        try:
            found.append(least_squares(search.residual, z0, bounds=BOUNDS, max_nfev=EVALUATIONS))
        except (ValueError, InputError):
            continue
    if not found:
        raise InputError("the Bouc-Wen model could not be fitted to this record")
    best = min(found, key=lambda result: result.cost)
    z = least_squares(problem.residual, best.x, bounds=BOUNDS, max_nfev=EVALUATIONS).x if thin > 1 else best.x
    linear, residual = problem.linear(z)
    model = BoucWenModel(problem.parameters(z, tuple(float(value) for value in linear)), output_unit)
    predicted, end = model.run(t, u)
    cost = float(np.sum(residual**2))
    count = model.parameter_count
    model = BoucWenModel(model.parameters, output_unit, end, {"identified_samples": int(t.size)})
    return BoucWenFit(model, predicted, error_metrics(y, predicted), cost, information_criterion(cost, t.size, count),
                      time.perf_counter() - started, count)
