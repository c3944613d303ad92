"""The model watch (sma_stage.identify.watch): the level test's false alarms and detection on synthetic window
RMS values; the path test on a record its model made with a structured error added (the model's own error along
the path, repeatable), before and after the plant changes by a fraction of that error."""

import math

import numpy as np
import pytest
from test_two_wire import example_model

from sma_stage.errors import InputError
from sma_stage.identify.path_memory import (
    SCALE_CONFIDENCE,
    _nearest_kept,
    in_a_row_factor,
    lag_one_correlation,
    rms_without_outliers,
    scale_confidence_factor,
)
from sma_stage.identify.watch import CusumOfWindows, DriftTest, ModelWatch, RecentRecord


def windows_to_alarm(levels: np.ndarray, test: DriftTest, held_out: float | None = None) -> list[int]:
    """Indices of the windows at which the level test alarms, restarting it after each alarm."""
    alarms, cusum = [], CusumOfWindows(test, held_out)
    for index, level in enumerate(levels):
        cusum.add(float(level))
        if cusum.drift:
            alarms.append(index)
            cusum.statistic = 0.0
    return alarms


def test_noise_alone_does_not_trip_the_level_test_in_a_thousand_hours_of_windows():
    """Window RMS values scattered +-20 % (log-normal, sigma 0.1 in ln) about a steady level: 180,000 windows of
    20 s (1,000 h) without an alarm at the defaults."""
    rng = np.random.default_rng(0)
    levels = 2e-6 * np.exp(rng.normal(0.0, 0.1, 180_000))
    assert windows_to_alarm(levels, DriftTest()) == []


def test_a_lasting_rise_above_anything_calibrated_trips_the_level_test_within_a_few_windows():
    rng = np.random.default_rng(1)
    test = DriftTest()
    steady = 2e-6 * np.exp(rng.normal(0.0, 0.1, test.warmup_windows + test.calibration_windows + 30))
    for factor, most_windows in ((4.0, 4), (10.0, 1)):
        risen = factor * 2e-6 * np.exp(rng.normal(0.0, 0.1, 10))
        alarms = windows_to_alarm(np.r_[steady, risen], test)
        assert alarms and steady.size <= alarms[0] < steady.size + most_windows, (factor, alarms)
    assert windows_to_alarm(np.r_[steady, 1.5 * steady[-30:]], test) == [], "within the allowance of the ceiling"


def test_the_reference_is_the_larger_of_the_held_out_level_and_the_calibration():
    cusum = CusumOfWindows(DriftTest(calibration_windows=2, warmup_windows=0), held_out_rms=5e-6)
    cusum.add(1e-6)
    assert cusum.reference is None
    cusum.add(2e-6)
    assert cusum.reference == 5e-6 and cusum.ceiling == 5e-6
    cusum.add(6e-6)
    assert not cusum.drift and cusum.statistic == 0.0, "1.2 times the held-out level is within the allowance"


@pytest.mark.parametrize(("setting", "value"), [("window_s", 0.0), ("allowance", 0.5), ("threshold", float("nan")),
                                                ("calibration_windows", 0), ("shift_allowance", -0.1),
                                                ("shift_threshold", 0.0), ("path_radius", float("inf")),
                                                ("min_coverage", 1.5), ("bias_allowance", -1.0),
                                                ("bias_threshold", 0.0), ("bias_threshold", float("inf")),
                                                ("path_time_constants_s", ()), ("path_time_constants_s", (2.0, -8.0))])
def test_bad_settings_are_refused_in_one_line(setting, value):
    with pytest.raises(InputError, match=setting):
        DriftTest(**{setting: value})


FAST = DriftTest(calibration_windows=60)  # a 600 s calibration: five periods of the paths below


def plant_record(path: str, shift_m: float = 0.0, shift_from_s: float = np.inf, seconds: float = 2400.0):
    """(t, u, measured position) of a plant that is the example model plus a structured error of 10 um RMS that
    depends on where the path is (not white: as a model's error is), plus 0.2 um of noise; shift_m added to the
    position from shift_from_s on. path: 'periodic' (a sine of period 120 s) or 'wandering' (a random walk of the
    current that never retraces its steps)."""
    model = example_model()
    rng = np.random.default_rng(2)
    t = np.arange(0.0, seconds, 0.2)
    if path == "periodic":
        u = 4.0 * np.sin(2 * np.pi * t / 120.0)
    else:
        u = np.clip(np.cumsum(rng.normal(0.0, 0.05, t.size)), -4.5, 4.5)
    predicted = model.predict(t, u)
    span = predicted.max() - predicted.min()
    structured = 1.4e-5 * np.sin(2 * np.pi * (predicted - predicted.min()) / span * 1.5)
    position = predicted + structured + rng.normal(0.0, 2e-7, t.size) + np.where(t >= shift_from_s, shift_m, 0.0)
    return t, u, position


def watch_record(t, u, position, test: DriftTest = FAST, chunk: int = 50) -> tuple[ModelWatch, list[tuple]]:
    """Feed a record in chunks (as the node does); the (time [s], path drift, level drift) of each flag, the tests
    restarted after each."""
    watch, flags = ModelWatch(example_model(), test), []
    for start in range(0, t.size, chunk):
        part = slice(start, start + chunk)
        watch.step(t[part], u[part], position[part])
        if watch.state == "drift":
            flags.append((t[part][-1], watch.path_drift, watch.cusum.drift))
            watch.restart_tests()
    return watch, flags


def watch_until_drift(t, u, position, chunk: int) -> tuple[ModelWatch, float]:
    """Feed a record in chunks until the first drift: (the watch, the last time fed [s])."""
    watch = ModelWatch(example_model(), FAST)
    for start in range(0, t.size, chunk):
        watch.step(t[start:start + chunk], u[start:start + chunk], position[start:start + chunk])
        if watch.state == "drift":
            break
    return watch, float(t[start:start + chunk][-1])


def test_the_path_test_stays_quiet_on_the_models_own_repeatable_error():
    watch, flags = watch_record(*plant_record("periodic", seconds=4800.0))
    assert flags == []
    assert watch.coverage is not None and watch.coverage > 0.5, "the periodic path is remembered ground"
    assert watch.last_innovation_rms < 0.1 * watch.cusum.reference


def test_a_shift_of_a_fifth_of_the_models_error_is_flagged_by_the_path_test_within_two_minutes():
    """2 um added from 1500 s where the model's structured error is 10 um RMS: the level test cannot see it, the
    path test does within six windows (120 s)."""
    _, flags = watch_record(*plant_record("periodic", 2e-6, 1500.0))
    assert flags, "not flagged"
    when, path_drift, level_drift = flags[0]
    assert 1500.0 <= when <= 1620.0 and path_drift and not level_drift, flags


def test_a_steady_shift_under_the_size_tests_allowance_is_flagged_by_the_mean_within_two_minutes():
    """0.5 um added from 1500 s, a twentieth of the model's structured error and under what the path test's size
    counts as no change: its mean (the bias test, scaled by how far a window's mean wandered while calibrating)
    flags it within six windows."""
    watch, when = watch_until_drift(*plant_record("periodic", 5e-7, 1500.0), chunk=50)
    assert watch.bias_drift, "not flagged by the mean"
    assert 1500.0 <= when <= 1620.0
    assert watch.path_statistic <= FAST.shift_threshold and not watch.cusum.drift, "the size and level did not trip"
    assert 0.0 < watch.held_out_bias_m < 0.5e-6


def test_the_calibrations_held_out_comparison_keeps_as_many_neighbours_as_a_judged_sample_gets():
    """Each remembered sample is compared with its nearest samples of the other passes, as many as a new sample is
    compared with (PATH_NEIGHBOURS), not with every one within the radius: those reach further along the path."""
    index = np.array([[3, 9, 1, 9, 2], [9, 9, 0, 4, 9]])
    np.testing.assert_array_equal(_nearest_kept(index, 9, 2), [[3, 1], [0, 4]])
    np.testing.assert_array_equal(_nearest_kept(index, 9, 3), [[3, 1, 2], [0, 4, 9]])


def test_one_wild_calibration_window_does_not_set_the_bias_tests_scale():
    means = 0.1e-6 * np.random.default_rng(3).standard_normal(112)
    plain = float(np.sqrt(np.mean(np.square(means))))
    assert rms_without_outliers(means) == pytest.approx(plain)  # nothing far out: the RMS of all
    assert rms_without_outliers(np.append(means, 3.8e-6)) == pytest.approx(plain)  # the settling pass left out
    assert rms_without_outliers(np.append(means, 3 * plain)) > plain  # a tail within reach is kept
    assert rms_without_outliers(means[:4]) == 0.0  # too few windows to say


def with_pass_wander(t, position, wander_m: float, seed: int = 0, period_s: float = 120.0):
    """position plus a residual that differs from pass to pass (each period_s [s] of the path: wander_m [m] times
    a draw per pass, on a shape of its own), as a loop whose timing jitters gives a model's residual."""
    per_pass = np.random.default_rng(seed).standard_normal(int(t[-1] // period_s) + 1)[(t // period_s).astype(int)]
    return position + wander_m * per_pass * np.sin(2 * np.pi * t / 40.0 + 0.3)


def size_trips(t, u, position) -> int:
    """How often the size test trips over a record (its statistic restarted after each trip, the other tests'
    left alone, so that their trips do not restart it)."""
    watch, trips = ModelWatch(example_model(), FAST), 0
    for start in range(0, t.size, 50):
        watch.step(t[start:start + 50], u[start:start + 50], position[start:start + 50])
        if watch.size_drift:
            trips += 1
            watch.path_statistic = 0.0
    return trips


def test_the_size_test_measures_how_far_passes_differ_and_still_flags_a_large_shift():
    """A residual that differs by 4 um from pass to pass, nothing changing: the calibration's held-out windows
    measure it, so the size test counts as change only what exceeds the largest of them (over two records of
    6000 s it tripped 19 times without that level, 4 with it; the rest is the bias test's to weigh); a 20 um
    shift is still flagged by the path test within 120 s."""
    t, u, position = plant_record("periodic", seconds=6000.0)
    steady, _ = watch_record(t, u, position)
    assert 0.0 < steady.held_out_size_m < 1e-6, "passes that agree: a small level (the model's error is 10 um)"
    assert sum(size_trips(t, u, with_pass_wander(t, position, 4e-6, seed)) for seed in (0, 1)) <= 6
    t, u, position = plant_record("periodic", 2e-5, 3000.0, seconds=4000.0)
    watch, flags = watch_record(t, u, with_pass_wander(t, position, 4e-6))
    assert watch.held_out_size_m > 1.5e-6, "passes 4 um apart: a scale near it"
    after = [(when, path_drift) for when, path_drift, _ in flags if when >= 3000.0]
    assert after and after[0][0] <= 3120.0 and after[0][1], flags


def test_the_bias_scale_widens_by_how_windows_in_a_row_share_their_mean():
    """Independent window means: the scale is their RMS (the factor about 1); means that persist from window to
    window (an AR(1) of 0.8, as a loop whose timing jitters gives on the simulator) trip three windows together,
    so the scale widens by what three in a row spread more (1.58); windows not adjacent say nothing of it."""
    rng, windows = np.random.default_rng(0), 120
    independent = rng.standard_normal(windows)
    slots = np.arange(windows)
    assert 1.0 <= in_a_row_factor(lag_one_correlation(slots, independent), 3) < 1.1
    persistent = np.zeros(windows)
    for k in range(1, windows):
        persistent[k] = 0.8 * persistent[k - 1] + rng.standard_normal()
    assert in_a_row_factor(lag_one_correlation(slots, persistent), 3) == pytest.approx(
        math.sqrt(1 + (4 * 0.8 + 2 * 0.64) / 3), abs=0.1)
    assert in_a_row_factor(lag_one_correlation(2 * np.arange(windows), persistent), 3) == 1.0


def test_the_bias_scale_is_widened_to_an_upper_bound_of_what_few_windows_measure():
    """The RMS of 40 windows' means falls under the true scale in about half of the calibrations; widened by
    scale_confidence_factor, in about 1 - SCALE_CONFIDENCE of them (the lag-one correlation estimated from the
    windows too), whether the windows are independent or share their mean as an AR(1) of 0.8."""
    rng, windows, draws = np.random.default_rng(1), 40, 400
    for rho in (0.0, 0.8):
        measured_low = widened_low = 0
        for _ in range(draws):
            means = np.zeros(windows + 100)
            for k in range(1, means.size):
                means[k] = rho * means[k - 1] + rng.standard_normal()
            means, true_scale = means[100:], 1.0 / math.sqrt(1.0 - rho**2)
            measured = math.sqrt(np.mean(np.square(means)))
            measured_low += measured < true_scale
            estimated = lag_one_correlation(np.arange(windows), means)
            widened_low += measured * scale_confidence_factor(estimated, windows) < true_scale
        assert 0.4 < measured_low / draws < 0.65, rho
        assert widened_low / draws < 2.0 * (1.0 - SCALE_CONFIDENCE), rho
    many = rng.standard_normal(400)
    assert scale_confidence_factor(lag_one_correlation(np.arange(400), many), 400) < 1.1, "many windows: hardly widened"


def test_a_path_never_retraced_is_not_judged_and_gives_no_alarm():
    watch, flags = watch_record(*plant_record("wandering", 2e-6, 1500.0))
    assert flags == [] and watch.judged_windows == 0


def test_the_watch_flags_a_plant_that_moved_by_far_more_than_its_error():
    """Positions made by the model itself with 0.5 um of noise; 10 um added to every position from 1500 s on:
    drift within three windows (60 s)."""
    model = example_model()
    rng = np.random.default_rng(2)
    t = np.arange(0.0, 2400.0, 0.2)
    u = 4.0 * np.sin(2 * np.pi * t / 120.0)
    position = model.predict(t, u) + rng.normal(0.0, 5e-7, t.size)
    position[t >= 1500.0] += 1e-5
    _, flags = watch_record(t, u, position)
    assert flags and 1500.0 <= flags[0][0] <= 1560.0, flags


def test_a_watch_started_from_the_applied_currents_history_predicts_as_one_run_over_it_all():
    model, t = example_model(), np.arange(0.0, 400.0, 0.2)
    u = 4.0 * np.sin(2 * np.pi * t / 90.0)
    position = model.predict(t, u)
    later = ModelWatch(model, history=(t[:1000], u[:1000]))
    residual = later.step(t[1000:], u[1000:], position[1000:])
    np.testing.assert_allclose(residual, 0.0, atol=1e-15)


def test_the_recent_record_keeps_the_last_seconds_in_order():
    record, t = RecentRecord(60.0), np.arange(0.0, 300.0, 0.5)
    for start in range(0, t.size, 7):
        part = t[start:start + 7]
        record.add(part, 2.0 * part, 3.0 * part)
    kept_t, kept_u, kept_y = record.arrays()
    np.testing.assert_array_equal(kept_t, t[t > t[-1] - 60.0])
    np.testing.assert_array_equal(kept_u, 2.0 * kept_t)
    np.testing.assert_array_equal(kept_y, 3.0 * kept_t)


def test_the_drift_says_where_the_change_began():
    watch, _ = watch_until_drift(*plant_record("periodic", 2e-6, 1500.0), chunk=5)
    assert watch.state == "drift" and 1500.0 - FAST.window_s <= watch.onset_s <= 1500.0 + FAST.window_s


@pytest.mark.parametrize(("arguments", "message"), [
    (["--loop-jitter", "-1"], "--loop-jitter must be 0 or more control steps"),
    (["--watch-starts", "0"], "--watch-starts must be from 1 to 100, got 0"),
    (["--families", "nope"], "--families: unknown model family 'nope'"),
])
def test_the_watch_bench_refuses_bad_arguments_in_one_line(arguments, message):
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parent.parent / "bench" / "bench_watch.py"
    run = subprocess.run([sys.executable, str(script), *arguments], capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and run.stdout == ""
    assert message in run.stderr.strip().splitlines()[-1] and "Traceback" not in run.stderr
