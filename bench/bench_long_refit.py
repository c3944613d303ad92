"""Refits of long recordings: the identification pipeline (what `gpi_tool diagnose` and the identification node's
~/refit run: fit, residual diagnosis, the model chosen) on records of the stage simulator of 20,000, 100,000 and
360,000 samples, with two workers, fitted on every sample or on the thinned copy the pipeline fits by default;
and how late a 100 Hz stage's cycles come while such a refit runs on the same machine. Prints tables.

    .venv/bin/python bench/bench_long_refit.py [--sizes 20000,100000,360000] [--thinning both|on|off]
                                               [--rounds 1] [--stage-seconds 0]

Records (the simulator, nothing switched on, from an idle stage): identification on the paper's decaying sine
(5 A to 3.6 A, period 250 s) over 1000 s at 20 Hz (20k samples), 1000 s at 100 Hz (100k) and 3600 s at 100 Hz
(360k, an hour of a stage at 100 Hz; the sine decays over the hour); validation on the paper's two cosines over
1000 s at the same rate. Every model is scored on the full-rate validation record, so the thinned and the full
fits are compared on the same samples. With --stage-seconds S, a stage node (100 Hz, the simulator) runs beside
the largest refit and its late cycles (a cycle starting more than 1.5 periods after the one before) are read
from its /diagnostics over the refit.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
from record_results import recorded

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from sma_stage.identify.metrics import error_metrics  # noqa: E402
from sma_stage.identify.pipeline import identify_recording  # noqa: E402
from sma_stage.io.series import Series, make_series  # noqa: E402
from sma_stage.plant import simulate  # noqa: E402
from sma_stage.signals import paper_identification_signal, paper_validation_signal  # noqa: E402

SIZES = {20_000: (1000.0, 20.0), 100_000: (1000.0, 100.0), 360_000: (3600.0, 100.0)}  # samples: (s, Hz)


def record(signal, duration_s: float, rate_hz: float, seed: int, source: str) -> Series:
    """The simulator's response to signal(t) from an idle stage, at rate_hz for duration_s."""
    step = 1.0 / rate_hz
    t = np.arange(1, int(round(duration_s * rate_hz)) + 1) * step
    run = simulate(signal(t - step), step, seed=seed)
    return make_series(run.t_s, run.current_a, run.measured_position_m, source)


def records(samples: int) -> tuple[Series, Series]:
    duration_s, rate_hz = SIZES[samples]
    ident = record(lambda t: paper_identification_signal(t, duration_s=duration_s), duration_s, rate_hz, 1,
                   f"identification {samples}")
    valid = record(paper_validation_signal, 1000.0, rate_hz, 2, f"validation at {rate_hz:g} Hz")
    return ident, valid


def refit(ident: Series, valid: Series, rounds: int, thinning: bool) -> tuple[float, object]:
    """(seconds, the Identification) of the pipeline with two workers, thinning on or off."""
    started = time.perf_counter()
    found = identify_recording(ident, valid, diagnose_rounds=rounds, workers=2,
                               max_fit_samples=None if thinning else 0)
    return time.perf_counter() - started, found


def scored(model, valid: Series) -> tuple[float, float]:
    """(RMS, max) % of the span of the model on the full-rate validation record, run from rest."""
    errors = error_metrics(valid.output, model.without_state().predict(valid.t, valid.input))
    return errors.rms_pct, errors.max_pct


def stage_lateness(seconds: float, work) -> tuple[dict[str, str], float]:
    """A 100 Hz simulated stage node in its own process while work() runs here: (its timing values from the
    last /diagnostics before and after, work's seconds)."""
    from diagnostic_msgs.msg import DiagnosticArray

    from sma_stage.nodes.launch import NodeProcesses, RosClient, wait_for

    domain = 150 + os.getpid() % 50
    with NodeProcesses(Path("/tmp") / f"bench_long_refit_{os.getpid()}", domain) as nodes:
        nodes.start("stage_node", {"rate_hz": 100.0})
        with RosClient(domain, "lateness") as client:
            seen: list[dict[str, str]] = []

            def on_diagnostics(message: DiagnosticArray) -> None:
                for status in message.status:
                    if status.name.endswith("sim stage"):
                        seen.append({item.key: item.value for item in status.values})

            client.node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 10)
            wait_for(lambda: len(seen) >= 2, 30.0, "the stage's diagnostics", nodes.check_running)
            time.sleep(seconds)
            before = dict(seen[-1])
            started = time.perf_counter()
            work()
            elapsed = time.perf_counter() - started
            count = len(seen)
            wait_for(lambda: len(seen) > count, 5.0, "the stage's diagnostics after the refit")
            after = dict(seen[-1])
        nodes.stop_all()
    return {"before": before, "after": after}, elapsed


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default=",".join(map(str, SIZES)), help="record sizes, of " + ", ".join(map(str, SIZES)))
    parser.add_argument("--thinning", choices=("both", "on", "off"), default="both")
    parser.add_argument("--rounds", type=int, default=1, help="diagnosis rounds (the node's default 1)")
    parser.add_argument("--stage-seconds", type=float, default=0.0,
                        help="run a 100 Hz stage node this long before the largest refit and through it (0: not)")
    args = parser.parse_args()
    modes = {"both": (True, False), "on": (True,), "off": (False,)}[args.thinning]
    print(f"{os.cpu_count()} CPUs; diagnosis rounds {args.rounds}, two workers\n")
    print("| samples | thinned to | seconds | model | validation RMS / max % (full rate) |")
    print("|---|---|---|---|---|")
    sizes = [int(text) for text in args.sizes.split(",")]
    for samples in sizes:
        ident, valid = records(samples)
        for thinning in modes:
            seconds, found = refit(ident, valid, args.rounds, thinning)
            fitted = found.report.get("thinned", {}).get("fitted_samples", len(ident))
            rms, peak = scored(found.model, valid)
            effects = " + ".join(getattr(found.model, "effect_names", [])) or "none"
            print(f"| {len(ident)} | {fitted if thinning else 'not thinned'} | {seconds:.1f} | {effects} | "
                  f"{rms:.3f} / {peak:.2f} |", flush=True)
    if args.stage_seconds > 0.0:
        ident, valid = records(max(sizes))
        timing, seconds = stage_lateness(args.stage_seconds, lambda: refit(ident, valid, args.rounds, True))
        before, after = timing["before"], timing["after"]
        cycles = int(after["cycles"]) - int(before["cycles"])
        late = int(after["late_cycles"]) - int(before["late_cycles"])
        print(f"\nA 100 Hz stage node beside the refit of {len(ident)} samples ({seconds:.1f} s): {cycles} cycles, "
              f"{late} late ({100.0 * late / max(cycles, 1):.2f} %)")
    return 0


if __name__ == "__main__":
    with recorded(__file__):
        raise SystemExit(main())
