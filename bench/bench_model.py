"""Benchmark of the GPI model core; prints tables.

    .venv/bin/python bench/bench_model.py [--samples 1000000] [--operators 50]

1. Forward model throughput (operator-samples per second) against a plain per-sample NumPy loop,
   both in this run (target: >= 5e8 /s and >= 50x).
2. Streaming exact inverse, one sample per call as the compensator calls it, 20 operators: latency
   percentiles (target p99 <= 20 us) and memory after short and long histories (must not grow).
3. How far the analytic inverse (eqs 6-8) is from exact as the envelopes gl and gr move apart.
"""

from __future__ import annotations

import argparse
import time
import tracemalloc

import numpy as np
from record_results import recorded

from sma_stage.model import GPIInverseStream, GPIParameters, forward, inverse
from sma_stage.signals import paper_identification_signal, paper_validation_signal

STAGE = GPIParameters(a1=0.5e-3, a2=0.6, a3=0.1, a4=0.0, a5=0.5e-3, a6=0.6, a7=-0.2, a8=0.05e-3,
                      a9=0.05e-3, a10=0.2, a11=5e3)


def plain_numpy_forward(v: np.ndarray, params: GPIParameters, operators: int) -> np.ndarray:
    """The per-sample loop a MATLAB-style script would write, vectorised over operators only."""
    r, p = params.thresholds(operators), params.densities(operators)
    gl, gr = params.envelope_left(v), params.envelope_right(v)
    z = np.zeros(operators)
    out = np.empty_like(v)
    for k in range(v.size):
        z = np.maximum(gl[k] - r, np.minimum(gr[k] + r, z))
        out[k] = p @ z
    return out


def best_time(function, repeats: int) -> float:
    """Smallest wall time of several calls [s]."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return min(times)


def forward_table(samples: int, operators: int) -> None:
    """Compiled forward against the plain loop, on the same input."""
    t = np.linspace(0.0, 1000.0, samples)
    v = paper_identification_signal(t)
    forward(v[:100], STAGE, operators)
    compiled = best_time(lambda: forward(v, STAGE, operators), 5)
    plain_samples = min(samples, 200_000)
    plain = best_time(lambda: plain_numpy_forward(v[:plain_samples], STAGE, operators), 1)
    same = np.max(np.abs(forward(v[:plain_samples], STAGE, operators)
                         - plain_numpy_forward(v[:plain_samples], STAGE, operators)))
    compiled_rate = samples * operators / compiled
    plain_rate = plain_samples * operators / plain
    print(f"\nForward model, {operators} operators (max |compiled - plain| = {same:.1e})")
    print("| implementation | samples | time [s] | operator-samples/s |\n|---|---|---|---|")
    print(f"| compiled (numba) | {samples:,} | {compiled:.4f} | {compiled_rate:.3e} |")
    print(f"| plain NumPy per-sample loop | {plain_samples:,} | {plain:.3f} | {plain_rate:.3e} |")
    print(f"| ratio compiled / plain | | | {compiled_rate / plain_rate:.0f}x |")


def stream_latencies(stream: GPIInverseStream, targets: np.ndarray) -> np.ndarray:
    """Wall time of each step() call [us]."""
    latencies = np.empty(targets.size)
    clock = time.perf_counter_ns
    for k, target in enumerate(targets):
        start = clock()
        stream.step(target)
        latencies[k] = (clock() - start) / 1e3
    return latencies


def streaming_table(operators: int = 20, samples: int = 100_000) -> None:
    """Latency percentiles of the streaming inverses and traced memory after short and long runs."""
    t = np.linspace(0.0, 4000.0, samples)
    targets = forward(paper_validation_signal(t), STAGE, operators)
    print(f"\nStreaming inverse, {operators} operators, {samples:,} calls of step()")
    print("| method | p50 [us] | p99 [us] | p99.9 [us] | max [us] |\n|---|---|---|---|---|")
    for method in ("exact", "analytic"):
        stream = GPIInverseStream(STAGE, operators, method=method, input_range=(-5.0, 5.0))
        stream_latencies(stream, targets[:1000])
        stream.reset()
        latency = stream_latencies(stream, targets)
        p50, p99, p999 = np.percentile(latency, [50, 99, 99.9])
        print(f"| {method} | {p50:.2f} | {p99:.2f} | {p999:.2f} | {latency.max():.1f} |")
    print("\n| history [steps] | traced memory held by the stream [bytes] |\n|---|---|")
    for history in (1_000, samples):
        tracemalloc.start()
        stream = GPIInverseStream(STAGE, operators, input_range=(-5.0, 5.0))
        for target in targets[:history]:
            stream.step(target)
        held, _ = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        print(f"| {history:,} | {held:,} |")


def analytic_table(operators: int = 10) -> None:
    """Analytic-inverse error (forward(analytic inverse(y)) - y) as gr's centre moves away from gl's."""
    print(f"\nAnalytic inverse (eqs 6-8) against exact, {operators} operators, the paper's decaying sine")
    print("| a7 - a3 (envelope shift) | max error [% of span] | rms error [% of span] | exact max [% of span] |")
    print("|---|---|---|---|")
    for shift in (0.0, 0.1, 0.3, 0.6, 1.0):
        params = STAGE.replace(a5=STAGE.a1, a6=STAGE.a2, a7=STAGE.a3 - shift, a8=STAGE.a4)
        target = forward(paper_identification_signal(np.linspace(0.0, 1000.0, 5000)), params, operators)
        errors = {}
        for method in ("analytic", "exact"):
            achieved = inverse(target, params, operators, method=method, full_output=True).output
            errors[method] = 100.0 * np.abs(achieved - target) / np.ptp(target)
        analytic = errors["analytic"]
        print(f"| {-shift:+.1f} | {analytic.max():.3g} | {np.sqrt(np.mean(analytic**2)):.3g} "
              f"| {errors['exact'].max():.1e} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=1_000_000)
    parser.add_argument("--operators", type=int, default=50)
    args = parser.parse_args()
    forward_table(args.samples, args.operators)
    streaming_table()
    analytic_table()


if __name__ == "__main__":
    with recorded(__file__):
        main()
