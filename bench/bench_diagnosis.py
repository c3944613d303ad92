"""Benchmark of the residual diagnosis: how long `gpi_tool diagnose`'s pipeline takes on records of the stage
simulator (a physical model with no GPI inside) of a given size, every candidate effect included, every round
run, and every model family given fitted and compared.

Identification on the paper's decaying sine, validation on its two cosines, each N samples over 1000 s
from an idle stage (the simulator with nothing switched on). Prints a table: samples, candidates, workers,
what was named, the validation RMS before and after, each family's validation RMS and the wall-clock seconds.

Each size runs with every --workers count given (candidates fitted in that many processes; the result is
the same for any count, which the table shows).

With --phases, instead: one identification of the record issue 50 times (`gpi_tool simulate --input identification
--rate-hz 20`, diagnosed with 30 % held out, every family, two workers, as `gpi_tool diagnose --holdout 0.3
--workers 2` runs it) with every job the worker processes ran timed: a table of the jobs by kind (count, the
seconds they took, when the first began and the last ended, from the identification's start), the worker-seconds
against the wall-clock seconds, and what the main process did meanwhile; written to
bench/results/diagnosis_phases.md.

Run: python bench/bench_diagnosis.py [--samples 5000,20000] [--workers 1,2] [--families gpi --families gpi,two_wire ...]
     python bench/bench_diagnosis.py --phases
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np
from record_results import recorded

from sma_stage.identify.effects import EFFECT_NAMES
from sma_stage.identify.families import FAMILIES
from sma_stage.identify.pipeline import identify_recording
from sma_stage.io.series import Series, make_series
from sma_stage.plant import simulate
from sma_stage.signals import paper_identification_signal, paper_validation_signal

DURATION_S = 1000.0


def record(signal, samples: int, seed: int) -> Series:
    """The simulator's record (t [s], current [A], measured position [m]) from an idle stage, `samples` samples."""
    step = DURATION_S / samples
    t = np.arange(1, samples + 1) * step
    run = simulate(signal(t - step), step, seed=seed)
    return make_series(run.t_s, run.current_a, run.measured_position_m, f"simulator {samples}")


def _timed(label: str, function: object, *args: object) -> tuple[object, tuple[str, float, float]]:
    """function(*args) in a worker, with (label, start, end [s, time.time()])."""
    started = time.time()
    value = function(*args)
    return value, (label, started, time.time())


def _label(function: object, args: tuple) -> str:
    """What a worker's job is, for the phases table."""
    name = getattr(function, "__qualname__", str(function))
    if name == "_judged":
        return f"candidate effect, round {len(args[1].stages)}"
    if name == "_solve":
        return "two-wire least squares" + (", tension coupling free" if args[0].tension else "")
    return {"_recounted": "operator count of a candidate", "_count_option": "operator count (held out)",
            "_cold_fit": "operator count's cold fit", "warm_up": "loading the kernels",
            "fit_bouc_wen": "Bouc-Wen fit", "fit_free_weights_row": "free-weight GPI"}.get(name, name)


def phases() -> None:
    """Time every worker job of one identification of issue 50's record (see the module's docstring)."""
    jobs: list[tuple[str, float, float]] = []
    submit = ProcessPoolExecutor.submit

    def timed_submit(executor: ProcessPoolExecutor, function: object, *args: object) -> object:
        future = submit(executor, _timed, _label(function, args), function, *args)
        unwrapped = type(future)()
        future.add_done_callback(lambda done: _unwrap(done, unwrapped, jobs))
        return unwrapped

    step = 1.0 / 20.0
    t = np.arange(0.0, DURATION_S, step)
    run = simulate(paper_identification_signal(t), step, seed=0)
    record = make_series(run.t_s, run.current_a, run.measured_position_m, "gpi_tool simulate --input identification")
    ProcessPoolExecutor.submit = timed_submit
    try:
        started = time.time()
        found = identify_recording(record, None, holdout_fraction=0.3, diagnose_rounds=4, workers=2,
                                   families=FAMILIES)
        wall = time.time() - started
    finally:
        ProcessPoolExecutor.submit = submit
    chosen = [row["family"] for row in found.report.get("families", []) if row["chosen"]]
    print(f"{os.cpu_count()} CPUs; {len(record)} samples, families {', '.join(FAMILIES)}, chosen: {', '.join(chosen)}; "
          f"{wall:.1f} s wall-clock\n")
    print("| job | count | seconds (sum) | first began, last ended [s] |\n|---|---|---|---|")
    for label in dict.fromkeys(job[0] for job in sorted(jobs, key=lambda job: job[1])):
        mine = [job for job in jobs if job[0] == label]
        print(f"| {label} | {len(mine)} | {sum(end - begin for _, begin, end in mine):.2f} | "
              f"{min(job[1] for job in mine) - started:.2f}, {max(job[2] for job in mine) - started:.2f} |")
    busy = sum(end - begin for _, begin, end in jobs)
    last = max(job[2] for job in jobs) - started
    print(f"| every job | {len(jobs)} | {busy:.2f} | the workers busy {busy / (2 * last):.0%} of 2 x {last:.1f} s; "
          f"the main process alone after them: {wall - last:.1f} s |")


def _unwrap(done: object, unwrapped: object, jobs: list) -> None:
    """Hand a timed job's value (or its error) to the future its caller holds, and keep its timing."""
    if done.cancelled():
        unwrapped.cancel()
        return
    error = done.exception()
    if error is not None:
        unwrapped.set_exception(error)
        return
    value, timing = done.result()
    jobs.append(timing)
    unwrapped.set_result(value)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", default="5000,20000", help="comma-separated record sizes")
    parser.add_argument("--workers", default=f"1,{os.cpu_count() or 1}", help="comma-separated worker counts")
    parser.add_argument("--families", action="append",
                        help="comma-separated model families compared; repeat it for several sets, each timed beside "
                             "the first (default: gpi, then every family)")
    parser.add_argument("--rounds", type=int, default=4, help="diagnosis rounds at most (gpi_tool's default 4)")
    parser.add_argument("--phases", action="store_true", help="time the worker jobs of issue 50's record instead")
    args = parser.parse_args(argv)
    if args.phases:
        phases()
        return
    family_sets = [tuple(text.split(",")) for text in (args.families or ["gpi", ",".join(FAMILIES)])]
    print(f"{os.cpu_count()} CPUs\n")
    print("| samples (each record) | candidates | workers | named | validation RMS before -> after % | families: "
          "validation RMS % (chosen *) | seconds | seconds / first set's |")
    print("|---|---|---|---|---|---|---|---|")
    for samples in (int(text) for text in args.samples.split(",")):
        ident = record(paper_identification_signal, samples, seed=1)
        valid = record(paper_validation_signal, samples, seed=2)
        for workers in dict.fromkeys(int(text) for text in args.workers.split(",")):
            first = None
            for families in family_sets:
                started = time.perf_counter()
                found = identify_recording(ident, valid, diagnose_rounds=args.rounds, workers=workers,
                                           families=families)
                seconds = time.perf_counter() - started
                first = first or seconds
                diagnosis = found.diagnosis
                rows = found.report.get("families", [])
                scores = ", ".join(f"{row['family']} {row['validation']['rms_pct']:.2f}{' *' if row['chosen'] else ''}"
                                   if row["validation"] else f"{row['family']} -" for row in rows) or "gpi only"
                print(f"| {samples} | {len(EFFECT_NAMES)} | {workers} | {' + '.join(diagnosis.effects) or 'none'} "
                      f"| {diagnosis.before.rms_pct:.2f} -> {diagnosis.after.rms_pct:.4f} | {scores} | {seconds:.1f} "
                      f"| {seconds / first:.2f} |", flush=True)


if __name__ == "__main__":
    with recorded(__file__, "diagnosis_phases" if "--phases" in sys.argv[1:] else None):
        main()
