"""rosbag2 directories (sqlite3 or mcap) of current commands and stage positions, through `rosbags`.

The input topic carries std_msgs/msg/Float64 [A]; the output topic sensor_msgs/msg/JointState
(position [m] of one joint, and as effort the heating current [A] applied over the period that ended at it,
as the stage node publishes) or std_msgs/msg/Float64. `rosbags` is imported on first use only.
"""

from __future__ import annotations

import functools
import math
import os
import shutil
import tempfile
import threading
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Self

import numpy as np

from sma_stage.errors import InputError
from sma_stage.io.series import DEFAULT_MIN_SAMPLES, Series, make_series

FLOAT64 = "std_msgs/msg/Float64"
JOINT_STATE = "sensor_msgs/msg/JointState"
DEFAULT_INPUT_TOPIC = "current_cmd"
DEFAULT_OUTPUT_TOPIC = "joint_states"
DEFAULT_JOINT = "stage_x"
JAZZY_BAG_VERSION = 9
DEFAULT_START_NS = 1_700_000_000 * 10**9
STORAGE_FILE_SUFFIXES = (".db3", ".mcap")
_CLOCK_MISMATCH_NS = 10**9


@functools.cache
def _typestore() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def _first_line(error: BaseException) -> str:
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__


@contextmanager
def _bag_errors(path: Path) -> Iterator[None]:
    """Turn any failure inside rosbags into a one-line InputError."""
    try:
        yield
    except InputError:
        raise
    except Exception as error:  # noqa: BLE001 -- rosbags, apsw and struct raise many types
        raise InputError(
            f"{path}: cannot read the rosbag2 ({_first_line(error)}); is it truncated or damaged?"
        ) from None


def _topic_key(name: str) -> str:
    return name.strip().strip("/")


def match_topic(requested: str, topics: Mapping[str, str], source: str = "") -> str:
    """The bag topic meant by `requested`: equal up to leading slashes, else the unique one ending in it."""
    prefix = f"{source}: " if source else ""
    key = _topic_key(requested)
    if not key:
        raise InputError(f"{prefix}empty topic name")
    exact = [name for name in topics if _topic_key(name) == key]
    if len(exact) == 1:
        return exact[0]
    by_suffix = [name for name in topics if _topic_key(name).endswith("/" + key)]
    if len(by_suffix) == 1:
        return by_suffix[0]
    if len(exact) + len(by_suffix) > 1:
        raise InputError(
            f"{prefix}topic '{requested}' matches several: {', '.join(sorted(exact + by_suffix))}; "
            "give the full name"
        )
    found = ", ".join(f"{name} [{kind}]" for name, kind in sorted(topics.items())) or "none"
    raise InputError(f"{prefix}no topic '{requested}' in the bag (topics found: {found})")


def _check_bag_path(path: Path) -> None:
    if not path.exists():
        raise InputError(f"{path}: no such file or directory")
    if path.is_dir() and not (path / "metadata.yaml").is_file():
        raise InputError(f"{path}: not a rosbag2 directory (metadata.yaml is missing)")
    if path.is_file() and path.suffix not in STORAGE_FILE_SUFFIXES:
        raise InputError(f"{path}: not a rosbag2 directory or a .db3/.mcap storage file")


def _check_type(topic: str, kinds: set[str], allowed: tuple[str, ...], source: str) -> None:
    wrong = sorted(kinds - set(allowed))
    if wrong:
        raise InputError(f"{source}: topic '{topic}' has type {', '.join(wrong)}, expected {' or '.join(allowed)}")


def joint_index(message: Any, joint_name: str) -> int | None:
    """Index of joint_name's position in a JointState (the only position of one without names); None when
    the message does not carry it. The one rule for bags and live topics alike."""
    names = list(message.name)
    if joint_name in names:
        index = names.index(joint_name)
        return index if index < len(message.position) else None
    return 0 if not names and len(message.position) == 1 else None


def _joint_reading(message: Any, joint_name: str) -> tuple[float | None, float]:
    """(position or None when the message does not carry the joint, its effort or NaN)."""
    index = joint_index(message, joint_name)
    if index is None:
        return None, math.nan
    effort = float(message.effort[index]) if index < len(message.effort) else math.nan
    return float(message.position[index]), effort


def _stamp_ns(message: Any) -> int:
    return int(message.header.stamp.sec) * 10**9 + int(message.header.stamp.nanosec)


def _read_inputs(reader: Any, connections: list[Any]) -> tuple[np.ndarray, np.ndarray]:
    store = _typestore()
    times, values = [], []
    for connection, receive_ns, raw in reader.messages(connections=connections):
        times.append(receive_ns)
        values.append(float(store.deserialize_cdr(raw, connection.msgtype).data))
    return np.array(times, dtype=np.int64), np.array(values, dtype=np.float64)


def _read_outputs(
    reader: Any, connections: list[Any], joint_name: str, source: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(receive times, header stamps or 0, positions, efforts or NaN) of the output messages that carry the joint."""
    store = _typestore()
    receive, stamps, values, efforts, names_seen, without_position = [], [], [], [], set(), 0
    for connection, receive_ns, raw in reader.messages(connections=connections):
        message = store.deserialize_cdr(raw, connection.msgtype)
        if connection.msgtype == FLOAT64:
            (position, effort), stamp = (float(message.data), math.nan), 0
        else:
            (position, effort), stamp = _joint_reading(message, joint_name), _stamp_ns(message)
            names_seen.update(message.name)
            without_position += joint_name in message.name and position is None
        if position is not None:
            receive.append(receive_ns)
            stamps.append(stamp)
            values.append(position)
            efforts.append(effort)
    if names_seen and not values:
        if without_position:
            raise InputError(f"{source}: joint '{joint_name}' is named but has no position in any of the "
                             f"{without_position} messages (their position arrays are shorter than their names)")
        raise InputError(f"{source}: no joint '{joint_name}' in the output (joints found: {', '.join(sorted(names_seen))})")
    return (np.array(receive, dtype=np.int64), np.array(stamps, dtype=np.int64), np.array(values, dtype=np.float64),
            np.array(efforts, dtype=np.float64))


def stamped_pairs(receive_ns: np.ndarray, stamp_ns: np.ndarray, currents: np.ndarray,
                  positions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(t [s] from the first sample, current [A], position) of outputs that each carry the current applied over
    the period that ended at them (JointState effort), ordered by time (output_times); None unless every one does."""
    if currents.size == 0 or not np.all(np.isfinite(currents)):
        return None
    times_ns = output_times(receive_ns, stamp_ns)
    return align_zero_order_hold(times_ns, currents, times_ns, positions)


def output_times(receive_ns: np.ndarray, stamp_ns: np.ndarray) -> np.ndarray:
    """Header stamps where non-zero, else receive times [ns]; all receive times if the stamps run on another
    clock (median offset over 1 s, e.g. simulated time recorded against wall time)."""
    stamped = stamp_ns != 0
    if stamped.any() and abs(float(np.median(receive_ns[stamped] - stamp_ns[stamped]))) > _CLOCK_MISMATCH_NS:
        return receive_ns
    return np.where(stamped, stamp_ns, receive_ns)


def align_zero_order_hold(
    input_ns: np.ndarray, input_values: np.ndarray, output_ns: np.ndarray, output_values: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t [s] from the first kept sample, input held at each output time, output).

    The input is a zero-order hold: the latest input at or before each output time. Outputs before the
    first input are dropped; of outputs with equal times the last one is kept.
    """
    in_order = np.argsort(input_ns, kind="stable")
    in_ns, in_values = np.asarray(input_ns)[in_order], np.asarray(input_values)[in_order]
    out_order = np.argsort(output_ns, kind="stable")
    out_ns, out_values = np.asarray(output_ns)[out_order], np.asarray(output_values)[out_order]
    last_of_equal = np.append(np.diff(out_ns) != 0, True)
    out_ns, out_values = out_ns[last_of_equal], out_values[last_of_equal]
    held = np.searchsorted(in_ns, out_ns, side="right") - 1
    kept = held >= 0
    out_ns = out_ns[kept]
    t = (out_ns - out_ns[0]).astype(np.float64) * 1e-9 if out_ns.size else out_ns.astype(np.float64)
    return t, in_values[held[kept]], out_values[kept]


def _topic_connections(reader: Any) -> tuple[dict[str, str], dict[str, list[Any]]]:
    kinds: dict[str, set[str]] = {}
    connections: dict[str, list[Any]] = {}
    for connection in reader.connections:
        kinds.setdefault(connection.topic, set()).add(connection.msgtype)
        connections.setdefault(connection.topic, []).append(connection)
    return {topic: "|".join(sorted(types)) for topic, types in kinds.items()}, connections


def read_bag(
    path: str | os.PathLike,
    input_topic: str | None = None,
    output_topic: str | None = None,
    joint_name: str = DEFAULT_JOINT,
    min_samples: int = DEFAULT_MIN_SAMPLES,
    default_input_topic: str = DEFAULT_INPUT_TOPIC,
) -> Series:
    """A checked Series from a rosbag2, t [s] from the first sample. Without input_topic, when every output
    message carries the joint's effort: the current [A] and position stamped together; otherwise the input
    topic's current (input_topic, else default_input_topic) held at each output time (a zero-order hold)."""
    from rosbags.rosbag2 import Reader

    path = Path(path)
    source = str(path)
    _check_bag_path(path)
    output_topic = output_topic or DEFAULT_OUTPUT_TOPIC
    with _bag_errors(path):
        reader = Reader(path)
        reader.open()
        try:
            if reader.message_count == 0:
                raise InputError(f"{source}: the bag has no messages")
            kinds, connections = _topic_connections(reader)
            output_name = match_topic(output_topic, kinds, source)
            _check_type(output_name, set(kinds[output_name].split("|")), (JOINT_STATE, FLOAT64), source)
            receive_ns, stamp_ns, positions, efforts = _read_outputs(reader, connections[output_name], joint_name,
                                                                     source)
            pairs = stamped_pairs(receive_ns, stamp_ns, efforts, positions) if input_topic is None else None
            if pairs is None:
                input_name = match_topic(input_topic or default_input_topic, kinds, source)
                _check_type(input_name, set(kinds[input_name].split("|")), (FLOAT64,), source)
                input_ns, input_values = _read_inputs(reader, connections[input_name])
        finally:
            reader.close()
    if pairs is not None:
        return make_series(*pairs, f"{source} ({output_name}: effort and position stamped together)", False,
                           min_samples)
    for name, count in ((input_name, input_ns.size), (output_name, positions.size)):
        if count == 0:
            raise InputError(f"{source}: no messages on topic '{name}'")
    t, held_input, output = align_zero_order_hold(input_ns, input_values, output_times(receive_ns, stamp_ns), positions)
    if t.size == 0:
        raise InputError(f"{source}: no '{output_name}' message at or after the first '{input_name}' message")
    return make_series(t, held_input, output, f"{source} ({input_name} -> {output_name})", False, min_samples)


def _storage_plugin(storage: str) -> Any:
    from rosbags.rosbag2 import StoragePlugin

    plugins = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}
    if str(storage).lower() not in plugins:
        raise InputError(f"unknown rosbag2 storage '{storage}'; use sqlite3 or mcap")
    return plugins[str(storage).lower()]


def unfinished_bags(path: str | os.PathLike) -> list[Path]:
    """Staging folders of bags for path that were never finished (their recorder was killed), oldest first:
    `.<name>.<random>.partial` beside it, each holding the storage file written up to the kill."""
    path = Path(path)
    found = [folder for folder in path.parent.glob(f".{path.name}.*.partial") if folder.is_dir()]
    return sorted(found, key=lambda folder: folder.stat().st_mtime)


def _refuse_existing(target: Path, overwrite: bool, note: str = "") -> None:
    if (target.exists() or target.is_symlink()) and not overwrite:
        raise InputError(f"{target} exists already; pass overwrite=True to replace it{note}")


def _move_into_place(staged: Path, target: Path, overwrite: bool) -> None:
    """Rename the finished bag directory onto target, replacing an old one only when allowed."""
    _refuse_existing(target, overwrite, f" (the new bag is kept at {staged})")
    if not (target.exists() or target.is_symlink()):
        os.replace(staged, target)
        return
    trash = Path(tempfile.mkdtemp(dir=target.parent, prefix=f".{target.name}.", suffix=".old"))
    os.replace(target, trash / target.name)
    os.replace(staged, target)
    shutil.rmtree(trash, ignore_errors=True)


RESERVE_NAME = ".reserve"
RESERVE_BYTES = 4 << 20  # given up when the disk is full, so that the bag can still be finished


def _write_reserve(path: Path) -> None:
    """A file of RESERVE_BYTES beside the bag (OSError when the disk cannot hold even that)."""
    with open(path, "wb") as file:
        file.write(bytes(RESERVE_BYTES))
        file.flush()
        os.fsync(file.fileno())


def _topic_name(name: str) -> str:
    key = _topic_key(name)
    if not key:
        raise InputError("empty topic name")
    return "/" + key


class BagRecorder:
    """Streams current commands [A] and stage positions [m] into a rosbag2 directory.

    Messages go to a hidden sibling directory; `close()` renames it onto `path`, so a reader never
    sees a half-written bag. Calls are serialised by a lock, but with the sqlite3 storage every call must
    come from the thread that opened the recorder (sqlite3's rule); the write methods return False once
    the recorder is closed.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        storage: str = "sqlite3",
        input_topic: str = DEFAULT_INPUT_TOPIC,
        output_topic: str = DEFAULT_OUTPUT_TOPIC,
        joint_name: str = DEFAULT_JOINT,
        overwrite: bool = False,
    ) -> None:
        from rosbags.rosbag2 import Writer

        self.path = Path(path)
        self.joint_name = joint_name
        self._overwrite = overwrite
        plugin = _storage_plugin(storage)
        topics = (_topic_name(input_topic), _topic_name(output_topic))
        _refuse_existing(self.path, overwrite)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._staging = Path(tempfile.mkdtemp(dir=self.path.parent, prefix=f".{self.path.name}.", suffix=".partial"))
        self._lock = threading.Lock()
        self.message_count = 0
        self._reserve = self._staging / RESERVE_NAME
        try:
            _write_reserve(self._reserve)
            self._writer = Writer(self._staging / self.path.name, version=JAZZY_BAG_VERSION, storage_plugin=plugin)
            self._writer.open()
            store = _typestore()
            self._input = self._writer.add_connection(topics[0], FLOAT64, typestore=store)
            self._output = self._writer.add_connection(topics[1], JOINT_STATE, typestore=store)
        except BaseException:
            shutil.rmtree(self._staging, ignore_errors=True)
            raise
        self._open = True

    @classmethod
    def open(cls, path: str | os.PathLike, storage: str = "sqlite3", **options: Any) -> BagRecorder:
        """Start recording into path (see the constructor for the options)."""
        return cls(path, storage, **options)

    @property
    def is_open(self) -> bool:
        """True until close() or abort()."""
        return self._open

    def _write(self, connection: Any, timestamp_ns: int, message: Any) -> bool:
        raw = _typestore().serialize_cdr(message, message.__msgtype__)
        with self._lock:
            if not self._open:
                return False
            self._writer.write(connection, int(timestamp_ns), raw)
            self.message_count += 1
            return True

    def write_input(self, stamp_ns: int, value: float) -> bool:
        """Record a current command [A] received at stamp_ns [ns]."""
        message = _typestore().types[FLOAT64](data=float(value))
        return self._write(self._input, stamp_ns, message)

    def write_output(
        self, stamp_ns: int, position: float, velocity: float = 0.0, receive_ns: int | None = None,
        effort: float | None = None,
    ) -> bool:
        """Record a JointState with header stamp stamp_ns [ns], position [m], velocity [m/s] and, when given, as
        effort the current [A] applied over the period that ended at it."""
        types = _typestore().types
        seconds, nanoseconds = divmod(int(stamp_ns), 10**9)
        header = types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=seconds, nanosec=nanoseconds), frame_id=""
        )
        message = types[JOINT_STATE](
            header=header,
            name=[self.joint_name],
            position=np.array([position], dtype=np.float64),
            velocity=np.array([velocity], dtype=np.float64),
            effort=np.array([] if effort is None else [effort], dtype=np.float64),
        )
        return self._write(self._output, stamp_ns if receive_ns is None else receive_ns, message)

    def checkpoint(self) -> None:
        """Make what was written so far durable: the sqlite3 storage commits its transaction (else a failed
        write later, a full disk, rolls all of it back); the mcap storage writes its chunks as they fill."""
        with self._lock:
            connection = getattr(getattr(self._writer, "storage", None), "conn", None)  # rosbags 0.11's sqlite3
            if self._open and connection is not None:
                connection.commit()

    def close(self) -> Path:
        """Finish the bag and rename it into place; returns its path. After a write failed for want of space,
        the reserve kept beside the bag is given up first, so that the storage's last records and
        metadata.yaml fit: the bag is then readable up to the failure. An OSError leaves the staging folder,
        with what it holds, in place."""
        with self._lock:
            if not self._open:
                return self.path
            self._open = False
            self._reserve.unlink(missing_ok=True)
            self._writer.close()
        _move_into_place(self._staging / self.path.name, self.path, self._overwrite)
        shutil.rmtree(self._staging, ignore_errors=True)
        return self.path

    @property
    def staging(self) -> Path:
        """The hidden folder the bag is written in until close()."""
        return self._staging

    def abort(self) -> None:
        """Stop and discard everything recorded."""
        with self._lock:
            was_open, self._open = self._open, False
            if was_open:
                self._writer.abort()
        shutil.rmtree(self._staging, ignore_errors=True)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, error_type: object, error: object, traceback: object) -> None:
        if error_type is None:
            self.close()
        else:
            self.abort()


def _checked_arrays(t: object, input: object, output: object) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    arrays = tuple(np.asarray(values, dtype=np.float64).reshape(-1) for values in (t, input, output))
    if not len(arrays[0]) == len(arrays[1]) == len(arrays[2]) or len(arrays[0]) == 0:
        raise InputError(f"t, input and output need equal non-zero lengths, got {[len(a) for a in arrays]}")
    for name, values in zip(("t", "input", "output"), arrays, strict=True):
        if not np.all(np.isfinite(values)):
            raise InputError(f"'{name}' has a non-finite value at sample {int(np.argmin(np.isfinite(values)))}")
    return arrays


def write_bag(
    path: str | os.PathLike,
    t: object,
    input: object,
    output: object,
    input_topic: str = DEFAULT_INPUT_TOPIC,
    output_topic: str = DEFAULT_OUTPUT_TOPIC,
    storage: str = "sqlite3",
    joint_name: str = DEFAULT_JOINT,
    overwrite: bool = False,
    start_ns: int = DEFAULT_START_NS,
) -> Path:
    """Write samples (t [s], input [A], output [m]) as a rosbag2 directory, atomically.

    Sample k becomes a Float64 on input_topic and then a JointState (stamped, with a finite-difference
    velocity and the input as effort) on output_topic, both at start_ns + t[k] [ns], so reading it back returns
    the same samples.
    """
    t, input, output = _checked_arrays(t, input, output)
    stamps = start_ns + np.round(t * 1e9).astype(np.int64)
    if np.any(np.diff(stamps) <= 0):
        raise InputError("t must increase by at least 1 ns from sample to sample")
    velocity = np.gradient(output, t) if len(t) > 1 else np.zeros_like(output)
    with BagRecorder(path, storage, input_topic, output_topic, joint_name, overwrite) as recorder:
        for stamp, current, position, speed in zip(stamps.tolist(), input, output, velocity, strict=True):
            recorder.write_input(stamp, current)
            recorder.write_output(stamp, position, speed, effort=current)
    return Path(path)
