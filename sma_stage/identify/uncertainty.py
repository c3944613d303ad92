"""The GPI fit's sensitivities and standard errors: the analytic Jacobian of the model's output and the
parameters' spread sigma^2 (J^T J)^-1 in the normalised form."""

from __future__ import annotations

import numpy as np

from sma_stage.identify._sensitivity import SENSITIVITY_COLUMNS, householder_r, play_sensitivities
from sma_stage.model.checks import as_signal
from sma_stage.model.forward import initial_states
from sma_stage.model.parameters import PARAMETER_NAMES, GPIParameters, check_operators

NULL_TOLERANCE = 1e-10  # singular values of the column-scaled Jacobian below this (relative) are blind spots


def model_jacobian(u: np.ndarray, params: GPIParameters, operators: int,
                   initial: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(output y [output unit], dy/d(a1..a11) as an (N, 11) array) in one compiled pass."""
    v = as_signal(u, "input")
    rows = sensitivities(v, params.as_array(), check_operators(operators),
                          initial_states(params, operators, initial))
    s, sens = rows[0], rows[1:]
    jac = np.empty((v.size, 11))
    jac[:, :9] = params.a10 * sens[:9].T
    jac[:, 9] = s
    jac[:, 10] = params.a10 * sens[9]
    return params.a10 * s, jac


def sensitivities(v: np.ndarray, theta: np.ndarray, operators: int, states: np.ndarray | None = None,
                   out: np.ndarray | None = None) -> np.ndarray:
    """Rows s (y = a10 s) and ds/d(a1..a9, a11), shape (11, N)."""
    out = np.empty((1 + SENSITIVITY_COLUMNS, v.size)) if out is None else out
    states = np.zeros(operators) if states is None else states.copy()
    play_sensitivities(v, np.ascontiguousarray(theta, dtype=float), operators, states, out)
    return out


def standard_errors(u: np.ndarray, params: GPIParameters, operators: int, regressors: np.ndarray,
                     cost: float, held: frozenset[str] = frozenset()) -> tuple[dict[str, float], np.ndarray]:
    """sigma^2 (J^T J)^-1, sigma^2 = SSR / (N - p), in the normalised form: free a1..a9, a11 and c;
    a10 = 1 / sum exp(-a11 r_i) follows from them (delta method). Infinite where the data cannot tell
    a parameter apart (e.g. a constant regressor column against a common shift of a4 and a8).
    The design's columns are built in place in one (11 + regressors) x N array (its only copy of N rows)."""
    v = as_signal(u, "input")
    m = regressors.shape[1]
    rows = np.empty((1 + SENSITIVITY_COLUMNS + m, v.size))
    sensitivities(v, params.as_array(), check_operators(operators), initial_states(params, operators, None),
                   out=rows[:1 + SENSITIVITY_COLUMNS])
    indices = np.arange(operators)
    weights = np.exp(-params.a11 * params.a9 * indices)
    total = weights.sum()
    a10_gradient = np.zeros(10)  # d a10 / d(a1..a9, a11)
    a10_gradient[8] = params.a11 * (indices @ weights) / total**2
    a10_gradient[9] = params.a9 * (indices @ weights) / total**2
    shape = rows[0]  # dy/da10 = s, carried into each free column through a10's gradient
    for column in range(SENSITIVITY_COLUMNS):
        rows[1 + column] *= params.a10
        rows[1 + column] += a10_gradient[column] * shape
    rows[1 + SENSITIVITY_COLUMNS:] = regressors.T
    columns = SENSITIVITY_COLUMNS + m
    functions = np.vstack([np.eye(columns), np.r_[a10_gradient, np.zeros(columns - 10)]])
    free_names = [name for name in PARAMETER_NAMES if name != "a10"]
    known = [free_names.index(name) for name in held]  # held: no column, and no part in a10's spread
    rows[[1 + column for column in known]] = 0.0
    functions[:, known] = 0.0
    variances = _variances(rows[1:], cost / max(u.size - columns + len(known), 1), functions)
    errors = {name: float(np.sqrt(variances[k])) for k, name in enumerate(free_names)}
    errors["a10"] = float(np.sqrt(variances[-1]))
    return {name: errors[name] for name in PARAMETER_NAMES}, np.sqrt(variances[10:-1])


def _variances(columns: np.ndarray, sigma2: float, functions: np.ndarray) -> np.ndarray:
    """sigma^2 g^T (J^T J)^+ g for each row g of functions (in J's column units), from J's R factor with
    columns scaled to unit norm; infinite for a g that changes along a direction J does not see.
    columns: J transposed (one row per column of J, N long), overwritten."""
    norms = np.sqrt(np.einsum("ij,ij->i", columns, columns))
    norms[norms == 0.0] = 1.0
    columns /= norms[:, None]
    r = householder_r(columns, np.arange(columns.shape[0], dtype=np.int64))
    _, singular, vt = np.linalg.svd(r)
    seen = singular > NULL_TOLERANCE * singular[0]
    scaled = functions / norms
    variances = sigma2 * np.sum((scaled @ vt[seen].T / singular[seen]) ** 2, axis=1)
    unseen = np.max(np.abs(scaled @ vt[~seen].T), axis=1, initial=0.0)
    variances[unseen > 1e-6 * np.linalg.norm(scaled, axis=1)] = np.inf
    return variances
