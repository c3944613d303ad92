"""Tests of a model residual e against its 95 % bands: whiteness, correlation with the input, its rate,
the lagged input and time.

The bands are those of the null hypothesis "the model is adequate": e is white and independent of
the input. Under it, any normalised correlation of e with another sequence has standard deviation
1/sqrt(N), whatever that sequence's colour, so the band is +-1.96/sqrt(N); the lagged-input test takes
the largest of 2L+1 correlations, so its band is Bonferroni-widened to keep 95 % overall. On slow data a misfit
always colours e, so a failed test says *that* the model lacks something; which correlation stands
out, its sign and its lag say *what*, and the refit of each candidate decides.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import correlate
from scipy.stats import chi2, norm

from sma_stage.errors import InputError

CONFIDENCE = 0.95
Z_95 = 1.959963984540054
MAX_AUTOCORRELATION_LAGS = 20
LAG_RANGE_FRACTION = 0.1  # lagged-input search: +-this fraction of the record
MIN_SAMPLES = 10
TEST_NAMES: tuple[str, ...] = ("whiteness", "input", "input_rate", "lagged_input", "time")


@dataclass(frozen=True)
class ResidualCheck:
    """One test: its statistic, the threshold it is held against, and whether it passed."""

    name: str
    statistic: str
    value: float
    threshold: float
    passed: bool
    lag_s: float | None = None

    @property
    def ratio(self) -> float:
        """|value| / threshold: above 1 the test fails; larger means the test points harder."""
        return abs(self.value) / self.threshold if self.threshold > 0.0 else float("inf")

    def evidence(self) -> str:
        """'value and its threshold' in one line, as in the JSON report."""
        verdict = "passed" if self.passed else "failed"
        at = f" at lag {self.lag_s:+.4g} s" if self.lag_s is not None else ""
        if self.name == "whiteness":
            return f"{self.statistic} = {self.value:.4g} vs {self.threshold:.4g} (chi2 {CONFIDENCE:.0%}): {verdict}"
        return f"{self.statistic} = {self.value:+.3f}{at} vs band +-{self.threshold:.3f} ({CONFIDENCE:.0%}): {verdict}"


@dataclass(frozen=True)
class ResidualTests:
    """All tests of one residual, with the correlation curves behind them (for plots)."""

    checks: dict[str, ResidualCheck]
    band: float
    autocorrelation_lags_s: np.ndarray
    autocorrelation: np.ndarray
    cross_correlation_lags_s: np.ndarray
    cross_correlation: np.ndarray

    @property
    def passed(self) -> bool:
        """True when every test passed."""
        return all(check.passed for check in self.checks.values())

    def evidence(self) -> dict[str, str]:
        """test name -> 'value and its threshold' string."""
        return {name: check.evidence() for name, check in self.checks.items()}

    def to_dict(self) -> dict[str, dict[str, object]]:
        """The checks as plain values (JSON)."""
        return {
            name: {"statistic": c.statistic, "value": c.value, "threshold": c.threshold, "passed": c.passed,
                   **({"lag_s": c.lag_s} if c.lag_s is not None else {})}
            for name, c in self.checks.items()
        }


def _centred(x: np.ndarray) -> np.ndarray:
    return x - np.mean(x)


def correlation(e: np.ndarray, x: np.ndarray) -> float:
    """Normalised correlation of e and x at lag 0 (0 when either is constant)."""
    a, b = _centred(e), _centred(x)
    norm = np.sqrt((a @ a) * (b @ b))
    return float(a @ b / norm) if norm > 0.0 else 0.0


def autocorrelation(e: np.ndarray, max_lag: int) -> np.ndarray:
    """rho(k) = sum_t e_t e_{t+k} / sum_t e_t^2 for k = 1..max_lag (biased estimator, centred e)."""
    a = _centred(e)
    energy = a @ a
    if energy <= 0.0:
        return np.zeros(max_lag)
    return np.array([a[:-k] @ a[k:] / energy for k in range(1, max_lag + 1)])


def cross_correlation(e: np.ndarray, x: np.ndarray, max_lag: int) -> tuple[np.ndarray, np.ndarray]:
    """(lags k = -max_lag..max_lag, r(k) = sum_t e_t x_{t-k} / (N sd_e sd_x)): r(k) > 0 at k > 0 means e
    follows x k samples later."""
    a, b = _centred(e), _centred(x)
    norm = np.sqrt((a @ a) * (b @ b))
    lags = np.arange(-max_lag, max_lag + 1)
    if norm <= 0.0:
        return lags, np.zeros(lags.size)
    full = correlate(a, b, mode="full", method="auto")  # index N-1+k holds sum_t a_{t+k} b_t
    centre = a.size - 1
    return lags, full[centre + lags] / norm


def ljung_box(rho: np.ndarray, samples: int) -> float:
    """Q = N (N + 2) sum_k rho_k^2 / (N - k), chi2 with len(rho) degrees of freedom for white e."""
    k = np.arange(1, rho.size + 1)
    return float(samples * (samples + 2) * np.sum(rho**2 / (samples - k)))


def residual_tests(e: np.ndarray, u: np.ndarray, t: np.ndarray, max_lag_s: float | None = None) -> ResidualTests:
    """Run every test on the residual e [output unit] against the input u [A] sampled at times t [s]."""
    e, u, t = (np.asarray(a, dtype=float).reshape(-1) for a in (e, u, t))
    n = e.size
    if not n == u.size == t.size or n < MIN_SAMPLES:
        raise InputError(f"residual, input and time must be equally long with at least {MIN_SAMPLES} samples")
    if not (np.all(np.isfinite(e)) and np.all(np.isfinite(u)) and np.all(np.isfinite(t))):
        raise InputError("residual, input and time must be finite")
    if np.any(np.diff(t) <= 0.0):
        raise InputError("time must increase from sample to sample")
    step = float(np.median(np.diff(t)))
    band = float(Z_95 / np.sqrt(n))
    acf_lags = min(MAX_AUTOCORRELATION_LAGS, n // 4)
    rho = autocorrelation(e, acf_lags)
    q = ljung_box(rho, n)
    q_threshold = float(chi2.ppf(CONFIDENCE, acf_lags))
    if max_lag_s is None:
        max_lag_s = LAG_RANGE_FRACTION * float(t[-1] - t[0])
    ccf_lags = int(np.clip(round(max_lag_s / step), 1, n // 4))
    lags, ccf = cross_correlation(e, u, ccf_lags)
    strongest = int(np.argmax(np.abs(ccf)))
    lagged_band = float(norm.isf((1.0 - CONFIDENCE) / (2.0 * lags.size))) / np.sqrt(n)

    def lag0(name: str, statistic: str, x: np.ndarray) -> ResidualCheck:
        value = correlation(e, x)
        return ResidualCheck(name, statistic, value, band, bool(abs(value) <= band))

    checks = {
        "whiteness": ResidualCheck("whiteness", f"Ljung-Box Q ({acf_lags} lags)", q, q_threshold,
                                   bool(q <= q_threshold)),
        "input": lag0("input", "r(e, u)", u),
        "input_rate": lag0("input_rate", "r(e, du/dt)", np.gradient(u, t)),
        "lagged_input": ResidualCheck("lagged_input", f"max r(e, u lagged) over {lags.size} lags",
                                      float(ccf[strongest]), lagged_band, bool(abs(ccf[strongest]) <= lagged_band),
                                      lag_s=float(lags[strongest] * step)),
        "time": lag0("time", "r(e, t)", t),
    }
    return ResidualTests(checks, band, np.arange(1, acf_lags + 1) * step, rho, lags * step, ccf)
