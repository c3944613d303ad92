"""The model watch's memory of the residual along the stage's path (no ROS): where the stage has been (the
measured position and low-passes of it), the residual it had there on each pass, and what a new sample's
residual is expected to be there; with the robust statistics the watch's tests scale by."""

from __future__ import annotations

import math

import numba
import numpy as np
from scipy.spatial import cKDTree
from scipy.special import gammaincinv

MIN_JUDGED = 5  # the path test judges a window with at least this many samples it could compare
MIN_HELD_OUT_WINDOWS = 5  # calibration windows compared with their other passes that measure the bias test's scale
SCALE_CONFIDENCE = 0.95  # the bias test's scale, measured on few windows, is widened to this upper confidence bound
HELD_OUT_OUTLIER = 6.0  # a calibration window whose mean is this many robust standard deviations out is left out
PATH_TIME_CONSTANTS_S = (2.0, 8.0, 30.0, 120.0)  # the low-passes of the measured position that summarise its path
PATH_NEIGHBOURS = 16  # remembered samples looked at for each one judged (from two passes or more)
MEMORY_RATE_HZ = 2.0  # the memory keeps at most this many samples per second of stage time
PASS_GAP_S = 20.0  # remembered samples this far apart [s] are separate passes along the path
MIN_PASSES = 3  # the memory judges a sample only where it holds this many passes that agreed ...
PASS_AGREEMENT = 1.0  # ... within this fraction of the reference r0
MAD_TO_SIGMA = 1.0 / 0.6745  # a normal variable's standard deviation over its median absolute deviation
MIN_FEATURE_SPREAD_M = 1e-9  # a feature that did not move in the memory is scaled as if it spread this much [m]


@numba.njit(cache=True, nogil=True)
def _low_passes(t: np.ndarray, u: np.ndarray, taus: np.ndarray, last_t: float, state: np.ndarray,
                out: np.ndarray) -> None:
    """Per sample, the current and its first-order low-passes (time constants taus [s]) into out's rows; state
    holds the low-passes at last_t [s] (NaN: start them at the first current) and is advanced in place."""
    for k in range(t.size):
        if math.isnan(state[0]):
            state[:] = u[k]
        else:
            dt = t[k] - last_t
            for j in range(taus.size):
                a = math.exp(-dt / taus[j])
                state[j] = a * state[j] + (1.0 - a) * u[k]
        last_t = t[k]
        out[k, 0] = u[k]
        out[k, 1:] = state


@numba.njit(cache=True, nogil=True)
def _revisits(index: np.ndarray, times: np.ndarray, residuals: np.ndarray, gap_s: float, tolerance: float,
              min_passes: int, reference: np.ndarray, spread: np.ndarray) -> None:
    """Per row of neighbour indices (len(times) where none): the remembered residual there and the variance a new
    residual there has about it with nothing changed, NaN unless the neighbours come from at least min_passes
    passes (runs of samples more than gap_s [s] apart) whose mean residuals agree within tolerance [m]; then
    the mean of the passes' means, and their variance (ddof 1) times 1 + 1/passes."""
    rows, columns = index.shape
    picked = np.empty(columns)
    means = np.empty(columns)
    for row in range(rows):
        reference[row] = np.nan
        spread[row] = np.nan
        count = 0
        for column in range(columns):
            if index[row, column] < times.size:
                picked[count] = index[row, column]
                count += 1
        if count < 2:
            continue
        order = np.argsort(times[picked[:count].astype(np.int64)])
        passes = 0
        pass_sum, pass_count, last_t = 0.0, 0, -np.inf
        for position in range(count + 1):
            if position < count:
                sample = int(picked[order[position]])
                time = times[sample]
            if position == count or time - last_t > gap_s:
                if pass_count:
                    means[passes] = pass_sum / pass_count
                    passes += 1
                pass_sum, pass_count = 0.0, 0
            if position < count:
                pass_sum += residuals[sample]
                pass_count += 1
                last_t = time
        if passes < min_passes or means[:passes].max() - means[:passes].min() > tolerance:
            continue
        mean = means[:passes].mean()
        reference[row] = mean
        spread[row] = np.sum((means[:passes] - mean) ** 2) / (passes - 1) * (1.0 + 1.0 / passes)


class PathMemory:
    """The residual [m] remembered against the stage's path: `features` of each sample from the measured
    position; `remember` until `build`; then `innovations` of new samples against it, where the memory holds
    the path at least twice and the residual agreed. time_constants_s: the position's low-passes that summarise
    the path [s]."""

    def __init__(self, time_constants_s: tuple[float, ...] = PATH_TIME_CONSTANTS_S) -> None:
        self._taus = np.array(time_constants_s, dtype=float)
        self._state = np.full(self._taus.size, np.nan)
        self._last_t = 0.0
        self._remembered: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._tree: cKDTree | None = None
        self._times = self._residuals = np.empty(0)
        self.noise_m = 0.0

    @property
    def built(self) -> bool:
        return self._tree is not None

    def features(self, t_s: np.ndarray, position_m: np.ndarray) -> np.ndarray:
        """The path at each sample (rows: the position and its low-passes [m]), carried on from the last call."""
        out = np.empty((t_s.size, self._taus.size + 1))
        _low_passes(t_s, position_m, self._taus, self._last_t, self._state, out)
        if t_s.size:
            self._last_t = float(t_s[-1])
        return out

    def remember(self, t_s: np.ndarray, features: np.ndarray, residual: np.ndarray) -> None:
        self._remembered.append((t_s, features, residual))

    def build(self) -> bool:
        """Build the memory from what was remembered (False when it holds too little to judge by)."""
        if not self._remembered:
            return False
        times, features, residuals = (np.concatenate(column) for column in zip(*self._remembered, strict=True))
        self._remembered = []
        if residuals.size < 2 * PATH_NEIGHBOURS:
            return False
        self.noise_m = float(MAD_TO_SIGMA * np.median(np.abs(np.diff(residuals))) / math.sqrt(2.0))
        kept = thinned_to_rate(times, MEMORY_RATE_HZ)
        features, self._times, self._residuals = features[kept], times[kept], residuals[kept]
        self._scale = max(float(features[:, 0].std()), MIN_FEATURE_SPREAD_M)
        self._tree = cKDTree(features / self._scale)
        return True

    def innovations(self, features: np.ndarray, residual: np.ndarray, radius: float, gap_s: float,
                    tolerance_m: float) -> tuple[np.ndarray, np.ndarray]:
        """(each residual less the residual remembered where the path was the same (within radius) on at least two
        passes that agreed within tolerance_m [m]; the variance of that with nothing changed [m^2], from how the
        passes differed), NaN where the memory cannot say."""
        _, index = self._tree.query(features / self._scale, k=PATH_NEIGHBOURS, distance_upper_bound=radius)
        reference, spread = np.empty(residual.size), np.empty(residual.size)
        _revisits(np.atleast_2d(index), self._times, self._residuals, gap_s, tolerance_m, MIN_PASSES, reference,
                  spread)
        return residual - reference, spread

    def held_out_windows(self, window_s: float, radius: float, gap_s: float, tolerance_m: float,
                         min_coverage: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(the index of each window_s [s] of the remembered samples, its mean innovation [m], their RMS [m]), each
        sample compared with its PATH_NEIGHBOURS nearest of the other passes (the samples within gap_s of it left
        out), as a judged sample is compared with the memory: what a window's innovations do with nothing changed.
        Windows with fewer than MIN_JUDGED or min_coverage of their samples compared are left out."""
        samples = self._times.size
        _, index = self._tree.query(self._tree.data, k=2 * PATH_NEIGHBOURS, distance_upper_bound=radius)
        found = index < samples
        own_pass = np.abs(self._times[np.where(found, index, 0)] - self._times[:, None]) <= gap_s
        index = _nearest_kept(np.where(found & ~own_pass, index, samples), samples, PATH_NEIGHBOURS)
        reference, spread = np.empty(samples), np.empty(samples)
        _revisits(index, self._times, self._residuals, gap_s, tolerance_m, MIN_PASSES, reference, spread)
        innovation = self._residuals - reference
        slot = np.floor((self._times - self._times[0]) / window_s).astype(np.int64)
        slots, means, sizes = [], [], []
        for window in np.unique(slot):
            values = innovation[slot == window]
            compared = values[np.isfinite(values)]
            if compared.size >= MIN_JUDGED and compared.size >= min_coverage * values.size:
                slots.append(int(window))
                means.append(float(np.mean(compared)))
                sizes.append(float(np.sqrt(np.mean(np.square(compared)))))
        return np.array(slots, dtype=np.int64), np.array(means), np.array(sizes)


def _nearest_kept(index: np.ndarray, missing: int, count: int) -> np.ndarray:
    """Per row of neighbour indices (nearest first, `missing` where left out), the first `count` not left out."""
    order = np.argsort(index == missing, axis=1, kind="stable")[:, :count]
    return np.take_along_axis(index, order, axis=1)


def inliers(values: np.ndarray) -> np.ndarray:
    """Which values lie within HELD_OUT_OUTLIER robust standard deviations (MAD_TO_SIGMA times the median |value|)
    of 0."""
    magnitudes = np.abs(np.asarray(values, dtype=float))
    return magnitudes <= HELD_OUT_OUTLIER * MAD_TO_SIGMA * np.median(magnitudes) if magnitudes.size else \
        np.ones(0, dtype=bool)


def rms_without_outliers(values: np.ndarray) -> float:
    """The RMS of the inliers of values; 0 when fewer than MIN_HELD_OUT_WINDOWS are left."""
    values = np.asarray(values, dtype=float)
    kept = values[inliers(values)]
    return float(np.sqrt(np.mean(np.square(kept)))) if kept.size >= MIN_HELD_OUT_WINDOWS else 0.0


def lag_one_correlation(slots: np.ndarray, values: np.ndarray) -> float:
    """The lag-one correlation of values (each window's, slots their indices) over adjacent windows, taken about 0
    and at least 0; 0 with fewer than MIN_HELD_OUT_WINDOWS adjacent pairs."""
    pairs = np.flatnonzero(np.diff(slots) == 1)
    if pairs.size < MIN_HELD_OUT_WINDOWS:
        return 0.0
    first, second = values[pairs], values[pairs + 1]
    return max(0.0, float(np.sum(first * second) / max(math.sqrt(np.sum(first**2) * np.sum(second**2)), 1e-300)))


def in_a_row_factor(rho: float, count: int) -> float:
    """How much wider the mean of `count` consecutive windows spreads than `count` independent windows' would, for
    window values correlated as an AR(1) with lag-one correlation rho: sqrt(1 + 2/count sum_k (count - k) rho^k)."""
    return math.sqrt(1.0 + 2.0 / count * sum((count - lag) * rho**lag for lag in range(1, count)))


def scale_confidence_factor(rho: float, windows: int) -> float:
    """How much to widen the RMS of `windows` window values so that it is at least the true scale with
    SCALE_CONFIDENCE: sqrt(n / q), q the chi-square quantile 1 - SCALE_CONFIDENCE on n degrees of freedom,
    n = windows (1 - rho^2) / (1 + rho^2) for their lag-one correlation rho (an AR(1)'s mean square varies as that
    many independent squares' would), at least 1; 1 with fewer than MIN_HELD_OUT_WINDOWS windows."""
    if windows < MIN_HELD_OUT_WINDOWS:
        return 1.0
    degrees = max(1.0, windows * (1.0 - rho**2) / (1.0 + rho**2))
    return math.sqrt(degrees / (2.0 * float(gammaincinv(0.5 * degrees, 1.0 - SCALE_CONFIDENCE))))


def thinned_to_rate(t_s: np.ndarray, rate_hz: float) -> np.ndarray:
    """Indices of the samples kept when at most rate_hz per second of t_s [s] are: the first of each 1/rate_hz."""
    slots = np.floor(t_s * rate_hz)
    return np.flatnonzero(np.r_[True, slots[1:] != slots[:-1]])
