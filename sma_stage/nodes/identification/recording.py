"""The identification node's recording: the aligned series of what it recorded, and the bag writer thread."""

from __future__ import annotations

import errno
import queue
import shutil
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from sma_stage.errors import InputError
from sma_stage.io import BagRecorder, align_zero_order_hold, make_series
from sma_stage.io.rosbag_io import output_times, stamped_pairs
from sma_stage.io.series import Series


def recording_series(inputs: list[tuple[int, float]], outputs: list[tuple[int, int, float, float]],
                     min_samples: int, input_topic: str = "current_applied", time_scale: float = 1.0,
                     from_effort: bool = True) -> Series:
    """The checked Series (t [s of stage time: node-clock seconds times time_scale], input [A], output [m]) of a
    recording; InputError saying what is missing. outputs: (receive, stamp [ns], position [m], effort [A] or NaN);
    with from_effort, when every one has its effort, the current and position stamped together, else the
    inputs (receive [ns], current [A]) held at each position's time. Either way the record starts at the first
    input when there is one (positions from before an excitation's first command are not part of it)."""
    if not outputs:
        raise InputError("no messages on joint_states were recorded: is the stage running?")
    receive_ns, stamp_ns, positions, efforts = (np.array(column) for column in zip(*outputs, strict=True))
    receive_ns, stamp_ns = receive_ns.astype(np.int64), stamp_ns.astype(np.int64)
    if from_effort and inputs:
        after_first_input = output_times(receive_ns, stamp_ns) >= min(receive for receive, _ in inputs)
        receive_ns, stamp_ns = receive_ns[after_first_input], stamp_ns[after_first_input]
        positions, efforts = positions[after_first_input], efforts[after_first_input]
    pairs = stamped_pairs(receive_ns, stamp_ns, efforts.astype(float), positions.astype(float)) if from_effort else None
    if pairs is not None:
        t, u, y = pairs
        return make_series(t * time_scale, u, y, "recording", min_samples=min_samples)
    if not inputs:
        unstamped = " (and joint_states carry no effort)" if from_effort else ""
        raise InputError(f"no messages on {input_topic} were recorded{unstamped}: is anything publishing it?")
    input_ns, input_values = (np.array(column) for column in zip(*inputs, strict=True))
    t, u, y = align_zero_order_hold(input_ns.astype(np.int64), input_values.astype(float),
                                    output_times(receive_ns.astype(np.int64), stamp_ns.astype(np.int64)),
                                    positions.astype(float))
    if t.size == 0:
        raise InputError(f"no joint_states message came at or after the first {input_topic} message")
    return make_series(t * time_scale, u, y, "recording", min_samples=min_samples)



BAG_QUEUE_LIMIT = 100_000  # messages waiting for the bag writer (25 s of both topics at 2 kHz); more are dropped
BAG_CHECKPOINT_S = 1.0  # the bag is made durable and the free space looked at this often [s]
MIN_FREE_BYTES = 64 << 20  # below this much free space the recording ends, the bag finished while it can be


class BagThread:
    """A BagRecorder driven from one thread of its own (the sqlite3 storage must stay in the thread that
    opened it, while the executor calls back from several), behind a bounded queue. A failure of the recorder
    (a full disk, a write error) ends the recording: the bag is finished as far as it can be, `failure` says
    what happened and where the data are, on_failure is told once, and further messages are dropped."""

    def __init__(self, path: Path, storage: str, overwrite: bool = False, input_topic: str = "current_applied",
                 on_failure: Callable[[str], None] | None = None) -> None:
        self.path = path
        if (path.exists() or path.is_symlink()) and not overwrite:
            raise InputError(f"record_bag {path} exists already: choose another path or set bag_overwrite true")
        self._queue: queue.Queue = queue.Queue(maxsize=BAG_QUEUE_LIMIT)
        self._opened = threading.Event()
        self._error: Exception | None = None
        self._on_failure = on_failure
        self.failure: str | None = None
        self.written = self.dropped = 0
        self._thread = threading.Thread(target=self._run, args=(storage, overwrite, input_topic), name="bag-writer",
                                        daemon=True)
        self._thread.start()
        self._opened.wait()
        if self._error is not None:
            raise self._error

    def _run(self, storage: str, overwrite: bool, input_topic: str) -> None:
        try:
            recorder = BagRecorder.open(self.path, storage, overwrite=overwrite, input_topic=input_topic)
        except Exception as error:  # noqa: BLE001 -- handed to the opening thread
            self._error = error if isinstance(error, InputError) else InputError(f"cannot record {self.path}: {error}")
            self._opened.set()
            return
        self._opened.set()
        checkpoint_at = time.monotonic() + BAG_CHECKPOINT_S
        while (item := self._queue.get()) is not None:
            if self.failure is not None:
                continue
            method, arguments = item
            try:
                getattr(recorder, method)(*arguments)
                self.written += 1
                if time.monotonic() >= checkpoint_at:
                    checkpoint_at = time.monotonic() + BAG_CHECKPOINT_S
                    self._checkpoint(recorder)
            except Exception as error:  # noqa: BLE001 -- any failure ends the recording, in one line
                self._fail(" ".join(str(error).split()) or type(error).__name__, recorder)
        if self.failure is None:
            try:
                recorder.close()
            except Exception as error:  # noqa: BLE001 -- as above
                self._fail(f"finishing the bag: {' '.join(str(error).split())}", recorder)

    def _checkpoint(self, recorder: BagRecorder) -> None:
        recorder.checkpoint()
        free = shutil.disk_usage(self.path.parent).free
        if free < MIN_FREE_BYTES:
            raise OSError(errno.ENOSPC, f"only {free / 2**20:.0f} MiB left on the disk (recording ends below "
                                        f"{MIN_FREE_BYTES >> 20} MiB)")

    def _fail(self, reason: str, recorder: BagRecorder) -> None:
        try:
            kept = f"the bag {recorder.close()} holds the {self.written} messages written"
        except Exception as error:  # noqa: BLE001 -- say where the data are instead
            kept = (f"what was written is in {recorder.staging} (the bag could not be finished: "
                    f"{' '.join(str(error).split())})")
        self.failure = f"recording stopped: {reason}; {kept}"
        if self._on_failure is not None:
            self._on_failure(self.failure)

    def _put(self, item: tuple) -> None:
        if self.failure is not None:
            return
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            self.dropped += 1

    def write_input(self, stamp_ns: int, value: float) -> None:
        """Queue a current command [A] received at stamp_ns."""
        self._put(("write_input", (stamp_ns, value)))

    def write_output(self, stamp_ns: int, position: float, velocity: float, receive_ns: int,
                     effort: float | None = None) -> None:
        """Queue a JointState (header stamp stamp_ns, position [m], velocity [m/s], effort: the current [A] applied
        over the period that ended at it, when known) received at receive_ns."""
        self._put(("write_output", (stamp_ns, position, velocity, receive_ns, effort)))

    def close(self) -> Path:
        """Write what is queued, finish the bag (renamed into place) and return its path."""
        self._queue.put(None)
        self._thread.join()
        return self.path
