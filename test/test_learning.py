"""Learning a repeated setpoint (sma_stage.control.learning): it converges on a lagging plant, keeps the best
correction when a period gets worse, stays within its bound, and refuses bad settings in one line (no ROS)."""

import math

import numpy as np
import pytest

from sma_stage.control import Compensator
from sma_stage.control.compensator import imc_gains
from sma_stage.control.learning import MIN_GAIN_FRACTION, PeriodicLearning, learning_lag_s
from sma_stage.errors import InputError
from sma_stage.model.kinds import load_any_model_file
from sma_stage.nodes.launch import DEFAULT_MODEL_FILE
from sma_stage.plant import StageSimulator

DT_S = 0.2
PERIOD_S = 50.0
TAU_S = 5.0


def lagging_run(learning: PeriodicLearning | None, periods: int) -> np.ndarray:
    """Each period's RMS error [m] of a first-order lag of TAU_S, with a gain of 0.8, driven by a sine setpoint of
    1 m amplitude (plus the learnt correction) over `periods` periods: what the PI loop leaves of a stage."""
    samples = round(PERIOD_S / DT_S)
    decay = math.exp(-DT_S / TAU_S)
    position, errors = 0.0, []
    for k in range(periods * samples):
        setpoint = math.sin(2.0 * math.pi * k * DT_S / PERIOD_S)
        error = position - setpoint
        errors.append(error)
        command = setpoint
        if learning is not None:
            learning.record(k * DT_S, error)
            command += learning.correction_m(k * DT_S)
        position = decay * position + (1.0 - decay) * 0.8 * command
    return np.sqrt(np.mean(np.reshape(errors, (periods, samples)) ** 2, axis=1))


def test_the_error_falls_period_by_period_on_a_lagging_stage():
    plain = lagging_run(None, 10)
    learnt = lagging_run(PeriodicLearning(PERIOD_S, learning_lag_s(TAU_S), limit_m=1.0), 10)
    assert plain[-1] > 0.9 * plain[1]  # without it the error stays
    assert learnt[-1] < 0.2 * plain[-1]
    assert np.all(np.diff(learnt[1:]) < 0.0)


def record_periods(learning: PeriodicLearning, periods: list[tuple[float, ...]], first: int = 0) -> None:
    """Record each period's errors [m], one per bin of 0.25 s, from period `first` on."""
    for index, errors in enumerate(periods, start=first):
        for sample, error in enumerate(errors):
            learning.record(index + 0.25 * sample, error)


def test_a_worse_period_takes_the_best_correction_back_and_halves_the_gain():
    learning = PeriodicLearning(1.0, 0.0, limit_m=10.0, gain=0.5, smoothing_s=0.0, resolution_s=0.25)
    record_periods(learning, [(1.0,) * 4, (0.2,) * 4, (0.5, -0.5, 0.5, -0.5)])
    np.testing.assert_allclose(learning.correction, -0.6)  # learnt from the first two periods: -0.5, then -0.1
    learning.record(3.0, 0.0)  # the third period ends: its 0.5 RMS is worse than the second's 0.2
    np.testing.assert_allclose(learning.correction, -0.5)  # the second period's correction, taken back
    assert learning.gain == 0.25
    record_periods(learning, [(1.0,) * 4] * 8, first=3)
    assert learning.gain == 0.5 * MIN_GAIN_FRACTION


def test_the_correction_stays_within_its_bound_and_wraps_round_the_period():
    learning = PeriodicLearning(1.0, 0.25, limit_m=0.3, gain=1.0, smoothing_s=0.0, resolution_s=0.25)
    record_periods(learning, [(0.0, 0.0, 0.0, 4.0)])
    learning.record(1.0, 0.0)
    np.testing.assert_allclose(learning.correction, [0.0, 0.0, -0.3, 0.0])  # the error a lag later: one bin earlier
    assert learning.correction_m(0.5) == -0.3
    assert learning.correction_m(1.5) == -0.3  # round the period
    assert learning.correction_m(0.625) == pytest.approx(-0.15)  # between bins, linearly


@pytest.mark.parametrize("settings", [
    {"period_s": 0.5}, {"gain": 0.0}, {"gain": 1.5}, {"limit_m": -1.0}, {"lag_s": -1.0}, {"resolution_s": 0.0},
    {"smoothing_s": math.nan}, {"period_s": "long"},
])
def test_bad_settings_are_refused_in_one_line(settings):
    arguments = {"period_s": 10.0, "lag_s": 1.0, "limit_m": 1e-4, **settings}
    with pytest.raises(InputError) as refused:
        PeriodicLearning(**arguments)
    assert "\n" not in str(refused.value)


def test_a_non_finite_error_or_a_time_gone_back_is_refused_and_changes_nothing():
    learning = PeriodicLearning(1.0, 0.0, limit_m=1.0)
    learning.record(1.0, 0.1)
    for time_s, error_m in ((1.1, math.nan), (0.5, 0.0), (math.inf, 0.0)):
        with pytest.raises(InputError):
            learning.record(time_s, error_m)
    for time_s in (1.2, 1.4, 1.6, 1.8):
        learning.record(time_s, 0.1)
    assert learning.periods == 0
    learning.record(2.0, 0.0)
    assert learning.periods == 1 and learning.last_rms_m == pytest.approx(0.1)  # none of the refused ones counted


def simulator_sine(learning_period_s: float, periods: int) -> np.ndarray:
    """Each period's RMS error [m] of the shipped model in the PI loop on the simulator (0.2 s steps), tracking a sine
    of PERIOD_S over 200-600 um after 30 s at its start; the compensator learns with learning_period_s."""
    model = load_any_model_file(DEFAULT_MODEL_FILE)
    stage = StageSimulator(seed=0)
    core = Compensator(model, 5.0, **imc_gains(model, DT_S))
    lead_in, samples = round(30.0 / DT_S), round(PERIOD_S / DT_S)
    measured, dt_s, errors = stage.state.measured_position_m, 0.0, []
    for k in range(lead_in + periods * samples):
        if k == lead_in:
            core.learning_period_s = learning_period_s
        setpoint = 4e-4 + 2e-4 * math.sin(2.0 * math.pi * max(k - lead_in, 0) * DT_S / PERIOD_S)
        if k >= lead_in:
            errors.append(measured - setpoint)
        measured = stage.step(core.command(setpoint, measured, dt_s), DT_S).measured_position_m
        dt_s = DT_S
    return np.sqrt(np.mean(np.reshape(errors, (periods, samples)) ** 2, axis=1))


def test_the_compensator_learns_a_repeated_sine_on_the_simulator():
    plain = simulator_sine(0.0, 5)
    learnt = simulator_sine(PERIOD_S, 5)
    np.testing.assert_allclose(learnt[0], plain[0], rtol=1e-9)  # the first period learns, corrects nothing yet
    assert learnt[-1] < 0.7 * plain[-1], f"{1e6 * learnt[-1]:.2f} um against {1e6 * plain[-1]:.2f} um"


def test_learning_waits_for_a_moving_setpoint_and_a_held_one_keeps_its_correction():
    model = load_any_model_file(DEFAULT_MODEL_FILE)
    core = Compensator(model, 5.0, **imc_gains(model, DT_S), learning_period_s=2.0)
    core.command(1e-4, None, DT_S)
    assert core.learning is None  # no measurement: nothing to learn from
    for _ in range(5):
        core.command(1e-4, 1.2e-4, DT_S)
    assert core.learning is None  # a held setpoint before the repeated one: not part of its period
    for k in range(1, 14):  # past a period's end: a correction is learnt
        core.command(1e-4 + 1e-6 * k, 1.2e-4, DT_S)
    assert core.learning is not None and core.learning.periods == 1
    before = core._learnt
    core.command(before[0], 1.2e-4, DT_S)
    assert core._learnt[1] == before[1]


def test_a_bad_learning_period_is_refused_and_the_one_in_force_stays():
    model = load_any_model_file(DEFAULT_MODEL_FILE)
    core = Compensator(model, 5.0, learning_period_s=50.0)
    for bad in (0.3, -1.0, math.nan):
        with pytest.raises(InputError) as refused:
            core.learning_period_s = bad
        assert "\n" not in str(refused.value)
    assert core.learning_period_s == 50.0
    with pytest.raises(InputError, match="period_s"):
        Compensator(model, 5.0, learning_period_s=0.1)


def test_a_control_period_longer_than_the_bins_learns_at_its_own_resolution():
    """At 0.5 s a command, 0.2 s bins would leave three in five empty and no period would learn."""
    model = load_any_model_file(DEFAULT_MODEL_FILE)
    core = Compensator(model, 5.0, **imc_gains(model, 0.5), learning_period_s=10.0)
    for k in range(45):
        core.command(1e-4 + 1e-6 * math.sin(0.2 * math.pi * k * 0.5), 1.1e-4, 0.5 if k else 0.0, hold_s=0.5)
    assert core.learning.resolution_s == 0.5 and core.learning.periods == 2
