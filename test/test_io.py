"""Data I/O: CSV and rosbag2 reading and writing, the Series checks, zero-order-hold alignment."""

import math
import os
import shutil
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from sma_stage.errors import InputError
from sma_stage.io import (
    BagRecorder,
    align_zero_order_hold,
    load_series,
    make_series,
    read_csv,
    write_bag,
    write_csv,
)
from sma_stage.io.rosbag_io import FLOAT64, JOINT_STATE, _typestore, unfinished_bags

STORAGES = ("sqlite3", "mcap")


def excitation(n=60, dt=0.01, seed=0):
    """A time base [s], a current [A] and a hysteresis-like position [m] with awkward float values."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt + rng.uniform(0, 1e-4, n)
    current = 4.0 * np.sin(2 * np.pi * t) + rng.normal(0, 1e-3, n)
    position = 1e-4 * np.tanh(current / 2) + rng.normal(0, 1e-9, n)
    return t, current, position


def assert_input_error(excinfo, *phrases):
    message = str(excinfo.value)
    assert "\n" not in message
    for phrase in phrases:
        assert phrase in message, f"{phrase!r} not in {message!r}"


def siblings(path):
    return sorted(p.name for p in Path(path).parent.iterdir())


# ---------------------------------------------------------------- Series


def test_make_series_keeps_values_and_freezes_arrays():
    t, u, y = excitation()
    series = make_series(t, u, y, source="lab")
    assert np.array_equal(series.t, t) and np.array_equal(series.input, u) and np.array_equal(series.output, y)
    assert len(series) == len(t) and series.output_span == pytest.approx(np.ptp(y))
    with pytest.raises(ValueError):
        series.input[0] = 1.0


@pytest.mark.parametrize(
    ("column", "value", "phrases"),
    [("t", np.nan, ["column 't'", "nan", "sample 7"]), ("input", np.inf, ["column 'input'", "inf", "sample 7"]),
     ("output", -np.inf, ["column 'output'", "-inf", "sample 7"])],
)
def test_make_series_names_the_first_non_finite_value(column, value, phrases):
    arrays = dict(zip(("t", "input", "output"), excitation(), strict=True))
    arrays[column][[7, 9]] = value
    with pytest.raises(InputError) as excinfo:
        make_series(arrays["t"], arrays["input"], arrays["output"])
    assert_input_error(excinfo, *phrases)


def test_make_series_rejects_bad_shapes_and_flat_data():
    t, u, y = excitation()
    cases = [
        ((t, u[:-1], y), ["differ in length", "input 59"]),
        ((t[:5], u[:5], y[:5]), ["only 5 samples", "at least 20"]),
        ((t[::-1], u, y), ["time must increase", "sample 1"]),
        ((t, np.full_like(u, 2.5), y), ["no excitation", "'input'"]),
        ((t, u, np.full_like(y, 3e-5)), ["no excitation", "'output'"]),
        ((t, u, np.zeros_like(y)), ["no excitation", "'output'"]),
    ]
    for arrays, phrases in cases:
        with pytest.raises(InputError) as excinfo:
            make_series(*arrays, source="run7")
        assert_input_error(excinfo, "run7:", *phrases)


def test_min_samples_is_adjustable():
    t, u, y = excitation(n=10)
    assert len(make_series(t, u, y, min_samples=10)) == 10


def test_split_slice_and_window():
    t, u, y = excitation(n=100)
    series = make_series(t, u, y)
    first, rest = series.split(0.7)
    assert (len(first), len(rest)) == (70, 30)
    assert np.array_equal(np.concatenate([first.output, rest.output]), y)
    assert rest.t[0] == t[70]
    middle = series.slice(10, 20)
    assert np.array_equal(middle.input, u[10:20])
    window = series.window(t[5], t[15])
    assert np.array_equal(window.t, t[5:15])
    for fraction in (0.0, 1.0, 0.001):
        with pytest.raises(InputError):
            series.split(fraction)


# ---------------------------------------------------------------- CSV


def test_csv_round_trip_is_exact(tmp_path):
    t, u, y = excitation()
    y[3] = 1.2345678901234567e-300
    path = tmp_path / "data.csv"
    write_csv(path, make_series(t, u, y), comment="recorded on the bench\nsecond line")
    back = read_csv(path)
    assert np.array_equal(back.t, t) and np.array_equal(back.input, u) and np.array_equal(back.output, y)
    assert back.source == str(path) and not back.time_is_index
    assert path.read_text().splitlines()[2] == "t,input,output"
    assert siblings(path) == ["data.csv"]


def test_csv_column_mapping_comments_and_other_delimiters(tmp_path):
    t, u, y = excitation(n=25)
    rows = "\n".join(f"{p!r}; label; {c!r}; {s!r}  # inline note" for s, c, p in zip(t.tolist(), u.tolist(), y.tolist(), strict=True))
    path = tmp_path / "mapped.csv"
    path.write_text(f"# exported by the bench\n\npos; note; current; time\n{rows}\n\n# end\n")
    series = load_series(path, columns={"t": "time", "input": "current", "output": "pos"})
    assert np.array_equal(series.t, t) and np.array_equal(series.input, u) and np.array_equal(series.output, y)


def test_csv_sample_index_as_time(tmp_path):
    _, u, y = excitation(n=30)
    path = tmp_path / "quasi.csv"
    path.write_text("current\tpos\n" + "".join(f"{c!r}\t{p!r}\n" for c, p in zip(u.tolist(), y.tolist(), strict=True)))
    series = read_csv(path, columns={"t": None, "input": "current", "output": "pos"})
    assert series.time_is_index and np.array_equal(series.t, np.arange(30))
    indexed = tmp_path / "indexed.csv"
    write_csv(indexed, series)
    assert read_csv(indexed).time_is_index


GOOD_ROWS = "".join(f"{0.1 * k},{np.sin(k)},{np.cos(k)}\n" for k in range(30))


@pytest.mark.parametrize(
    ("text", "phrases"),
    [
        ("", ["empty file"]),
        ("# only a comment\n\n", ["empty file"]),
        ("t,input,output\n", ["no data rows"]),
        ("t,input,y\n" + GOOD_ROWS, ["no column 'output'", "columns found: t, input, y"]),
        ("t,input,output\n0,1,2\n0.1,abc,3\n" + GOOD_ROWS, ["line 3", "column 'input'", "'abc' is not a number"]),
        ("t,input,output\n0,1,2\n0.1,2\n", ["line 3 has 2 cells", "header has 3"]),
        ("t,input,output\n0,1,2,3\n", ["line 2 has 4 cells"]),
        ("t,input,output\n0,1,\n", ["line 2", "'' is not a number"]),
        ("t,input,output\n0,1,nan\n" + GOOD_ROWS, ["line 2", "column 'output'", "not finite"]),
        ("0,1,2\n" + GOOD_ROWS, ["line 1 is data", "expected a header"]),
        ("t,input,t\n" + GOOD_ROWS, ["duplicate column", "t"]),
        ("t,input,output\n" + GOOD_ROWS + "0.5,1,2\n", ["time must increase"]),
        ("t,input,output\n" + "".join(f"{k},2.0,{k * k}\n" for k in range(30)), ["no excitation", "'input'"]),
        ("t,input,output\n0,1,2\n1,2,3\n", ["only 2 samples"]),
    ],
)
def test_bad_csv_gives_one_line_error(tmp_path, text, phrases):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(InputError) as excinfo:
        load_series(path)
    assert_input_error(excinfo, str(path), *phrases)
    assert siblings(path) == ["bad.csv"]


def test_csv_missing_file_and_unknown_role(tmp_path):
    with pytest.raises(InputError) as excinfo:
        load_series(tmp_path / "nothing.csv")
    assert_input_error(excinfo, "nothing.csv", "no such file")
    path = tmp_path / "ok.csv"
    path.write_text("t,input,output\n" + GOOD_ROWS)
    with pytest.raises(InputError) as excinfo:
        load_series(path, columns={"current": "input"})
    assert_input_error(excinfo, "unknown column role", "current")


def test_binary_file_is_refused(tmp_path):
    path = tmp_path / "image.csv"
    path.write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe" * 10)
    with pytest.raises(InputError) as excinfo:
        load_series(path)
    assert_input_error(excinfo, "not a UTF-8 text file")


# ---------------------------------------------------------------- rosbag2


@pytest.mark.parametrize("storage", STORAGES)
def test_bag_round_trip_values_and_timing(tmp_path, storage):
    t, u, y = excitation()
    path = tmp_path / "run"
    write_bag(path, t, u, y, storage=storage)
    assert siblings(path) == ["run"]
    series = load_series(path)
    assert np.array_equal(series.input, u) and np.array_equal(series.output, y)
    np.testing.assert_allclose(series.t, t - t[0], rtol=0, atol=1.5e-9)
    assert "/joint_states: effort and position stamped together" in series.source
    by_topic = load_series(path, input_topic="current_cmd")
    assert np.array_equal(by_topic.input, u) and np.array_equal(by_topic.output, y)
    assert "/current_cmd" in by_topic.source and "/joint_states" in by_topic.source


@pytest.mark.parametrize("storage", STORAGES)
def test_bag_joint_state_content(tmp_path, storage):
    from rosbags.rosbag2 import Reader

    t, u, y = excitation(n=25)
    path = write_bag(tmp_path / "run", t, u, y, storage=storage, start_ns=5 * 10**9)
    store = _typestore()
    with Reader(path) as reader:
        states = [
            (stamp, store.deserialize_cdr(raw, connection.msgtype))
            for connection, stamp, raw in reader.messages()
            if connection.msgtype == JOINT_STATE
        ]
    assert len(states) == len(t)
    stamp, message = states[4]
    header_ns = message.header.stamp.sec * 10**9 + message.header.stamp.nanosec
    assert header_ns == stamp == 5 * 10**9 + round(t[4] * 1e9)
    assert list(message.name) == ["stage_x"] and list(message.effort) == [u[4]]
    assert message.position[0] == y[4]
    assert message.velocity[0] == pytest.approx(np.gradient(y, t)[4])


def test_storage_file_inside_the_bag_reads_too(tmp_path):
    t, u, y = excitation()
    path = write_bag(tmp_path / "run", t, u, y, storage="mcap")
    series = load_series(path / "run.mcap")
    assert np.array_equal(series.output, y)


def test_write_bag_refuses_to_overwrite_and_leaves_nothing_on_bad_input(tmp_path):
    t, u, y = excitation()
    path = write_bag(tmp_path / "run", t, u, y)
    before = sorted(p.name for p in path.iterdir())
    with pytest.raises(InputError) as excinfo:
        write_bag(path, t, u, -y)
    assert_input_error(excinfo, "exists already", "overwrite=True")
    assert np.array_equal(load_series(path).output, y)
    write_bag(path, t, u, -y, overwrite=True)
    assert np.array_equal(load_series(path).output, -y)
    assert sorted(p.name for p in path.iterdir()) == before and siblings(path) == ["run"]
    u[3] = np.nan
    for args, phrase in (((t, u, y), "'input' has a non-finite value at sample 3"), ((t, y[:-1], y), "equal")):
        with pytest.raises(InputError) as excinfo:
            write_bag(tmp_path / "other", *args)
        assert_input_error(excinfo, phrase)
    with pytest.raises(InputError) as excinfo:
        write_bag(tmp_path / "other", t, y, y, storage="rosbag1")
    assert_input_error(excinfo, "unknown rosbag2 storage")
    assert siblings(path) == ["run"]


def test_recorder_publishes_only_on_close_and_abort_discards(tmp_path):
    t, u, y = excitation()
    path = tmp_path / "live"
    recorder = BagRecorder.open(path, "mcap")
    for k in range(len(t)):
        stamp = 10**9 + round(t[k] * 1e9)
        assert recorder.write_input(stamp, u[k]) and recorder.write_output(stamp, y[k], 0.0)
    assert not path.exists()
    assert recorder.close() == path and not recorder.is_open
    assert not recorder.write_input(0, 1.0)
    assert np.array_equal(load_series(path).output, y) and siblings(path) == ["live"]
    aborted = BagRecorder(tmp_path / "aborted")
    aborted.write_input(1, 1.0)
    aborted.abort()
    assert siblings(path) == ["live"]


def write_custom_bag(path, topics, storage="sqlite3"):
    """A bag with the given {topic: [(receive_ns, message), ...]} written straight through rosbags."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = _typestore()
    plugin = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}[storage]
    with Writer(path, version=9, storage_plugin=plugin) as writer:
        for topic, messages in topics.items():
            kind = messages[0][1].__msgtype__
            connection = writer.add_connection(topic, kind, typestore=store)
            for stamp, message in messages:
                writer.write(connection, stamp, store.serialize_cdr(message, kind))
    return path


def float64(value):
    return _typestore().types[FLOAT64](data=float(value))


def joint_state(stamp_ns, positions, names=("stage_x",)):
    types = _typestore().types
    time = types["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    return types[JOINT_STATE](
        header=types["std_msgs/msg/Header"](stamp=time, frame_id=""),
        name=list(names),
        position=np.array(positions, dtype=float),
        velocity=np.array([], dtype=float),
        effort=np.array([], dtype=float),
    )


def test_missing_topic_lists_the_topics_found(tmp_path):
    t, u, y = excitation()
    path = write_bag(tmp_path / "run", t, u, y, output_topic="stage/position_state")
    with pytest.raises(InputError) as excinfo:
        load_series(path)
    assert_input_error(excinfo, "no topic 'joint_states'", "/current_cmd [std_msgs/msg/Float64]",
                       "/stage/position_state [sensor_msgs/msg/JointState]")
    assert len(load_series(path, output_topic="position_state")) == len(t)


def test_topic_names_match_with_slash_namespace_or_unique_suffix(tmp_path):
    t, u, y = excitation()
    path = write_bag(tmp_path / "ns", t, u, y, input_topic="/robot1/current_cmd", output_topic="robot1/joint_states")
    for input_topic in (None, "current_cmd", "/current_cmd", "robot1/current_cmd", "/robot1/current_cmd/"):
        assert np.array_equal(load_series(path, input_topic=input_topic).input, u)
    samples = [(10**9 + k, float64(k)) for k in range(30)]
    states = [(10**9 + k, joint_state(10**9 + k, [k * 1e-6])) for k in range(30)]
    twin = write_custom_bag(tmp_path / "twin", {"/a/current_cmd": samples, "/b/current_cmd": samples,
                                                "/joint_states": states})
    with pytest.raises(InputError) as excinfo:
        load_series(twin)
    assert_input_error(excinfo, "matches several", "/a/current_cmd, /b/current_cmd")
    assert np.array_equal(load_series(twin, input_topic="b/current_cmd").input, np.arange(30.0))


def test_wrong_message_type_empty_bag_and_missing_joint(tmp_path):
    types = _typestore().types
    text = [(10**9 + k, types["std_msgs/msg/String"](data="hi")) for k in range(3)]
    states = [(10**9 + k, joint_state(10**9 + k, [k * 1e-6])) for k in range(30)]
    wrong = write_custom_bag(tmp_path / "wrong", {"/current_cmd": text, "/joint_states": states})
    with pytest.raises(InputError) as excinfo:
        load_series(wrong)
    assert_input_error(excinfo, "'/current_cmd' has type std_msgs/msg/String", "expected std_msgs/msg/Float64")

    BagRecorder(tmp_path / "empty").close()
    with pytest.raises(InputError) as excinfo:
        load_series(tmp_path / "empty")
    assert_input_error(excinfo, "no messages")

    samples = [(10**9 + k, float64(k)) for k in range(30)]
    other = [(10**9 + k, joint_state(10**9 + k, [1.0, 2.0], names=("arm", "wrist"))) for k in range(30)]
    unnamed = write_custom_bag(tmp_path / "joints", {"/current_cmd": samples, "/joint_states": other})
    with pytest.raises(InputError) as excinfo:
        load_series(unnamed)
    assert_input_error(excinfo, "no joint 'stage_x'", "joints found: arm, wrist")

    empty = [(10**9 + k, joint_state(10**9 + k, [], names=("stage_x",))) for k in range(30)]
    named = write_custom_bag(tmp_path / "empty_positions", {"/current_cmd": samples, "/joint_states": empty})
    with pytest.raises(InputError) as excinfo:
        load_series(named)
    assert_input_error(excinfo, "joint 'stage_x' is named but has no position in any of the 30 messages")


def test_float64_output_topic_is_accepted(tmp_path):
    samples = [(10**9 + 10 * k, float64(np.sin(k))) for k in range(30)]
    outputs = [(10**9 + 10 * k + 5, float64(np.cos(k))) for k in range(30)]
    path = write_custom_bag(tmp_path / "plain", {"/current_cmd": samples, "/position": outputs}, "mcap")
    series = load_series(path, output_topic="position")
    assert np.array_equal(series.input, np.sin(np.arange(30))) and np.array_equal(series.output, np.cos(np.arange(30)))
    np.testing.assert_allclose(series.t, np.arange(30) * 10e-9)


@pytest.mark.parametrize("storage", STORAGES)
def test_truncated_or_malformed_bag_gives_one_line_error(tmp_path, storage):
    t, u, y = excitation(n=400)
    good = write_bag(tmp_path / "good", t, u, y, storage=storage)
    storage_file = next(p for p in good.iterdir() if p.name != "metadata.yaml")

    cut = tmp_path / "cut"
    shutil.copytree(good, cut)
    data = storage_file.read_bytes()
    (cut / storage_file.name).write_bytes(data[: len(data) // 2])

    no_metadata = tmp_path / "no_metadata"
    shutil.copytree(good, no_metadata)
    (no_metadata / "metadata.yaml").unlink()

    bad_metadata = tmp_path / "bad_metadata"
    shutil.copytree(good, bad_metadata)
    (bad_metadata / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed\n")

    no_storage = tmp_path / "no_storage"
    shutil.copytree(good, no_storage)
    (no_storage / storage_file.name).unlink()

    cases = {cut: "truncated or damaged", no_metadata: "metadata.yaml is missing",
             bad_metadata: "cannot read the rosbag2", no_storage: "cannot read the rosbag2"}
    for path, phrase in cases.items():
        with pytest.raises(InputError) as excinfo:
            load_series(path)
        assert_input_error(excinfo, str(path), phrase)


def brute_force_hold(input_ns, input_values, output_ns):
    """For each output time, the value of the last input at or before it (None before the first input)."""
    held = []
    for when in output_ns:
        earlier = [(stamp, k) for k, stamp in enumerate(input_ns) if stamp <= when]
        held.append(input_values[max(earlier)[1]] if earlier else None)
    return held


def test_zero_order_hold_matches_brute_force():
    rng = np.random.default_rng(3)
    input_ns = np.sort(rng.choice(np.arange(1_000, 2_000), 40, replace=False))
    input_values = rng.normal(size=40)
    output_ns = np.sort(rng.choice(np.arange(900, 2_100), 120, replace=False))
    output_values = rng.normal(size=120)
    t, held, output = align_zero_order_hold(input_ns, input_values, output_ns, output_values)
    expected = brute_force_hold(input_ns, input_values, output_ns)
    kept = [k for k, value in enumerate(expected) if value is not None]
    assert np.array_equal(held, [expected[k] for k in kept])
    assert np.array_equal(output, output_values[kept])
    np.testing.assert_allclose(t, (output_ns[kept] - output_ns[kept[0]]) * 1e-9)


def test_zero_order_hold_sorts_and_drops_repeated_stamps():
    t, held, output = align_zero_order_hold(
        np.array([20, 0, 10]), np.array([2.0, 0.0, 1.0]), np.array([15, 5, 15, 25]), np.array([1.5, 0.5, 1.6, 2.5])
    )
    assert np.array_equal(held, [0.0, 1.0, 2.0]) and np.array_equal(output, [0.5, 1.6, 2.5])
    np.testing.assert_allclose(t, [0.0, 10e-9, 20e-9])


def recorded_bag(path, output_stamp, input_period_ns=7_000_000, output_period_ns=2_000_000, n_out=200):
    """Slow commands and fast positions from a recorder; output_stamp(k, receive_ns) gives the header stamp."""
    start = 10**18
    inputs = [(start + k * input_period_ns, np.sin(0.3 * k)) for k in range(n_out * output_period_ns // input_period_ns)]
    with BagRecorder(path) as recorder:
        for k in range(n_out):
            receive = start + 1_000_000 + k * output_period_ns
            while inputs and inputs[0][0] <= receive:
                recorder.write_input(*inputs.pop(0))
            recorder.write_output(output_stamp(k, receive), 1e-5 * k, receive_ns=receive)
    return path


def expected_hold(start=10**18, input_period_ns=7_000_000, n_in=57, at=()):
    stamps = start + np.arange(n_in) * input_period_ns
    return brute_force_hold(stamps, np.sin(0.3 * np.arange(n_in)), at)


def test_bag_alignment_uses_header_stamps_when_set(tmp_path):
    latency = 300_000
    path = recorded_bag(tmp_path / "stamped", lambda k, receive: receive - latency)
    series = load_series(path)
    stamps = 10**18 + 1_000_000 + np.arange(200) * 2_000_000 - latency
    held = expected_hold(at=stamps)
    kept = [k for k, value in enumerate(held) if value is not None]
    assert np.array_equal(series.input, [held[k] for k in kept])
    assert np.array_equal(series.output, 1e-5 * np.array(kept))
    np.testing.assert_allclose(series.t, (stamps[kept] - stamps[kept[0]]) * 1e-9)


@pytest.mark.parametrize("stamp", [lambda k, receive: 0, lambda k, receive: 5 * 10**9 + k * 2_000_000])
def test_bag_alignment_falls_back_to_receive_time(tmp_path, stamp):
    """Zero header stamps, or stamps on another clock (e.g. simulated time), use the bag receive time."""
    series = load_series(recorded_bag(tmp_path / "bag", stamp))
    receive = 10**18 + 1_000_000 + np.arange(200) * 2_000_000
    held = expected_hold(at=receive)
    assert np.array_equal(series.input, held)
    np.testing.assert_allclose(series.t, (receive - receive[0]) * 1e-9)


def jittered_bag(path, with_effort=lambda k: True, n=200, period_ns=10_000_000, jitter_ns=6_000_000):
    """A stage's bag: position k stamped at k periods, the current applied over the period before it as its effort
    (where with_effort(k)), and the same current on current_cmd arriving up to jitter_ns after that stamp."""
    rng = np.random.default_rng(3)
    start, current = 10**18, np.round(np.sin(0.05 * np.arange(n)), 6)
    arrivals = start + np.arange(n) * period_ns + rng.integers(0, jitter_ns, n)
    with BagRecorder(path, input_topic="current_cmd") as recorder:
        for k in range(n):
            stamp = start + k * period_ns
            recorder.write_input(int(arrivals[k]), current[k])
            recorder.write_output(stamp, 1e-5 * k, receive_ns=stamp + jitter_ns,
                                  effort=current[k] if with_effort(k) else None)
    return current


def test_a_bag_with_the_current_in_joint_states_effort_reads_the_pair_stamped_together(tmp_path):
    """The input topic timed by arrival misses the current a position went with wherever it arrived late; the
    effort stamped with the position does not. Naming the input topic, or a bag whose messages do not all carry
    the effort (an older stage), reads the topic as before."""
    current = jittered_bag(tmp_path / "stamped")
    series = load_series(tmp_path / "stamped")
    assert np.array_equal(series.input, current) and np.array_equal(series.output, 1e-5 * np.arange(200))
    by_arrival = load_series(tmp_path / "stamped", input_topic="current_cmd")
    assert not np.array_equal(by_arrival.input, current[-by_arrival.input.size:])
    jittered_bag(tmp_path / "mixed", with_effort=lambda k: k % 2 == 0)
    mixed = load_series(tmp_path / "mixed")
    assert "/current_cmd" in mixed.source
    assert np.array_equal(mixed.input, by_arrival.input)


def test_a_bag_whose_effort_is_not_finite_reads_the_input_topic_or_says_in_one_line_what_is_missing(tmp_path):
    """A NaN effort is no current: the bag reads the input topic as an older stage's; without one, one line."""
    path = tmp_path / "nan_effort"
    with BagRecorder(path, input_topic="current_cmd") as recorder:
        for k in range(40):
            stamp = 10**18 + k * 10_000_000
            recorder.write_input(stamp, 0.1 * k)
            recorder.write_output(stamp, 1e-5 * k, effort=math.nan if k == 7 else 0.1 * k)
    series = load_series(path)
    assert "/current_cmd" in series.source and np.all(np.isfinite(series.input))
    with pytest.raises(InputError, match="current_applied") as refused:
        load_series(path, input_topic="current_applied")
    assert "\n" not in str(refused.value)


def test_csv_with_byte_order_mark_and_crlf_lines(tmp_path):
    t, u, y = excitation(n=20)
    rows = "".join(f"{a!r},{b!r},{c!r}\r\n" for a, b, c in zip(t.tolist(), u.tolist(), y.tolist(), strict=True))
    path = tmp_path / "excel.csv"
    path.write_bytes(("\ufefft,input,output\r\n" + rows).encode("utf-8"))
    series = load_series(path)
    assert np.array_equal(series.t, t) and np.array_equal(series.output, y)


@pytest.mark.parametrize("umask", [0o022, 0o002, 0o077])
def test_atomic_writes_follow_the_umask_and_keep_an_existing_files_mode(tmp_path, umask):
    """A new file gets 0666 less the umask, as open() gives (it was 0600 whatever the umask: a compensator running
    as another user could not read the model); a replaced file keeps its mode."""
    from sma_stage.io.atomic import atomic_write_text

    previous = os.umask(umask)
    try:
        atomic_write_text(tmp_path / "new.yaml", "a: 1\n")
        shared = tmp_path / "shared.yaml"
        shared.write_text("old")
        shared.chmod(0o644)
        atomic_write_text(shared, "new")
    finally:
        os.umask(previous)
    assert stat.S_IMODE((tmp_path / "new.yaml").stat().st_mode) == 0o666 & ~umask
    assert stat.S_IMODE(shared.stat().st_mode) == 0o644 and shared.read_text() == "new"


def test_an_atomic_write_that_fails_names_the_file_not_its_temporary(tmp_path):
    from sma_stage.io.atomic import atomic_write_text

    target = tmp_path / "model.yaml"
    target.mkdir()  # a folder where the file should go: the rename fails
    with pytest.raises(OSError) as failed:
        atomic_write_text(target, "x")
    assert failed.value.filename == str(target) and ".tmp" not in str(failed.value)
    assert [path.name for path in tmp_path.iterdir()] == ["model.yaml"], "no temporary file left"


def test_a_write_sweeps_the_temporaries_killed_writes_left_and_keeps_a_running_writers(tmp_path):
    from sma_stage.io.atomic import STALE_TEMPORARY_S, atomic_write_text

    ended = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead_pid = int(ended.stdout)
    target = tmp_path / "model.yaml"
    old = time.time() - 2 * STALE_TEMPORARY_S
    leftover = tmp_path / f".model.yaml.{dead_pid}.abc123.tmp"
    fresh = tmp_path / f".model.yaml.{dead_pid}.def456.tmp"  # too new: could be a write just begun
    running = tmp_path / f".model.yaml.{os.getpid()}.ghi789.tmp"  # a live writer's
    other = tmp_path / f".other.yaml.{dead_pid}.jkl012.tmp"  # another file's
    for path in (leftover, fresh, running, other):
        path.write_text("half")
    for path in (leftover, running, other):
        os.utime(path, (old, old))
    atomic_write_text(target, "new")
    assert target.read_text() == "new"
    assert not leftover.exists() and fresh.exists() and running.exists() and other.exists()


def test_a_huge_bad_cell_is_quoted_short_and_1_0_is_not_ten(tmp_path):
    rows = ["t,input,output"] + [f"{k},{np.sin(k / 10):.6f},{np.tanh(k / 30):.6f}" for k in range(100)]
    giant, underscored = list(rows), list(rows)
    giant[8] = "7," + "x" * 1_000_000 + ",0.1"
    underscored[8] = "7,1_0,0.1"
    for name, lines, quoted in (("giant.csv", giant, "'xxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxx... (1,000,000 characters)'"),
                                ("underscored.csv", underscored, "'1_0'")):
        path = tmp_path / name
        path.write_text("\n".join(lines) + "\n")
        with pytest.raises(InputError) as refused:
            read_csv(path)
        assert str(refused.value) == f"{path}: line 9, column 'input': {quoted} is not a number"


def test_a_recording_killed_before_it_finished_is_found_beside_its_bag(tmp_path):
    """A node killed while recording leaves its hidden staging folder: unfinished_bags lists it (the
    identification node reports it when it records to the same path again)."""
    script = (f"import os, time; from sma_stage.io import BagRecorder; "
              f"r = BagRecorder({str(tmp_path / 'session')!r}); print('open', flush=True); time.sleep(60)")
    child = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "open"
    finally:
        child.kill()
        child.wait(10)
    (left,) = unfinished_bags(tmp_path / "session")
    assert left.name.startswith(".session.") and left.name.endswith(".partial")
    assert not (tmp_path / "session").exists()
    assert unfinished_bags(tmp_path / "other") == []


def test_a_wide_header_is_answered_in_linear_time(tmp_path):
    """header.count(name) for each name made a 200,000-column header take minutes."""
    names = [f"c{k}" for k in range(200_000)]
    path = tmp_path / "wide.csv"
    path.write_text(",".join(["t", "input", "output", *names]) + "\n" + ",".join(["0"] * 200_003) + "\n")
    started = time.monotonic()
    with pytest.raises(InputError, match="only 1 samples"):
        read_csv(path)
    path.write_text(",".join([*names, "c7"]) + "\n")
    with pytest.raises(InputError, match="duplicate column name"):
        read_csv(path)
    assert time.monotonic() - started < 10.0


@pytest.mark.parametrize("kind", ["fifo", "folder", "device"])
def test_a_data_path_that_is_not_a_regular_file_is_refused_at_once(tmp_path, kind):
    path = {"folder": tmp_path, "device": Path("/dev/zero"), "fifo": tmp_path / "data.fifo"}[kind]
    if kind == "fifo":
        os.mkfifo(path)
    with pytest.raises(InputError, match="not a regular file"):
        read_csv(path)


def test_the_fast_reader_and_the_strict_reader_agree(tmp_path):
    """Lines numpy reads as the strict reader would go through numpy; the others (single quotes) through the
    strict reader: the same values either way."""
    t, u, y = excitation(n=50)
    plain = tmp_path / "plain.csv"
    plain.write_text("t,input,output # header\n" + "".join(
        f'{a!r}, "{b!r}" ,{c!r}\n\n# comment\n' for a, b, c in zip(t.tolist(), u.tolist(), y.tolist(), strict=True)))
    quoted = tmp_path / "quoted.csv"
    quoted.write_text(plain.read_text().replace('"', "'"))
    first, second = read_csv(plain), read_csv(quoted)
    assert np.array_equal(first.input, u) and np.array_equal(second.input, u) and np.array_equal(first.t, second.t)


def test_a_long_curve_is_drawn_thinned_with_its_peaks():
    from sma_stage.plots import MAX_DRAWN_POINTS, drawn_indices

    values = np.sin(np.linspace(0.0, 100.0, 2_000_001))
    values[777_777] = 5.0
    shown = drawn_indices(values)
    assert shown.size <= MAX_DRAWN_POINTS + 2 and np.all(np.diff(shown) > 0)
    assert values[shown].max() == 5.0 and values[shown].min() == values.min()
    assert drawn_indices(values[:100]).tolist() == list(range(100))
