"""diagnose on the stage simulator (a physical model with no GPI inside), nothing declared to the
identification: the simulator's own wire heating and cooling is the effect the GPI lacks; a sensor delay
switched on in the simulator is named on top of it when the identification record can tell a dead time
from a lag (two frequencies and a step: the paper's validation signal)."""

import functools

import numpy as np
import pytest

from sma_stage.identify.diagnosis import diagnose
from sma_stage.plant import Effects, StageConfig, simulate
from sma_stage.signals import paper_identification_signal, paper_validation_signal

STEP_S = 0.1  # the simulator's step
RECORD_EVERY = 10  # recorded at 1 Hz, as in docs/identification.md
DURATION_S = 1000.0
SENSOR_DELAY_S = 8.0


def simulator_record(signal, effects: Effects, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t [s], current [A], measured position [m]) of a run from an idle stage."""
    t = np.arange(1, round(DURATION_S / STEP_S) + 1) * STEP_S
    run = simulate(signal(t - STEP_S), STEP_S, effects=effects, seed=seed)
    keep = slice(RECORD_EVERY - 1, None, RECORD_EVERY)
    return run.t_s[keep], run.current_a[keep], run.measured_position_m[keep]


@functools.cache
def diagnosed(sensor_delay_s: float, identify_on_two_cosines: bool):
    effects = Effects(sensor_delay_s=sensor_delay_s)
    signals = (paper_identification_signal, paper_validation_signal)
    first, second = reversed(signals) if identify_on_two_cosines else signals
    return diagnose(simulator_record(first, effects, seed=1), simulator_record(second, effects, seed=2))


def test_names_the_simulators_own_thermal_lag_and_nothing_more():
    result = diagnosed(0.0, identify_on_two_cosines=False)
    rounds = [[(c.effect, c.reason) for c in found.candidates] for found in result.rounds]
    assert result.effects == ["thermal_lag"], rounds
    tau = StageConfig().thermal_time_constant_s
    assert 0.5 * tau < result.parameters["tau_s"] < 2.0 * tau, "of the order of the wires' thermal time constant"
    assert result.after.rms_pct < 0.75 * result.before.rms_pct


def test_names_a_switched_on_sensor_delay_on_top_of_the_lag():
    result = diagnosed(SENSOR_DELAY_S, identify_on_two_cosines=True)
    rounds = [[(c.effect, c.reason) for c in found.candidates] for found in result.rounds]
    assert result.effects == ["thermal_lag", "delay"], rounds
    assert result.parameters["delay_s"] == pytest.approx(SENSOR_DELAY_S, rel=0.1)
    assert result.after.rms_pct < 0.5 * result.before.rms_pct
    assert result.after.rms_pct < 0.95 * result.rounds[1].before.rms_pct, "the delay lowered it further"
