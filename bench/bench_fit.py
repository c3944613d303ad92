"""Benchmark of the GPI fit: 100,000 samples with 20 operators, and the speed-up against a plain
scipy least_squares (finite differences over a per-sample NumPy forward model) on a size it finishes.

Run: python bench/bench_fit.py [--samples 100000] [--plain-samples 2000]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from record_results import recorded
from scipy.optimize import least_squares

from sma_stage.identify.fit import fit_gpi, normalized
from sma_stage.identify.initial_guess import initial_guess
from sma_stage.identify.metrics import error_metrics
from sma_stage.model import GPIParameters, forward
from sma_stage.signals import paper_identification_signal

OPERATORS = 20
NOISE = 1e-6  # [m], 0.1 % of the ~1 mm stroke
TRUTH = GPIParameters(a1=0.55e-3, a2=0.55, a3=0.1, a4=0.45e-3, a5=0.5e-3, a6=0.5, a7=-0.05,
                      a8=0.56e-3, a9=0.006e-3, a10=0.13, a11=1.0 / 0.06e-3)


def data(samples: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The paper's decaying sine [A] over 1000 s and the GPI output [m] with white noise."""
    u = paper_identification_signal(np.linspace(0.0, 1000.0, samples))
    y = forward(u, TRUTH, OPERATORS) + np.random.default_rng(seed).normal(0.0, NOISE, samples)
    return u, y


def plain_forward(u: np.ndarray, theta: np.ndarray, operators: int) -> np.ndarray:
    """Eqs 1-5 with a Python loop over samples and the operators vectorised in NumPy."""
    a1, a2, a3, a4, a5, a6, a7, a8, a9, a10, a11 = theta
    r = a9 * np.arange(operators)
    p = a10 * np.exp(-a11 * r)
    z = np.zeros(operators)
    y = np.empty(u.size)
    for k, v in enumerate(u):
        low = a1 * np.tanh(a2 * v + a3) + a4
        high = a5 * np.tanh(a6 * v + a7) + a8
        z = np.maximum(low - r, np.minimum(high + r, z))
        y[k] = p @ z
    return y


def plain_fit(u: np.ndarray, y: np.ndarray, start: GPIParameters) -> tuple[np.ndarray, int]:
    """scipy least_squares (TRF, 2-point finite differences) over all eleven parameters."""
    low = np.array([0, 0, -np.inf, -np.inf, 0, 0, -np.inf, -np.inf, 1e-12, 0, -np.inf])
    solution = least_squares(lambda theta: plain_forward(u, theta, OPERATORS) - y, start.as_array(),
                             bounds=(low, np.inf), method="trf", x_scale="jac")
    return solution.x, int(solution.nfev)


def largest_scale(params: GPIParameters, y: np.ndarray) -> float:
    """Largest of the normalised a1, a5 and largest threshold, in output spans (fit_gpi keeps it <= 1e3)."""
    params = normalized(params, OPERATORS)
    return max(abs(params.a1), abs(params.a5), params.a9 * (OPERATORS - 1)) / float(np.ptp(y))


def row(name: str, samples: int, seconds: float, iterations: str, u: np.ndarray, y: np.ndarray,
        predicted: np.ndarray, params: GPIParameters) -> str:
    metrics = error_metrics(y, predicted)
    return (f"| {name} | {samples} | {seconds:.3f} | {iterations} | {metrics.rms_pct:.4f} | "
            f"{metrics.max_pct:.4f} | {largest_scale(params, y):.3g} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=100_000)
    parser.add_argument("--plain-samples", type=int, default=2_000)
    args = parser.parse_args()

    clock = time.perf_counter()
    fit_gpi(*data(200), operators=OPERATORS)
    warm_up = time.perf_counter() - clock

    print(f"GPI fit benchmark, {OPERATORS} operators, noise {NOISE:g} m, warm-up (numba load/compile) "
          f"{warm_up:.2f} s")
    print("| fit | samples | seconds | iterations, all starts (plain: evaluations) | RMS % | max % | "
          "largest scale [spans] |")
    print("|---|---|---|---|---|---|---|")
    u, y = data(args.samples)
    clock = time.perf_counter()
    result = fit_gpi(u, y, operators=OPERATORS)
    seconds = time.perf_counter() - clock
    print(row("fit_gpi, data-derived multi-start", u.size, seconds, str(result.iterations), u, y,
              result.predicted, result.parameters))

    u, y = data(args.plain_samples, seed=1)
    start = initial_guess(u, y, OPERATORS)
    clock = time.perf_counter()
    single = fit_gpi(u, y, operators=OPERATORS, initial=start)
    single_seconds = time.perf_counter() - clock
    print(row("fit_gpi from the data-derived guess (one start)", u.size, single_seconds, str(single.iterations),
              u, y, single.predicted, single.parameters))
    clock = time.perf_counter()
    multi = fit_gpi(u, y, operators=OPERATORS)
    multi_seconds = time.perf_counter() - clock
    print(row("fit_gpi, data-derived multi-start", u.size, multi_seconds, str(multi.iterations), u, y,
              multi.predicted, multi.parameters))
    clock = time.perf_counter()
    theta, evaluations = plain_fit(u, y, start)
    plain_seconds = time.perf_counter() - clock
    print(row("plain least_squares, finite differences, from the same guess", u.size, plain_seconds,
              f"({evaluations})", u, y, plain_forward(u, theta, OPERATORS), GPIParameters.from_array(theta)))
    print(f"\nspeed-up on {u.size} samples: {plain_seconds / single_seconds:.0f}x from the same start; "
          f"{plain_seconds / multi_seconds:.0f}x for the whole multi-start fit against one plain start")


if __name__ == "__main__":
    with recorded(__file__):
        main()
