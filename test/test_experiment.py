"""The probe and the excitation designed from it (sma_stage.experiment), on the second physical stage
(test/antagonistic_plant.py, which shares nothing with the package), and `gpi_tool excitation probe/designed`."""

import json

import numpy as np
import pytest
from antagonistic_plant import VARIANTS, Stage, paper_identification, simulate

from sma_stage.cli import main
from sma_stage.errors import InputError
from sma_stage.experiment.design import INNER_HOLD_TAUS, design_schedule, designed_signal
from sma_stage.experiment.probe import ProbeResult, WireBand, analyse_probe, probe_signal
from sma_stage.identify.checks import moving_parts

PROBE_S, STEP_S = 100.0, 0.2


def probed(stage: Stage, limit: float = 5.0) -> ProbeResult:
    t = np.arange(0.0, PROBE_S, STEP_S)
    current = probe_signal(t, limit, PROBE_S)
    return analyse_probe(t, current, simulate(current, stage))


def thermal_time_constant_s(stage: Stage) -> float:
    """m c / (h A) of one wire: what the probe estimates from the position alone."""
    return stage.density_kg_m3 * stage.specific_heat_j_kg_k * stage.wire_diameter_m / 4.0 / stage.convection_w_m2_k


@pytest.mark.parametrize("name", ["nominal", "thin_wires", "prestrained"])
def test_the_probe_finds_the_lag_and_where_each_wire_moves_the_stage(name):
    found = probed(VARIANTS[name])
    assert found.time_constant_s == pytest.approx(thermal_time_constant_s(VARIANTS[name]), rel=0.35)
    for band in found.wires:
        assert band.moves and 0.0 <= band.start_a < band.end_a <= 5.0
    if name == "prestrained":  # held currents below about 4.2 A do not move it
        assert all(band.start_a > 3.8 for band in found.wires)
    else:
        assert all(band.start_a < 3.0 for band in found.wires)
    assert found.wires[0].travel * found.wires[1].travel < 0.0  # the wires pull opposite ways
    assert "time constant" in found.summary() and json.dumps(found.as_dict())


def test_a_start_below_the_lowest_held_current_is_told_as_such():
    """On `thin_wires` wire b's first held current (2 A) already moves the stage past 5 % of its travel: the start
    interpolated from rest (0.6 A) is not claimed, the summary says "below 2.00 A" and what finds it; on `nominal`
    both starts lie between held currents."""
    thin, nominal = probed(VARIANTS["thin_wires"]), probed(VARIANTS["nominal"])
    assert not thin.wires[1].resolved and thin.wires[1].start_a < thin.wires[1].held_a[0]
    assert "wire b moves the stage from below 2.00 A" in thin.summary() and "lower current limit" in thin.summary()
    assert all(band.resolved for band in nominal.wires) and "below" not in nominal.summary()
    assert json.loads(json.dumps(thin.as_dict()))["wires"][1]["resolved"] is False


def test_a_probe_that_moves_nothing_or_is_not_a_probe_is_refused_in_one_line():
    t = np.arange(0.0, PROBE_S, STEP_S)
    current = probe_signal(t, 5.0, PROBE_S)
    still = np.random.default_rng(0).normal(0.0, 1e-9, t.size)
    for u, y, message in ((current, still, "the probe did not move the stage"),
                          (np.sin(t), simulate(np.sin(t), VARIANTS["nominal"]), "not a probe record"),
                          (current, np.r_[np.nan, still[1:]], "non-finite"),
                          (current[:60], still[:60], "not a probe record: no hold of 4 samples at")):
        with pytest.raises(InputError, match=message) as error:
            analyse_probe(t[: u.size], u, y)
        assert "\n" not in str(error.value)


def band(wire: str, start: float, end: float, moves: bool = True) -> WireBand:
    return WireBand(wire, moves, 1.0 if wire == "a" else -1.0, start, end, (), ())


def test_the_design_spreads_peaks_over_each_band_within_the_limit_and_holds_by_the_lag():
    probe = ProbeResult(4.0, 5.0, (band("a", 1.0, 3.0), band("b", 2.0, 3.5)))
    times, levels = design_schedule(probe, 900.0, seed=3)
    assert times[-1] == 900.0 and np.all(np.diff(times) >= 0.0) and np.max(np.abs(levels)) <= 4.0
    for sign, (start, end) in ((1.0, (1.0, 3.0)), (-1.0, (2.0, 3.5))):
        peaks = np.abs(levels[np.sign(levels) == sign])
        top = peaks.max()
        assert end <= top <= 4.0  # the band's end is passed: the wire saturates
        width = end - start
        quarters = np.linspace(start + 0.2 * width, min(end + 0.2 * width, 4.0), 5)  # where peaks are drawn
        assert all(np.any((peaks >= low) & (peaks <= high))
                   for low, high in zip(quarters[:-1], quarters[1:], strict=True))
    held = np.diff(times)[(np.diff(levels) == 0.0) & (np.abs(levels[1:]) > 0.8 * 2.0) & (np.diff(times) > 0.0)]
    assert held.min() >= INNER_HOLD_TAUS[0] * 5.0 - 1e-9  # within a band no hold is shorter than the least
    slower = design_schedule(ProbeResult(4.0, 10.0, probe.wires), 900.0, seed=3)
    assert slower[0].size < times.size  # longer holds: fewer reversal curves in the same time
    np.testing.assert_array_equal(design_schedule(probe, 900.0, seed=3)[1], levels)  # deterministic by seed
    assert not np.array_equal(design_schedule(probe, 900.0, seed=4)[1], levels)


def test_the_design_drives_only_the_wires_that_move_and_refuses_a_stage_that_does_not():
    one = ProbeResult(5.0, 4.0, (band("a", 4.2, 5.0, moves=False), band("b", 4.2, 4.9)))
    levels = design_schedule(one, 600.0)[1]
    assert np.all(levels <= 0.0) and levels.min() < -4.2
    with pytest.raises(InputError, match="no wire that moves the stage"):
        design_schedule(ProbeResult(5.0, 4.0, (band("a", 0, 0, False), band("b", 0, 0, False))), 600.0)


def test_on_a_narrow_band_stage_the_designed_record_moves_where_the_papers_stops():
    """The prestrained variant moves only above about 4.2 A: the paper's decaying sine (5 A falling to 3.6 A) stops
    moving it after its first cycles; the probe and the design from it keep it moving."""
    stage = VARIANTS["prestrained"]
    t = np.arange(0.0, 1000.0, STEP_S)
    paper = simulate(paper_identification(t), stage)
    moving, parts = moving_parts(paper[t.size // 2:])
    assert np.ptp(paper[t.size // 2:]) < 0.05 * np.ptp(paper)  # the second half barely moves
    probe_t = np.arange(0.0, PROBE_S, STEP_S)
    probe_current = probe_signal(probe_t, 5.0, PROBE_S)
    found = analyse_probe(probe_t, probe_current, simulate(probe_current, stage))
    current = np.r_[probe_current, designed_signal(np.arange(0.0, 900.0, STEP_S), found, 900.0)]
    designed = simulate(current, stage)
    moving, parts = moving_parts(designed[probe_current.size:])
    assert moving >= 0.5 * parts and np.ptp(designed) >= 0.9 * np.ptp(paper)


def test_gpi_tool_writes_a_probe_and_a_design_from_the_recorded_probe(tmp_path, capsys):
    probe_csv = tmp_path / "probe.csv"
    assert main(["excitation", "probe", "--out", str(probe_csv), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["samples"] == 500
    written = np.loadtxt(probe_csv, delimiter=",", skiprows=1)
    recorded = tmp_path / "probe_record.csv"
    np.savetxt(recorded, np.c_[written, simulate(written[:, 1], VARIANTS["nominal"])], delimiter=",",
               header="t,input,output", comments="")
    out = tmp_path / "designed.csv"
    assert main(["excitation", "designed", "--probe", str(recorded), "--seed", "2", "--out", str(out),
                 "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["samples"] == 4500 and report["probe"]["time_constant_s"] > 0.0
    data = np.loadtxt(out, delimiter=",", skiprows=1)
    found = analyse_probe(written[:, 0], written[:, 1], np.loadtxt(recorded, delimiter=",", skiprows=1)[:, 2])
    np.testing.assert_allclose(data[:, 1], designed_signal(data[:, 0], found, 900.0, 2), atol=1e-8)


@pytest.mark.parametrize(("arguments", "message"), [
    (["designed", "--probe", "missing.csv"], "missing.csv"),
    (["probe", "--probe", "x.csv"], "--probe is for the designed excitation"),
])
def test_a_bad_probe_option_is_one_line_and_writes_nothing(tmp_path, capsys, arguments, message):
    out = tmp_path / "x.csv"
    assert main(["excitation", *arguments, "--out", str(out)]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and message in error and not out.exists()
