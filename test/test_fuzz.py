"""Fuzzing the readers, the numerical core at extreme magnitudes, the command line and the compensator's
callbacks: whatever comes in, the answer is a result or InputError (one line), never another exception, and
nothing in force changes on a refusal. The number of cases each tries is its max_examples (hypothesis)."""

import math
import os

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sma_stage.cli import main
from sma_stage.control import Compensator
from sma_stage.errors import InputError
from sma_stage.io import read_csv
from sma_stage.model import GPIInverseStream, IdentifiedModel, forward, load_model_file

SHIPPED = load_model_file("config/model_default.yaml")
SHIPPED_TEXT = SHIPPED.to_yaml_text()
EXPLORE = os.environ.get("HYPOTHESIS_PROFILE") == "explore"  # conftest.py: new cases each run, more of them
FAST = settings(max_examples=2000 if EXPLORE else 200, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture])
ANY_FLOAT = st.floats(allow_nan=True, allow_infinity=True, width=64)
FINITE = st.floats(allow_nan=False, allow_infinity=False, width=64)

cells = st.one_of(FINITE.map(repr), st.sampled_from(["", "nan", "inf", "-inf", "1_0", "0x10", "1e400", "--1",
                                                      "NaN", " 3 ", "\"4\"", "1,5", "é", "\x00"]),
                  st.text(max_size=8))


def one_line(error: BaseException) -> bool:
    text = str(error)
    return "\n" not in text and 0 < len(text) <= 400


@FAST
@given(header=st.lists(st.sampled_from(["t", "input", "output", "time", "x", "", "t"]), min_size=0, max_size=4),
       rows=st.lists(st.lists(cells, min_size=0, max_size=4), min_size=0, max_size=40),
       delimiter=st.sampled_from([",", ";", "\t", " "]))
def test_the_csv_reader_answers_a_series_or_one_line(tmp_path_factory, header, rows, delimiter):
    path = tmp_path_factory.mktemp("csv") / "data.csv"
    path.write_text("\n".join(delimiter.join(row) for row in [header, *rows]) + "\n", encoding="utf-8",
                    errors="surrogatepass")
    try:
        series = read_csv(path, min_samples=2)
    except InputError as error:
        assert one_line(error), str(error)
    else:
        assert np.all(np.isfinite(series.t)) and np.all(np.isfinite(series.output))


model_lines = SHIPPED_TEXT.splitlines()


@FAST
@given(edits=st.lists(st.tuples(st.integers(0, len(model_lines) - 1),
                                st.sampled_from(["drop", "duplicate", "number", "text", "indent"]),
                                st.one_of(FINITE.map(repr), st.text(max_size=6))), min_size=1, max_size=4))
def test_the_model_file_reader_answers_a_model_or_one_line(edits):
    lines = list(model_lines)
    for index, kind, value in edits:
        index %= len(lines)
        key = lines[index].split(":")[0]
        lines[index] = {"drop": "", "duplicate": lines[index] + "\n" + lines[index], "number": f"{key}: {value}",
                        "text": f"{key}: '{value}'", "indent": "  " + lines[index]}[kind]
    try:
        model = IdentifiedModel.from_yaml_text("\n".join(lines))
    except InputError as error:
        assert one_line(error), str(error)
    else:
        assert isinstance(model, IdentifiedModel)


yaml_keys = st.one_of(st.sampled_from(["kind", "operators", "parameters", "a1", "a9", "effects", "state", "x"]),
                      st.integers(-3, 3), st.booleans(), st.none())
yaml_scalars = st.one_of(FINITE, st.integers(-(10**400), 10**400), st.text(max_size=5), st.booleans(), st.none())
yaml_documents = st.recursive(yaml_scalars, lambda inner: st.one_of(
    st.lists(inner, max_size=4), st.dictionaries(yaml_keys, inner, max_size=4)), max_leaves=12)


@FAST
@given(replacement=yaml_documents, where=st.sampled_from(["parameters", "operators", "effects", "state", "top"]),
       depth=st.integers(0, 200))
def test_any_yaml_structure_in_a_model_answers_a_model_or_one_line(replacement, where, depth):
    """Mixed-type keys, integers beyond a float, nesting (up to 200 levels): a model or one line, never a
    TypeError, OverflowError or RecursionError (which used to end the compensator)."""
    import yaml

    document = yaml.safe_load(SHIPPED_TEXT)
    nested = replacement
    for _ in range(depth):
        nested = [nested]
    if where == "top":
        document = nested
    else:
        document[where] = nested
    try:
        text = yaml.safe_dump(document)
    except (yaml.YAMLError, RecursionError):
        return  # a structure the YAML writer itself cannot write
    try:
        model = IdentifiedModel.from_yaml_text(text)
    except InputError as error:
        assert one_line(error), str(error)
    else:
        assert isinstance(model, IdentifiedModel)


@FAST
@given(targets=st.lists(FINITE, min_size=1, max_size=20), method=st.sampled_from(["exact", "analytic"]))
def test_the_inverse_gives_a_current_within_its_range_for_any_finite_target(targets, method):
    stream = GPIInverseStream(SHIPPED.parameters, SHIPPED.operators, method, input_range=(-5.0, 5.0))
    for target in targets:
        current = stream.step(target)
        assert -5.0 <= current <= 5.0, (target, current)


@FAST
@given(currents=st.lists(st.floats(-1e6, 1e6), min_size=1, max_size=30))
def test_the_forward_model_is_finite_for_any_current_within_the_input_bounds(currents):
    assert np.all(np.isfinite(forward(np.array(currents), SHIPPED.parameters, SHIPPED.operators)))


@FAST
@given(calls=st.lists(st.tuples(ANY_FLOAT, st.one_of(st.none(), ANY_FLOAT), ANY_FLOAT), min_size=1, max_size=20),
       method=st.sampled_from(["exact", "analytic"]), kp=st.floats(0.0, 100.0), ki=st.floats(0.0, 1e4))
def test_the_compensator_commands_within_its_limit_or_refuses_one_non_finite_value(calls, method, kp, ki):
    core = Compensator(SHIPPED, 5.0, method, kp=kp, ki=ki)
    for setpoint, measured, dt in calls:
        finite = math.isfinite(setpoint) and (measured is None or math.isfinite(measured)) and \
            math.isfinite(dt) and dt >= 0.0
        before = core.command_a
        try:
            current = core.command(setpoint, measured, dt)
        except InputError as error:
            assert not finite, (setpoint, measured, dt, str(error))
            assert core.command_a == before, "a refused call changes no command"
        else:
            assert finite and -5.0 <= current <= 5.0, (setpoint, measured, dt, current)


words = st.sampled_from(["fit", "diagnose", "simulate", "paper", "--operators", "0", "1", "31", "-3", "1e9",
                         "--holdout", "0.5", "nan", "--rounds", "9", "--columns", "t=,input=x", "--unit", "",
                         "--json", "--rate-hz", "inf", "--duration", "--seed", "--input", "validation", "--validate",
                         "--out", "/proc/forbidden", "missing.csv", "--effect", "bogus=1", "--set", "a=b"])


@settings(FAST, max_examples=1000 if EXPLORE else 150)
@given(argv=st.lists(words, min_size=0, max_size=7))
def test_the_command_line_ends_with_0_or_2_and_one_error_line(argv, capsys):
    try:
        status = main(argv)
    except SystemExit as stopped:  # argparse: --help or an argument error
        status = stopped.code
    error = capsys.readouterr().err.strip().splitlines()
    assert status in (0, 2), (argv, status)
    if status == 2:
        assert [line for line in error if not line.startswith("gpi_tool: ") or "error" in line][-1:], (argv, error)
        assert "Traceback" not in "\n".join(error), (argv, error)
