"""The model watch (sma_stage.identify.watch): the drift test's false alarms and detection on synthetic window
RMS values, and the watch's residual on a record its model made, before and after the plant changes."""

import numpy as np
import pytest
from test_two_wire import example_model

from sma_stage.errors import InputError
from sma_stage.identify.watch import CusumOfWindows, DriftTest, ModelWatch


def windows_to_alarm(levels: np.ndarray, test: DriftTest, held_out: float | None = None) -> list[int]:
    """Indices of the windows at which the test alarms, restarting it after each alarm."""
    alarms, cusum = [], CusumOfWindows(test, held_out)
    for index, level in enumerate(levels):
        cusum.add(float(level))
        if cusum.drift:
            alarms.append(index)
            cusum = CusumOfWindows(test, held_out)
    return alarms


def test_noise_alone_does_not_trip_the_test_in_a_thousand_hours_of_windows():
    """Window RMS values scattered +-20 % (log-normal, sigma 0.1 in ln) about a steady level: 180,000 windows of
    20 s (1,000 h) without an alarm at the defaults."""
    rng = np.random.default_rng(0)
    levels = 2e-6 * np.exp(rng.normal(0.0, 0.1, 180_000))
    assert windows_to_alarm(levels, DriftTest()) == []


def test_a_lasting_rise_of_the_residual_trips_it_within_a_few_windows():
    rng = np.random.default_rng(1)
    steady = 2e-6 * np.exp(rng.normal(0.0, 0.1, 30))
    for factor, most_windows in ((2.5, 4), (4.0, 2), (10.0, 1)):
        risen = factor * 2e-6 * np.exp(rng.normal(0.0, 0.1, 10))
        alarms = windows_to_alarm(np.r_[steady, risen], DriftTest())
        assert alarms and 30 <= alarms[0] < 30 + most_windows, (factor, alarms)


def test_the_reference_is_the_larger_of_the_held_out_level_and_the_calibration():
    cusum = CusumOfWindows(DriftTest(calibration_windows=2, warmup_windows=0), held_out_rms=5e-6)
    cusum.add(1e-6)
    assert cusum.reference is None
    cusum.add(1e-6)
    assert cusum.reference == 5e-6
    cusum.add(6e-6)
    assert not cusum.drift and cusum.statistic == 0.0, "1.2 times the held-out level is within the allowance"


@pytest.mark.parametrize(("setting", "value"), [("window_s", 0.0), ("allowance", 0.5), ("threshold", float("nan")),
                                                ("calibration_windows", 0)])
def test_bad_settings_are_refused_in_one_line(setting, value):
    with pytest.raises(InputError, match=setting):
        DriftTest(**{setting: value})


def test_the_watch_follows_its_own_model_and_flags_a_plant_that_moved():
    """Positions made by the model itself with 0.5 um of noise: the residual is the noise and the watch stays ok
    over 1,500 s; 10 um added to every position from then on: drift within three windows (60 s)."""
    model = example_model()
    rng = np.random.default_rng(2)
    t = np.arange(0.0, 2400.0, 0.2)
    u = 4.0 * np.sin(2 * np.pi * t / 120.0)
    position = model.predict(t, u) + rng.normal(0.0, 5e-7, t.size)
    position[t >= 1500.0] += 1e-5
    watch = ModelWatch(model)
    flagged_at = None
    for start in range(0, t.size, 50):  # in chunks, as the node feeds it
        chunk = slice(start, start + 50)
        residual = watch.step(t[chunk], u[chunk], position[chunk])
        if t[chunk][-1] < 1500.0:
            assert np.sqrt(np.mean(residual**2)) < 1e-6 and watch.state == "ok"
        elif flagged_at is None and watch.state == "drift":
            flagged_at = t[chunk][-1]
    assert flagged_at is not None and flagged_at - 1500.0 <= 60.0, flagged_at
