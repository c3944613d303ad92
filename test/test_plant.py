"""Tests of the stage physics simulator (sma_stage.plant): shape of the map, physics, effects, numerics, API."""

import dataclasses
import time

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from sma_stage.errors import InputError
from sma_stage.plant import Effects, SimulationResult, StageConfig, StageSimulator, simulate
from sma_stage.signals import IDENTIFICATION_PERIOD_S, paper_identification_signal

PERIOD = IDENTIFICATION_PERIOD_S
QUIET = StageConfig(sensor_noise_m=0.0, sensor_resolution_m=0.0)


def constant_run(current_a: float, seconds: float, dt: float = 0.5, **kwargs) -> SimulationResult:
    return simulate(np.full(int(round(seconds / dt)), current_a), dt, **kwargs)


@pytest.fixture(scope="module")
def identification_run() -> SimulationResult:
    t = np.arange(0.0, 1000.0, 0.1)
    return simulate(paper_identification_signal(t), 0.1)


@pytest.fixture(scope="module")
def stepped_amplitude_run() -> tuple[np.ndarray, SimulationResult]:
    dt = 0.5
    t = np.arange(0.0, 5 * PERIOD, dt)
    amplitude = np.select([t < 3 * PERIOD, t < 4 * PERIOD], [5.0, 4.2], 3.8)
    current = amplitude * np.sin(2 * np.pi * t / PERIOD)
    return t, simulate(current, dt, config=QUIET)


def cycle(t: np.ndarray, result: SimulationResult, index: int) -> tuple[np.ndarray, np.ndarray]:
    keep = (t >= index * PERIOD) & (t < (index + 1) * PERIOD)
    return result.current_a[keep], result.position_m[keep]


def loop_area(current: np.ndarray, position: np.ndarray) -> float:
    """|closed integral of x di| over one cycle [A m]."""
    closed_i = np.append(current, current[0])
    closed_x = np.append(position, position[0])
    return abs(np.trapezoid(closed_x, closed_i))


def test_identification_signal_gives_a_hysteresis_loop(identification_run):
    t = identification_run.t_s
    keep = (t > PERIOD) & (t <= 2 * PERIOD)
    current = identification_run.current_a[keep]
    position = identification_run.position_m[keep]
    stroke = np.ptp(position)
    assert 0.8e-3 < stroke < 1.2e-3, "about +/- 0.5 mm, the paper's stage"
    area = loop_area(current, position)
    assert 0.1 * stroke * np.ptp(current) < area < 0.6 * stroke * np.ptp(current)
    rising = np.gradient(current) > 0
    at_zero_rising = position[rising][np.argmin(np.abs(current[rising]))]
    at_zero_falling = position[~rising][np.argmin(np.abs(current[~rising]))]
    assert 0.1 * stroke < at_zero_falling - at_zero_rising < 0.6 * stroke, "a loop, not a rectangle"


def test_static_map_has_a_threshold_then_rises_and_saturates():
    currents = np.arange(0.5, 5.01, 0.5)
    final = np.array([constant_run(i, 300.0, config=QUIET).position_m[-1] for i in currents])
    rest = StageSimulator(QUIET).state.position_m
    assert np.all(np.abs(final[currents < 1.6] - rest) < 5e-6), "Joule heating i^2 R: nothing moves at low current"
    growth = np.diff(final)
    assert np.all(growth[currents[1:] > 2.0] > 0.0)
    middle, top = growth[currents[1:] == 3.0][0], growth[-1]
    assert middle > 100e-6
    assert top < 0.6 * middle, "the last 0.5 A moves the stage much less than the middle of the range"


def test_map_is_asymmetric(identification_run):
    position = identification_run.position_m
    rest = identification_run.position_m[0]
    push, pull = position.max() - rest, rest - position.min()
    assert abs(push - pull) > 0.05 * (push + pull)


def test_minor_loops_lie_inside_the_major_loop(stepped_amplitude_run):
    t, result = stepped_amplitude_run
    major_i, major_x = cycle(t, result, 2)
    edges = np.linspace(-5.0, 5.0, 41)
    major_bin = np.digitize(major_i, edges)
    tolerance = 2e-6
    for index in (3, 4):
        minor_i, minor_x = cycle(t, result, index)
        assert loop_area(minor_i, minor_x) < loop_area(major_i, major_x)
        for b in np.unique(np.digitize(minor_i, edges)):
            near = np.abs(major_bin - b) <= 1
            inside = minor_x[np.digitize(minor_i, edges) == b]
            assert major_x[near].min() - tolerance <= inside.min()
            assert inside.max() <= major_x[near].max() + tolerance
    first_i, first_x = cycle(t, result, 1)
    assert np.abs(first_x - major_x).max() < 1e-6, "the major loop repeats itself"


def test_temperatures_rise_when_heated_and_return_to_ambient():
    ambient = QUIET.ambient_temperature_k
    tau = QUIET.thermal_time_constant_s
    heat = constant_run(4.0, 100.0, config=QUIET)
    temps = heat.wire_temperatures_k
    assert temps[-1, 0] > ambient + 50.0
    assert np.all(np.diff(temps[:, 0]) > 0.0)
    assert np.allclose(temps[:, 1], ambient), "the relay sends no current to wire B"
    sim = StageSimulator(QUIET)
    hot = sim.step(4.0, 100.0)
    cooled = sim.step(0.0, 12 * tau)
    assert abs(cooled.wire_temperatures_k[0] - ambient) < 0.01
    assert cooled.martensite_fractions[0] > hot.martensite_fractions[0] + 0.3, "martensite forms again on cooling"


def test_conduction_into_the_clamps_cools_the_wire():
    no_conduction = dataclasses.replace(QUIET, thermal_conductivity_w_m_k=0.0)
    hot = constant_run(5.0, 300.0, config=no_conduction)
    assert hot.martensite_fractions[-1, 0] == pytest.approx(0.0, abs=1e-9)
    rise = hot.wire_temperatures_k[-1, 0] - QUIET.ambient_temperature_k
    assert rise == pytest.approx(QUIET.steady_temperature_rise_k(5.0), rel=1e-6)
    clamped = constant_run(5.0, 300.0, config=QUIET)
    assert clamped.wire_temperatures_k[-1, 0] - QUIET.ambient_temperature_k < 0.9 * rise
    assert clamped.martensite_fractions[-1, 0] > 0.05, "the wire next to the clamps stays partly martensite"


def test_thermal_time_constant_matches_the_step_response():
    dt = 0.05
    below_transformation = constant_run(1.0, 200.0, dt=dt, config=QUIET)
    rise = below_transformation.wire_temperatures_k[:, 0] - QUIET.ambient_temperature_k
    assert below_transformation.martensite_fractions[-1, 0] == 1.0
    time_to_63 = below_transformation.t_s[np.argmax(rise >= (1.0 - np.exp(-1.0)) * rise[-1])]
    assert time_to_63 == pytest.approx(QUIET.thermal_time_constant_s, rel=0.25)


def test_more_wire_nodes_change_the_stage_little():
    coarse = constant_run(4.0, 300.0, config=QUIET).position_m[-1]
    fine = constant_run(4.0, 300.0, config=dataclasses.replace(QUIET, wire_nodes=32)).position_m[-1]
    assert abs(fine - coarse) < 0.02 * abs(fine)


def test_relay_routes_negative_current_to_wire_b():
    state = StageSimulator(QUIET).step(-4.0, 100.0)
    assert state.wire_temperatures_k[1] > state.wire_temperatures_k[0] + 50.0
    assert state.martensite_fractions[1] < 0.5 < state.martensite_fractions[0]
    assert state.position_m < -100e-6


def test_thermal_time_constant_is_seconds_to_tens_of_seconds():
    assert 2.0 < StageConfig().thermal_time_constant_s < 60.0


def test_effects_are_off_by_default():
    assert all(getattr(Effects(), name) == 0.0 for name in ("ambient_drift_k_per_s", "sensor_delay_s",
                                                            "creep_amplitude_m", "load_change_n"))
    current = 4.5 * np.sin(2 * np.pi * np.arange(0.0, 300.0, 0.5) / PERIOD)
    plain = simulate(current, 0.5, seed=1)
    explicit = simulate(current, 0.5, effects=Effects(creep_time_constant_s=10.0, load_change_time_s=5.0), seed=1)
    assert np.array_equal(plain.measured_position_m, explicit.measured_position_m)


def test_ambient_drift_warms_the_wires_and_pushes_further():
    base = constant_run(3.3, 400.0, config=QUIET)
    warm = constant_run(3.3, 400.0, config=QUIET, effects=Effects(ambient_drift_k_per_s=0.05))
    assert warm.wire_temperatures_k[-1, 0] - base.wire_temperatures_k[-1, 0] == pytest.approx(20.0, rel=0.1)
    assert warm.position_m[-1] > base.position_m[-1] + 20e-6


def test_sensor_delay_shifts_the_measurement():
    dt, delay = 0.1, 2.0
    current = 4.5 * np.sin(2 * np.pi * np.arange(0.0, 200.0, dt) / PERIOD)
    result = simulate(current, dt, config=QUIET, effects=Effects(sensor_delay_s=delay))
    lag = int(round(delay / dt))
    np.testing.assert_array_equal(result.measured_position_m[lag:], result.position_m[:-lag])
    rest = StageSimulator(QUIET).state.position_m
    assert np.all(result.measured_position_m[:lag] == rest)


def test_creep_adds_a_slow_drift_in_the_direction_of_the_load():
    tau, amplitude = 100.0, 20e-6
    base = constant_run(4.5, 600.0, config=QUIET)
    assert base.position_m[-1] > Effects().creep_reference_m, "the load is past the creep's saturation"
    crept = constant_run(4.5, 600.0, config=QUIET,
                         effects=Effects(creep_amplitude_m=amplitude, creep_time_constant_s=tau))
    drift = crept.position_m - base.position_m
    assert np.all(np.diff(drift[200:]) >= 0.0)
    assert drift[-1] == pytest.approx(amplitude, rel=0.05)
    assert drift[int(tau / 0.5)] < 0.7 * amplitude


def test_load_change_moves_the_stage_after_its_time():
    when = 200.0
    base = constant_run(4.5, 400.0, config=QUIET)
    loaded = constant_run(4.5, 400.0, config=QUIET, effects=Effects(load_change_n=20.0, load_change_time_s=when))
    before = base.t_s < when
    np.testing.assert_array_equal(loaded.position_m[before], base.position_m[before])
    assert loaded.position_m[-1] > base.position_m[-1] + 1e-6
    pulled = constant_run(4.5, 400.0, config=QUIET, effects=Effects(load_change_n=-20.0, load_change_time_s=when))
    assert pulled.position_m[-1] < base.position_m[-1] - 1e-6


@pytest.mark.parametrize("effects", [Effects(ambient_drift_k_per_s=0.05, ambient_drift_start_s=200.0),
                                     Effects(creep_amplitude_m=20e-6, creep_time_constant_s=50.0, creep_start_s=200.0)])
def test_ambient_drift_and_creep_act_from_their_start_time(effects):
    base = constant_run(4.5, 400.0, config=QUIET)
    changed = constant_run(4.5, 400.0, config=QUIET, effects=effects)
    before = base.t_s <= 200.0
    np.testing.assert_array_equal(changed.position_m[before], base.position_m[before])
    assert abs(changed.position_m[-1] - base.position_m[-1]) > 1e-6


def test_sensor_noise_and_quantisation():
    config = StageConfig(sensor_noise_m=0.3e-6, sensor_resolution_m=0.1e-6)
    result = constant_run(0.0, 1000.0, dt=0.1, config=config)
    error = result.measured_position_m - result.position_m
    assert np.std(error) == pytest.approx(0.3e-6, rel=0.1)
    steps = result.measured_position_m / 0.1e-6
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-6)


@settings(max_examples=30, deadline=None)
@given(
    currents=st.lists(st.floats(-8.0, 8.0), min_size=1, max_size=40),
    dt=st.floats(1e-3, 0.5),
    hold=st.floats(0.0, 200.0),
)
@example(currents=[0.0], dt=0.5, hold=2.2250738585e-313)  # a denormal step once overflowed C/dt to NaN
def test_state_stays_physical_for_any_current_sequence(currents, dt, hold):
    sim = StageSimulator(QUIET)
    ambient = QUIET.ambient_temperature_k
    for current in currents:
        sim.step(current, dt)
        state = sim.step(current, hold) if hold > 0.0 else sim.state
        assert all(0.0 <= xi <= 1.0 for xi in state.martensite_fractions)
        assert all(ambient - 1e-9 <= temp < ambient + 300.0 for temp in state.wire_temperatures_k)
        assert all(stress >= 0.0 for stress in state.wire_stresses_pa)
        assert abs(state.position_m) < 2e-3


def test_same_seed_same_run_other_seed_other_noise():
    current = np.linspace(0.0, 4.0, 500)
    first, again = simulate(current, 0.2, seed=7), simulate(current, 0.2, seed=7)
    other = simulate(current, 0.2, seed=8)
    assert np.array_equal(first.measured_position_m, again.measured_position_m)
    assert not np.array_equal(first.measured_position_m, other.measured_position_m)
    np.testing.assert_array_equal(first.position_m, other.position_m)


def test_step_and_simulate_give_the_same_trajectory():
    dt = 0.2
    effects = Effects(sensor_delay_s=0.6, creep_amplitude_m=5e-6, ambient_drift_k_per_s=0.01,
                      load_change_n=5.0, load_change_time_s=50.0)
    current = 5.5 * np.sin(2 * np.pi * np.arange(0.0, 300.0, dt) / PERIOD)
    batch = simulate(current, dt, effects=effects, seed=3)
    sim = StageSimulator(effects=effects, seed=3)
    states = [sim.step(i, dt) for i in current]
    for field, column in (("time_s", batch.t_s), ("position_m", batch.position_m),
                          ("measured_position_m", batch.measured_position_m),
                          ("velocity_m_s", batch.velocity_m_s), ("current_a", batch.current_a)):
        np.testing.assert_array_equal([getattr(s, field) for s in states], column, err_msg=field)
    np.testing.assert_array_equal([s.wire_temperatures_k for s in states], batch.wire_temperatures_k)
    np.testing.assert_array_equal([s.martensite_fractions for s in states], batch.martensite_fractions)
    sim.reset()
    assert sim.step(current[0], dt) == states[0]


def test_current_is_clamped_to_max_current():
    config = dataclasses.replace(QUIET, max_current_a=4.0)
    over = constant_run(9.0, 50.0, config=config)
    at_limit = constant_run(4.0, 50.0, config=config)
    assert np.all(over.current_a == 4.0)
    np.testing.assert_array_equal(over.position_m, at_limit.position_m)
    assert StageSimulator(config).step(-7.0, 0.1).current_a == -4.0


def test_time_step_does_not_change_the_physics():
    coarse_dt, fine_dt = 0.5, 0.01
    current = paper_identification_signal(np.arange(0.0, 500.0, coarse_dt))
    repeat = int(round(coarse_dt / fine_dt))
    coarse = simulate(current, coarse_dt, config=QUIET)
    fine = simulate(np.repeat(current, repeat), fine_dt, config=QUIET)
    np.testing.assert_allclose(fine.position_m[repeat - 1 :: repeat], coarse.position_m, atol=1e-6)
    np.testing.assert_allclose(fine.t_s[repeat - 1 :: repeat], coarse.t_s, rtol=1e-9)


def test_velocity_is_the_rate_of_position():
    result = simulate(paper_identification_signal(np.arange(0.0, 300.0, 0.1)), 0.1, config=QUIET)
    np.testing.assert_allclose(np.diff(result.position_m) / 0.1, result.velocity_m_s[1:], atol=1e-12)
    assert np.abs(result.velocity_m_s).max() > 10e-6


def test_runs_much_faster_than_real_time():
    dt = 0.01
    current = paper_identification_signal(np.arange(0.0, 300.0, dt))
    simulate(current[:10], dt)
    start = time.perf_counter()
    simulate(current, dt)
    assert time.perf_counter() - start < 30.0, "300 s of simulated time at 100 Hz must take well under real time"


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_current_is_refused(bad):
    sim = StageSimulator()
    before = sim.state
    with pytest.raises(InputError):
        sim.step(bad, 0.1)
    assert sim.state == before
    with pytest.raises(InputError):
        simulate([0.0, bad], 0.1)


@pytest.mark.parametrize("dt", [0.0, -0.1, float("nan"), float("inf"), "x"])
def test_bad_time_step_is_refused(dt):
    with pytest.raises(InputError):
        StageSimulator().step(1.0, dt)
    with pytest.raises(InputError):
        simulate([1.0], dt)


def test_bad_current_arrays_are_refused():
    for bad in ([], [[1.0, 2.0]], ["a"]):
        with pytest.raises(InputError):
            simulate(bad, 0.1)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"wire_diameter_m": -1e-3},
        {"convection_w_m2_k": float("nan")},
        {"max_current_a": 0.0},
        {"austenite_start_k": 400.0},
        {"detwin_start_stress_pa": 200e6},
        {"lever_ratio": "2"},
        {"wire_nodes": 2.5},
        {"wire_nodes": 0},
    ],
)
def test_out_of_range_config_is_refused(kwargs):
    with pytest.raises(InputError):
        StageConfig(**kwargs)


@pytest.mark.parametrize("kwargs", [{"sensor_delay_s": -1.0}, {"creep_time_constant_s": 0.0},
                                    {"ambient_drift_k_per_s": float("inf")}])
def test_out_of_range_effects_are_refused(kwargs):
    with pytest.raises(InputError):
        Effects(**kwargs)


def test_config_and_effects_from_mappings():
    config = StageConfig.from_mapping({"max_current_a": 3.0, "sensor_noise_m": 0.0, "wire_nodes": 4.0})
    assert config.max_current_a == 3.0 and config.as_dict()["sensor_noise_m"] == 0.0
    assert StageConfig.from_mapping(config.as_dict()) == config
    assert Effects.from_mapping(Effects(sensor_delay_s=0.5).as_dict()).sensor_delay_s == 0.5
    with pytest.raises(InputError, match="max_curent_a"):
        StageConfig.from_mapping({"max_curent_a": 3.0})
    with pytest.raises(InputError):
        Effects.from_mapping({"sensor_delay_s": "soon"})


def test_a_simulation_run_in_parts_with_progress_is_the_same_run(monkeypatch):
    import sma_stage.plant.simulator as simulator

    currents = 4.0 * np.sin(np.linspace(0.0, 12.0, 50))
    whole = simulator.simulate(currents, 0.2, seed=3)
    monkeypatch.setattr(simulator, "PROGRESS_SAMPLES", 7)
    seen = []
    parts = simulator.simulate(currents, 0.2, seed=3, progress=lambda done, total: seen.append((done, total)))
    assert seen == [(min(k, 50), 50) for k in range(7, 57, 7)]
    for name in ("t_s", "position_m", "measured_position_m", "wire_temperatures_k", "martensite_fractions"):
        np.testing.assert_array_equal(getattr(parts, name), getattr(whole, name))
