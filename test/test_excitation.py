"""The identification excitations: the designed signal's properties and `gpi_tool excitation`."""

import json

import numpy as np
import pytest

from sma_stage.cli import main
from sma_stage.signals import (
    DESIGNED_LEVELS,
    designed_identification_signal,
    designed_schedule,
    held_levels_signal,
    paper_validation_signal,
)


def test_the_designed_signal_heats_each_wire_to_every_level_within_the_limit():
    t = np.arange(0.0, 1000.0, 0.2)
    current = designed_identification_signal(t, max_current_a=4.0)
    assert np.max(np.abs(current)) <= 4.0 + 1e-12
    times, levels = designed_schedule(4.0)
    peaks = np.unique(np.round(np.abs(levels[levels != 0.0]) / 4.0, 6))
    assert set(DESIGNED_LEVELS) <= set(peaks.tolist())  # every peak level reached
    first_heated = current[np.flatnonzero(current != 0.0)]
    assert first_heated[0] > 0.0 and np.any(first_heated < 0.0)  # wire a first, then wire b
    assert np.max(np.abs(np.diff(current))) < 0.5  # raised-cosine ramps: no steps at 0.2 s
    held = np.diff(times)[np.diff(levels) == 0.0]
    assert held.min() >= 5.0  # holds long enough for a wire's temperature to settle most of the way


def test_gpi_tool_excitation_writes_t_and_input(tmp_path, capsys):
    out = tmp_path / "designed.csv"
    assert main(["excitation", "designed", "--duration", "300", "--step", "0.5", "--max-current", "3", "--out",
                 str(out), "--json"]) in (0, None)
    report = json.loads(capsys.readouterr().out)
    data = np.loadtxt(out, delimiter=",", skiprows=1)
    assert out.read_text().startswith("t,input\n") and data.shape == (600, 2) and report["samples"] == 600
    np.testing.assert_allclose(data[:, 1], designed_identification_signal(data[:, 0], 3.0, 300.0), atol=1e-8)


@pytest.mark.parametrize("arguments", [["--step", "0"], ["--duration", "nan"], ["--max-current", "-1"]])
def test_a_bad_excitation_option_is_one_line_and_writes_nothing(tmp_path, capsys, arguments):
    out = tmp_path / "x.csv"
    assert main(["excitation", "paper", "--out", str(out), *arguments]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and error.startswith("gpi_tool: error:")
    assert not out.exists()


def test_gpi_tool_excitation_writes_the_validation_shapes(tmp_path):
    """`validation` is the paper's two cosines scaled to --max-current; `levels` holds random levels within it for
    --hold seconds each, on both wires, the same for a seed and another for another seed."""
    written = {}
    for name, arguments in (("validation", []), ("levels", ["--hold", "40", "--seed", "3"]),
                            ("again", ["--hold", "40", "--seed", "3"]), ("other", ["--hold", "40", "--seed", "4"])):
        out = tmp_path / f"{name}.csv"
        kind = "validation" if name == "validation" else "levels"
        assert main(["excitation", kind, "--max-current", "4", "--out", str(out), *arguments]) in (0, None)
        written[name] = np.loadtxt(out, delimiter=",", skiprows=1)
    t, validation = written["validation"].T
    np.testing.assert_allclose(validation, paper_validation_signal(t, 0.8), atol=1e-8)
    t, levels = written["levels"].T
    assert t.size == 5000 and np.max(np.abs(levels)) <= 4.0 and levels.min() < -1.0 and levels.max() > 1.0
    holds = levels.reshape(-1, 200)  # 40 s of 0.2 s samples
    assert np.all(holds == holds[:, :1]) and np.all(np.diff(holds[:, 0]) != 0.0)
    np.testing.assert_array_equal(levels, written["again"][:, 1])
    assert not np.array_equal(levels, written["other"][:, 1])
    np.testing.assert_allclose(levels, held_levels_signal(t, 4.0, 40.0, 3), atol=1e-8)


@pytest.mark.parametrize(("arguments", "message"), [(["levels", "--hold", "0"], "--hold must be positive"),
                                                    (["paper", "--hold", "30"], "--hold is for the levels excitation")])
def test_a_bad_hold_is_one_line_and_writes_nothing(tmp_path, capsys, arguments, message):
    out = tmp_path / "x.csv"
    assert main(["excitation", *arguments, "--out", str(out)]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and message in error and not out.exists()
