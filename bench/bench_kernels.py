"""Benchmark of the GPI fit's compiled kernels, per sample, at the sizes the diagnosis calls them with: the play
operators' sensitivities (1, 5 and 20 operators) and the QR of the fit's columns (11 and 13), on the paper's
decaying sine. With --baseline DIR (a checkout of another commit, e.g. `git worktree add DIR COMMIT`), the same
kernels from DIR are timed in alternation with this checkout's and the table gives the ratio, and whether the
two give the same numbers to the bit.

Run: python bench/bench_kernels.py [--samples 2858] [--rounds 5] [--baseline DIR]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from record_results import recorded

HERE = Path(__file__).resolve().parent.parent
CASES = [("play_sensitivities", 1), ("play_sensitivities", 5), ("play_sensitivities", 20),
         ("householder_r", 11), ("householder_r", 13)]


def _inputs(samples: int) -> tuple[np.ndarray, np.ndarray]:
    """The paper's decaying sine [A] (1000 s) at `samples` samples, and a GPI parameter vector a1..a11."""
    from sma_stage.signals import paper_identification_signal
    v = paper_identification_signal(np.linspace(0.0, 1000.0, samples))
    theta = np.array([1.0, 0.55, 0.1, 0.0, 1.0, 0.5, -0.05, 0.0, 0.02, 1.0, 3.0])
    return v, theta


def _time_case(kernel: str, size: int, samples: int, repeats: int) -> tuple[float, str]:
    """(fastest of `repeats` calls [ns per sample], a digest of the result's bytes) in this process."""
    from sma_stage.identify import _sensitivity
    v, theta = _inputs(samples)
    if kernel == "play_sensitivities":
        out = np.empty((11, samples))

        def call() -> np.ndarray:
            _sensitivity.play_sensitivities(v, theta, size, np.zeros(size), out)
            return out
    else:
        columns = np.random.default_rng(size).standard_normal((size, samples))
        order = np.arange(size, dtype=np.int64)

        def call() -> np.ndarray:
            return _sensitivity.householder_r(columns.copy(), order)
    call()
    best = float("inf")
    for _ in range(repeats):
        started = time.perf_counter()
        result = call()
        best = min(best, time.perf_counter() - started)
    return best / samples * 1e9, hashlib.sha256(result.tobytes()).hexdigest()


def _child(samples: int, repeats: int) -> None:
    print(json.dumps({f"{kernel} {size}": _time_case(kernel, size, samples, repeats) for kernel, size in CASES}))


def _run(checkout: Path, samples: int, repeats: int) -> dict[str, list]:
    environment = {**os.environ, "PYTHONPATH": str(checkout)}
    done = subprocess.run([sys.executable, __file__, "--child", "--samples", str(samples), "--repeats",
                           str(repeats)], capture_output=True, text=True, env=environment, cwd=checkout, check=True)
    return json.loads(done.stdout.splitlines()[-1])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=2858, help="samples per call (the diagnosis's screen copy)")
    parser.add_argument("--rounds", type=int, default=5, help="alternated runs of each checkout; the fastest kept")
    parser.add_argument("--repeats", type=int, default=200, help="calls timed per run")
    parser.add_argument("--baseline", type=Path, help="another checkout to time against this one")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        _child(args.samples, args.repeats)
        return
    checkouts = {"this": HERE} | ({"baseline": args.baseline.resolve()} if args.baseline else {})
    best: dict[str, dict[str, float]] = {name: {} for name in checkouts}
    digests: dict[str, dict[str, str]] = {name: {} for name in checkouts}
    for _ in range(args.rounds):
        for name, checkout in checkouts.items():
            for case, (seconds, digest) in _run(checkout, args.samples, args.repeats).items():
                best[name][case] = min(best[name].get(case, float("inf")), seconds)
                digests[name][case] = digest
    print(f"{args.samples} samples per call, fastest of {args.rounds} x {args.repeats} calls\n")
    if args.baseline is None:
        print("| kernel | operators / columns | ns per sample |\n|---|---|---|")
        for case, seconds in best["this"].items():
            print(f"| {case.split()[0]} | {case.split()[1]} | {seconds:.1f} |")
        return
    print("| kernel | operators / columns | this ns/sample | baseline ns/sample | this / baseline | same bits |")
    print("|---|---|---|---|---|---|")
    for case, seconds in best["this"].items():
        baseline = best["baseline"][case]
        same = "yes" if digests["this"][case] == digests["baseline"][case] else "no"
        print(f"| {case.split()[0]} | {case.split()[1]} | {seconds:.1f} | {baseline:.1f} | {seconds / baseline:.2f} "
              f"| {same} |")


if __name__ == "__main__":
    with recorded(__file__):
        main()
