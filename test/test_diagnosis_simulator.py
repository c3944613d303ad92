"""diagnose on the stage simulator (a physical model with no GPI inside), nothing declared to the
identification: the simulator's own wire heating and cooling is the effect the GPI lacks, and a sensor
delay switched on in the simulator shows up in what is named."""

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
def diagnosed(sensor_delay_s: float, max_rounds: int):
    effects = Effects(sensor_delay_s=sensor_delay_s)
    ident = simulator_record(paper_identification_signal, effects, seed=1)
    valid = simulator_record(paper_validation_signal, effects, seed=2)
    return diagnose(ident, valid, max_rounds=max_rounds)


def test_names_the_simulators_own_thermal_lag_and_nothing_more():
    result = diagnosed(0.0, 4)
    rounds = [[(c.effect, c.reason) for c in found.candidates] for found in result.rounds]
    assert result.effects == ["thermal_lag"], rounds
    tau = StageConfig().thermal_time_constant_s
    assert 0.5 * tau < result.parameters["tau_s"] < 2.0 * tau, "of the order of the wires' thermal time constant"
    assert result.after.rms_pct < 0.75 * result.before.rms_pct


def test_a_switched_on_sensor_delay_lengthens_the_lag_named():
    plain, delayed = diagnosed(0.0, 4), diagnosed(SENSOR_DELAY_S, 1)
    assert delayed.effect == "thermal_lag"
    longer = delayed.parameters["tau_s"] - plain.parameters["tau_s"]
    assert longer == pytest.approx(SENSOR_DELAY_S, rel=0.4), "a lag absorbs a dead time of the same size"
    assert delayed.before.rms_pct > plain.before.rms_pct
    assert delayed.after.rms_pct < 0.75 * delayed.before.rms_pct
