"""Identification on records the package did not make (test/independent_plant.py: no code shared with
sma_stage), none of which starts from rest, and on a real piezo stage's measured data."""

from pathlib import Path

import numpy as np
import pytest
from independent_plant import NOISE_PCT, TRUTH, make_records

from sma_stage.identify.diagnosis import diagnose
from sma_stage.identify.pipeline import identify_recording
from sma_stage.io.csv_io import read_csv
from sma_stage.io.series import make_series
from sma_stage.model import GPIInverseStream

DATA = Path(__file__).parent / "data"
NAMED = {"rate_multiplicative": ("rate", "rate_gain_s_per_A"), "rate_additive": ("rate", "rate_shift_m_s_per_A")}
RMS_LIMIT = 1.2  # validation RMS after, in noise floors
MAX_LIMIT_PCT = 1.5  # largest validation error after, % of span: no start transient


@pytest.mark.parametrize("plant", list(TRUTH))
def test_the_effect_is_named_and_the_whole_validation_record_reaches_the_noise_floor(plant):
    """Identification held at 5 A before its first sample, validation after an arbitrary history: the
    effect named (the rate's form too), every validation sample counted."""
    ident, valid = make_records(plant, seed=0)
    result = diagnose((ident.t, ident.u, ident.y), (valid.t, valid.u, valid.y))
    effect, parameter = NAMED.get(plant, (plant, None))
    assert result.effects == ([] if plant == "none" else [effect])
    if parameter is not None:
        assert parameter in result.parameters
    assert result.after.rms_pct <= RMS_LIMIT * valid.noise_floor_pct
    assert result.after.max_pct <= MAX_LIMIT_PCT
    assert result.validation_predicted_after.size == valid.y.size
    assert valid.noise_floor_pct == pytest.approx(NOISE_PCT, rel=0.05)


def test_the_two_wires_reach_the_noise_floor_on_a_second_seed():
    """Seed 1's wires, where the fit's search once stopped short (1.27 noise floors with scipy's TRF)."""
    ident, valid = make_records("wire_thermal", seed=1)
    result = diagnose((ident.t, ident.u, ident.y), (valid.t, valid.u, valid.y))
    assert result.effects == ["wire_thermal"]
    assert result.after.rms_pct <= RMS_LIMIT * valid.noise_floor_pct


def test_the_report_says_how_each_record_started():
    """With a thermal lag the identification record (held at 5 A) starts held, and the validation record
    (after an arbitrary history) starts where the data put it, not at rest; the report carries both."""
    ident, valid = make_records("thermal_lag", seed=1)
    result = diagnose((ident.t, ident.u, ident.y), (valid.t, valid.u, valid.y), max_rounds=1)
    starts = result.to_dict()["starts"]
    assert starts["identification"]["kind"] == "held"
    assert starts["validation"]["kind"] != "rest"
    assert starts["validation"]["bic"]["rest"] > starts["validation"]["bic"][starts["validation"]["kind"]]
    assert set(result.to_dict()["operators"]["by_count"]) == {"5", "10", "15", "20", "25", "30"}


def _piezo() -> tuple:
    ident = read_csv(DATA / "piezo_identification.csv")
    valid = read_csv(DATA / "piezo_validation.csv")
    return ident, valid


def test_real_piezo_data_is_identified_better_than_by_the_plain_gpi():
    """Measured data: identified on a burst that starts from a hold, validated on one that starts mid-loop.
    The model with what the diagnosis adds, and the start it finds, beats the plain GPI on every sample."""
    ident, valid = _piezo()
    found = identify_recording(ident, validation=valid, diagnose_rounds=1, output_unit="sensor")
    diagnosis = found.diagnosis
    assert diagnosis is not None, found.warnings
    assert diagnosis.after.rms_pct < diagnosis.before.rms_pct
    assert diagnosis.after.max_pct < diagnosis.before.max_pct


def test_the_exact_inverse_recovers_the_measured_input_from_the_measured_output():
    """inverse(measured position) against the measured voltage, on the validation burst, from the plain
    GPI fitted on the identification burst: within a few % of the input's span, over the whole record and
    once the sensor has settled."""
    ident, valid = _piezo()
    found = identify_recording(ident, output_unit="sensor")
    inverse = GPIInverseStream(found.fit.parameters, found.fit.operators, "exact",
                               input_range=(float(np.min(valid.input)), float(np.max(valid.input))))
    recovered = np.array([inverse.step(value) for value in valid.output])
    error = 100.0 * (recovered - valid.input) / np.ptp(valid.input)
    assert np.sqrt(np.mean(error**2)) < 4.0  # the whole record (measured: 3.37 %)
    settled = slice(100, None)  # after its first 0.5 s, the sensor settling from below the loop
    assert np.sqrt(np.mean(error[settled] ** 2)) < 3.0  # measured: 2.65 %


def test_a_record_thinned_for_its_fit_is_scored_on_every_sample_and_a_costly_thinning_is_said():
    """A 2 s lag sampled at 10 Hz, thinned fourfold (the input averaged over 0.4 s blocks): the effect is named
    again and the report scores the model on every validation sample; that is far worse than on the thinned
    samples (2.4 % against 1.5 %; fitted whole, 0.2 %), so a warning says to fit every sample. On the stage
    simulator's 100 Hz records thinning costs nothing (bench/bench_long_refit.py)."""
    ident, valid = make_records("thermal_lag", seed=0)
    ident_series, valid_series = (make_series(r.t, r.u, r.y, name) for r, name in ((ident, "ident"), (valid, "valid")))
    limit = len(ident_series) // 4
    thinned = identify_recording(ident_series, valid_series, diagnose_rounds=1, max_fit_samples=limit)
    entry = thinned.report["thinned"]
    assert entry["samples"] == len(ident_series) and entry["fitted_samples"] <= limit and entry["block"] == 4
    assert thinned.model.effect_names == ["thermal_lag"]
    full_rate = entry["validation_full_rate"]
    assert full_rate["samples"] == len(valid_series)
    assert full_rate["rms_pct"] > 1.25 * thinned.report["diagnosis"]["after"]["validation"]["rms_pct"]
    assert any("max_fit_samples 0" in warning for warning in thinned.warnings), thinned.warnings
    assert "thinned" not in identify_recording(ident_series, valid_series, max_fit_samples=0).report


def test_thinning_averages_the_input_over_each_block_and_keeps_the_last_sample():
    series = make_series(np.arange(10.0), np.arange(10.0) ** 2, np.arange(10.0) * 3.0, "ten", min_samples=1)
    thinned = series.thinned(4)
    np.testing.assert_array_equal(thinned.t, [5.0, 9.0])
    np.testing.assert_array_equal(thinned.input, [np.mean([4, 9, 16, 25]), np.mean([36, 49, 64, 81])])
    np.testing.assert_array_equal(thinned.output, [15.0, 27.0])
    assert series.thinned(1) is series
