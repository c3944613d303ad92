"""The checks a record passes before it is identified: finite, long enough, in range, moving over much of
the record, rising with the input; and the extra regressor columns a fit may take."""

from __future__ import annotations

import numpy as np

from sma_stage.errors import InputError
from sma_stage.model.checks import as_signal

MIN_SAMPLES = 20
INPUT_MAGNITUDES_A = (1e-6, 1e6)  # the largest |input| a record may have: a current in A
OUTPUT_MAGNITUDES = (1e-100, 1e100)  # the largest |output|, any unit: the fit is scale-free within these


def check_regressors(regressors: np.ndarray | None, samples: int, columns: int | None = None) -> np.ndarray:
    """The regressor columns as an (N, m) float array (m = 0 for None); InputError unless finite, N = samples
    rows, `columns` columns when given, and (for a fit) linearly independent."""
    if regressors is None:
        return np.zeros((samples, 0))
    try:
        matrix = np.array(regressors, dtype=float)
    except (TypeError, ValueError):
        raise InputError("regressors must be numeric") from None
    if matrix.ndim == 1:
        matrix = matrix[:, None]
    if matrix.ndim != 2 or matrix.shape[0] != samples:
        raise InputError(f"regressors must be an (N, m) array with N = {samples}, got shape {matrix.shape}")
    if columns is not None and matrix.shape[1] != columns:
        raise InputError(f"regressors have {matrix.shape[1]} columns, the fit has {columns}")
    if not np.all(np.isfinite(matrix)):
        raise InputError("regressors contain a non-finite value")
    if columns is None and matrix.shape[1]:
        singular = np.linalg.svd(matrix / np.maximum(np.linalg.norm(matrix, axis=0), 1e-300), compute_uv=False)
        if singular[-1] <= 1e-10 * singular[0]:
            raise InputError("regressor columns are linearly dependent (or one is all zeros)")
    return matrix


MOTION_PARTS = 50  # the record is cut into this many parts (fewer for a short record: at least 4 samples each)
MOTION_SHARE = 0.05  # a part moves when its output spans at least this share of the record's span
MIN_MOVING_SHARE = 0.10  # of the parts; a record moving in fewer does not excite the stage


def moving_parts(y: np.ndarray) -> tuple[int, int]:
    """(moving, all): the record cut into up to MOTION_PARTS parts, how many move over MOTION_SHARE of its span."""
    parts = np.array_split(y, max(min(MOTION_PARTS, y.size // 4), 1))
    moving = sum(float(np.ptp(part)) >= MOTION_SHARE * float(np.ptp(y)) for part in parts)
    return moving, len(parts)


def check_motion(y: np.ndarray) -> None:
    """InputError (one line) when the output moves over MOTION_SHARE of its span in fewer than MIN_MOVING_SHARE
    of the record's parts: a stage the input moved once, or a record mostly of a stage at rest."""
    moving, parts = moving_parts(y)
    if moving < MIN_MOVING_SHARE * parts:
        raise InputError(f"no excitation: the output moved over {100 * MOTION_SHARE:g} % of its span in only "
                         f"{100 * moving / parts:.0f} % of the record ({moving} of {parts} parts); excite "
                         "over a wider current range, or record only while the stage is excited")


def check_data(u: np.ndarray, y: np.ndarray, regressors: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Input [A] and output as float arrays, refused (InputError) unless fit for identification: finite,
    equal lengths, at least MIN_SAMPLES, both varying, the output moving over much of the record
    (check_motion), and the output (less what the regressor columns explain) rising with the input."""
    u = as_signal(u, "input")
    y = as_signal(y, "output")
    if u.size != y.size:
        raise InputError(f"input and output differ in length ({u.size} and {y.size} samples)")
    if u.size < MIN_SAMPLES:
        raise InputError(f"too few samples to identify the model: {u.size} (at least {MIN_SAMPLES})")
    for name, values, (low, high), hint in (
            ("input", u, INPUT_MAGNITUDES_A, "give the current in A"),
            ("output", y, OUTPUT_MAGNITUDES, "rescale the column (gpi_tool --unit names its unit)")):
        largest = float(np.max(np.abs(values)))
        if largest != 0.0 and not low <= largest <= high:
            raise InputError(f"the {name}'s largest magnitude is {largest:.3g}, outside {low:g} to {high:g}: {hint}")
        if np.ptp(values) <= 1e-12 * largest:
            raise InputError(f"no excitation: the {name} is constant")
    check_motion(y)
    trend = y
    if regressors is not None and np.size(regressors):
        trend = y - regressors @ np.linalg.lstsq(regressors, y, rcond=None)[0]
    if np.cov(u, trend)[0, 1] <= 0.0:
        raise InputError("the output falls as the input rises; the GPI model is increasing (negate the output)")
    return u, y
