"""The identification's worker processes: where a diagnosis round's candidates and the model families' fits run
(in this process, or in forked or forkserver processes at a lower priority), and the pieces that make a result
the same whatever the worker count (BLAS on one thread)."""

from __future__ import annotations

import multiprocessing
import os
import signal
import sys
import threading
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool

import numpy as np
from threadpoolctl import threadpool_limits

from sma_stage.errors import InputError
from sma_stage.identify.cancel import Progress, check_cancelled, report
from sma_stage.identify.fit import fit_gpi
from sma_stage.model.effects import EFFECT_KINDS, Effect
from sma_stage.model.effects import PARAMETERS as EFFECT_PARAMETERS
from sma_stage.model.identified import IdentifiedModel

CANCEL_POLL_S = 0.05  # how often a wait for the worker processes looks for a cancellation [s]


def _first_item(job: tuple) -> str:
    return str(job[0])


def _no_cost(job: tuple) -> float:
    return 0.0


class Pending:
    """A job's result to come (Workers.submit): `result()` waits for it, or computes it the first time;
    `begin()` starts the part of it that can start now (the `begin` given, once), without waiting."""

    def __init__(self, compute: Callable[[], object], begin: Callable[[], object] | None = None) -> None:
        self._compute: Callable[[], object] | None = compute
        self._begin = begin
        self._value: object = None

    def begin(self) -> None:
        """Start what can start now (nothing unless a `begin` was given)."""
        if self._begin is not None:
            self._begin, begin = None, self._begin
            begin()

    def result(self) -> object:
        """The job's result (its exception raised here)."""
        if self._compute is not None:
            self._value, self._compute = self._compute(), None
        return self._value


WORKER_NICENESS = 10  # the workers yield the CPU to a stage or a node on the same computer
MAX_NICENESS = 19


def check_niceness(niceness: int) -> int:
    """niceness as an int from 0 to MAX_NICENESS; InputError (one line) otherwise."""
    if isinstance(niceness, bool) or not isinstance(niceness, (int, np.integer)) or not 0 <= niceness <= MAX_NICENESS:
        raise InputError(f"niceness must be an integer from 0 to {MAX_NICENESS}, got {niceness!r}")
    return int(niceness)


class Workers:
    """Where a round's candidates are fitted: in this process, one after the other (workers 1), or in up to
    `workers` processes at once (forked, or a forkserver's children beside other threads: Workers.start). Each
    candidate's fit is the same computation either way, so the diagnosis does not depend on the count; a
    worker's progress messages are not relayed, only each candidate's outcome. The processes run `niceness`
    levels below this one (lower_priority)."""

    def __init__(self, workers: int = 1, niceness: int = WORKER_NICENESS) -> None:
        if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
            raise InputError(f"workers must be a positive integer, got {workers!r}")
        self.workers = int(workers)
        self.niceness = check_niceness(niceness)
        self._executor: ProcessPoolExecutor | None = None
        self._starting: threading.Thread | None = None
        self._failure = "unknown reason"

    def run(self, function: Callable[..., object], jobs: list[tuple], progress: Progress, doing: str,
            then: Callable[[], object] | None = None, name: Callable[[tuple], str] = _first_item,
            cost: Callable[[tuple], float] = _no_cost) -> list[object]:
        """[function(*job) for job in jobs], in order; progress is told what starts (`doing` with the job's
        `name` in its {}), and in this process what each job reports. Processes take the costlier jobs first
        (`cost`), so that the round's longest fit does not start last.
        then: called once the jobs are handed out, before they are waited for (to submit work behind them)."""
        if self.workers == 1 or len(jobs) < 2:
            results = []
            for job in jobs:
                report(progress, doing.format(name(job)))
                results.append(_as_in_a_worker(function, *job, progress))
            if then is not None:
                then()
            return results
        executor = self._started()
        report(progress, doing.format(", ".join(name(job) for job in jobs)) + f" in {self.workers} processes")
        costliest_first = sorted(range(len(jobs)), key=lambda index: -cost(jobs[index]))
        futures = {index: executor.submit(function, *jobs[index]) for index in costliest_first}
        if then is not None:
            then()
        return [self._answered(futures[index]) for index in range(len(jobs))]

    def submit(self, function: Callable[..., object], *args: object) -> Pending:
        """function(*args) begun now in a worker process, behind the jobs already waiting; with workers 1, run in
        this process when its result is asked for."""
        if self.workers == 1:
            return Pending(lambda: _as_in_a_worker(function, *args))
        future = self._started().submit(function, *args)
        return Pending(lambda: self._answered(future))

    def _answered(self, future: Future) -> object:
        try:
            return self._result(future)
        except BrokenProcessPool:
            raise InputError("the identification's worker processes ended before answering (killed, out of memory, "
                             "or a script that identifies with workers > 1 outside `if __name__ == '__main__':`); "
                             "use workers=1") from None

    @staticmethod
    def _result(future: Future) -> object:
        """A job's result, waited for in slices so that a cancellation (sma_stage.identify.cancel) is seen."""
        while True:
            try:
                return future.result(timeout=CANCEL_POLL_S)
            except TimeoutError:
                check_cancelled()

    def terminate(self) -> None:
        """End the worker processes now, their running jobs with them (a cancelled diagnosis)."""
        self._wait_for_start()
        executor, self._executor = self._executor, None
        if executor is None:
            return
        processes = list((getattr(executor, "_processes", None) or {}).values())  # no public handle before 3.14
        for process in processes:
            process.terminate()
        executor.shutdown(wait=True, cancel_futures=True)

    def start(self) -> None:
        """Start the worker processes, each loading the fit's compiled kernels (warm_up), while this process goes on
        (the plain fit): the first round then does not wait for them. A process with no other thread (gpi_tool, a
        script) forks them, in milliseconds; any other (a ROS node) has a thread start them from a forkserver, where
        no other thread's lock is copied into them (the forkserver's start costs about 2 s of CPU). Nothing with
        workers 1."""
        if self.workers == 1 or self._starting is not None or self._executor is not None:
            return
        if threading.active_count() == 1 and sys.platform.startswith("linux"):
            self._launch("fork")
        else:
            self._starting = threading.Thread(target=self._launch, args=("forkserver",), name="diagnosis-workers",
                                              daemon=True)
            self._starting.start()

    def _launch(self, method: str) -> None:
        """Create the executor (start method "fork" or "forkserver") and have each worker load the kernels. While
        this process forks, Ctrl-C and SIGTERM wait (_interrupts_held) and are raised once the executor is kept."""
        held = _interrupts_held() if method == "fork" else None
        try:
            context = multiprocessing.get_context(method)
            if method == "forkserver":
                context.set_forkserver_preload([__name__])
            executor = ProcessPoolExecutor(self.workers, mp_context=context, initializer=_worker_setup,
                                           initargs=(self.niceness,))
            for _ in range(self.workers):
                executor.submit(warm_up)
            self._executor = executor
        except (OSError, RuntimeError, ValueError) as error:
            self._failure = " ".join(str(error).split()) or type(error).__name__
        finally:
            if held is not None:
                signal.pthread_sigmask(signal.SIG_SETMASK, held)

    def _started(self) -> ProcessPoolExecutor:
        """The executor, once start() has launched it (launched here if it was not)."""
        self.start()
        self._wait_for_start()
        if self._executor is None:
            raise InputError(f"the diagnosis's worker processes could not be started ({self._failure}); use workers=1")
        return self._executor

    def _wait_for_start(self) -> None:
        if self._starting is not None:
            self._starting.join()
            self._starting = None

    def close(self) -> None:
        """Stop the worker processes (none were started with workers 1)."""
        self._wait_for_start()
        if self._executor is not None:
            self._executor.shutdown(cancel_futures=True)
            self._executor = None

    def __enter__(self) -> Workers:
        return self

    def __exit__(self, kind: type[BaseException] | None, *exc_info: object) -> None:
        if kind is None:
            self.close()
        else:  # an error, a cancellation or an interrupt: the running jobs are not waited for
            self.terminate()


def one_blas_thread() -> threadpool_limits:
    """Run BLAS on one thread in this process, until the returned context ends (`with one_blas_thread():`)
    or for good. The fits' matrices are small (about 12 x 12 after the QR compression): OpenBLAS's threads
    cost more than they give, and with Workers they fight over the cores (bench/README.md, Diagnosis)."""
    return threadpool_limits(1, user_api="blas")


def _as_in_a_worker(function: Callable[..., object], *args: object) -> object:
    """function(*args) in this process with BLAS on one thread, as a worker process runs it: with OpenBLAS on
    two threads a two-wire fit took another path and ended at another model (the result must not depend on
    the worker count)."""
    with one_blas_thread():
        return function(*args)


INTERRUPTS = {signal.SIGINT, signal.SIGTERM}


def _interrupts_held() -> set[signal.Signals]:
    """Block Ctrl-C and SIGTERM in this thread until the returned mask is set again: a Python handler run in an
    after-fork callback (logging has one) has its exception printed as "Exception ignored" and dropped."""
    return signal.pthread_sigmask(signal.SIG_BLOCK, INTERRUPTS)


def _worker_setup(niceness: int) -> None:
    """A worker process: SIGTERM ends it (a forked worker does not keep gpi_tool's handler, which would have it
    raise instead of ending when the pool is terminated; nor the parent's block of it while it forked), BLAS on one
    thread, and `niceness` levels below the process that started it."""
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, INTERRUPTS)
    one_blas_thread()
    lower_priority(niceness=niceness)


def lower_priority(thread: bool = False, niceness: int = WORKER_NICENESS) -> None:
    """Lower this process's scheduling priority (or only the calling thread's, on Linux) by `niceness` levels, so
    that a long fit yields the CPU to a stage's control cycle; nothing where the system does not allow it."""
    if niceness == 0:
        return
    try:
        if thread and sys.platform.startswith("linux"):
            identity = threading.get_native_id()
            os.setpriority(os.PRIO_PROCESS, identity, os.getpriority(os.PRIO_PROCESS, identity) + niceness)
        elif not thread:
            os.nice(niceness)
    except (OSError, AttributeError):
        pass


def warm_up() -> None:
    """Load the fit's and the effects' compiled kernels in this process (or build them: seconds on a cold numba
    cache): a small fit of a loop, then a model with each effect run over it."""
    u = np.sin(np.linspace(0.0, 4.0 * np.pi, 60))
    found = fit_gpi(u, np.tanh(u), operators=5, max_iterations=3)
    t_s = np.arange(u.size, dtype=float)
    for kind in EFFECT_KINDS:
        required, optional = EFFECT_PARAMETERS[kind]
        effect = Effect(kind, {name: 1.0 for name in required or optional[:1]})
        IdentifiedModel(found.parameters, 5, (effect,)).predict(t_s, u)


