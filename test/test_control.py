"""The control core: the lag lead, the PI loop with anti-windup, and its input checks (no ROS)."""

import copy
import math
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from test_two_wire import example_model as example_two_wire

from sma_stage.control import Compensator
from sma_stage.control import compensator as compensator_module
from sma_stage.control.compensator import RELAY_HOLD_S, imc_gains, slew_time_s
from sma_stage.control.drives import dead_band_a, drive_for, reach_span_m
from sma_stage.control.thermal import ThermalState
from sma_stage.errors import InputError
from sma_stage.model import Effect, GPIForwardStream, GPIInverseStream, IdentifiedModel, load_model_file
from sma_stage.model.effects import EffectState, lag_step
from sma_stage.model.kinds import load_any_model_file
from sma_stage.model.two_wire import TwoWireModel
from sma_stage.nodes.launch import DEFAULT_MODEL_FILE
from sma_stage.plant import StageSimulator

SHIPPED = load_model_file(DEFAULT_MODEL_FILE)
MODEL = IdentifiedModel(SHIPPED.parameters, SHIPPED.operators)  # its GPI, without the shipped lag
LIMIT_A = 5.0
UNLIMITED = 1e12  # a lead limit no step reaches: the exact lead
EXACT_LEAD = {"feedforward_lead_limit": UNLIMITED, "feedforward_step_lead_limit": UNLIMITED}  # moving or not


def inverse_stream(method: str = "exact", limit_a: float = LIMIT_A) -> GPIInverseStream:
    return GPIInverseStream(MODEL.parameters, MODEL.operators, method, input_range=(-limit_a, limit_a))


def with_effects(*effects: Effect) -> IdentifiedModel:
    return IdentifiedModel(MODEL.parameters, MODEL.operators, effects)


def lagged(tau_s: float, joule_reference_a: float = 0.0) -> IdentifiedModel:
    reference = {"joule_reference_a": joule_reference_a} if joule_reference_a else {}
    return with_effects(Effect("thermal_lag", {"tau_s": tau_s, **reference}))


def slow_setpoints(steps: int, dt_s: float) -> np.ndarray:
    """A smooth setpoint [m] within the default model's reach."""
    t = dt_s * np.arange(steps)
    return 5e-5 + 1.0e-4 * np.sin(2.0 * np.pi * t / 200.0) + 3.5e-5 * np.sin(2.0 * np.pi * t / 70.0)


def lag_input(current_a: float, joule_reference_a: float) -> float:
    return current_a * abs(current_a) / joule_reference_a if joule_reference_a else current_a


@pytest.mark.parametrize("joule_reference_a", [0.0, LIMIT_A, 3.0])
def test_the_lead_undoes_a_first_order_lag_exactly(joule_reference_a):
    tau_s, dt_s = 8.0, 0.2
    setpoints = slow_setpoints(3000, dt_s)
    core = Compensator(lagged(tau_s, joule_reference_a), LIMIT_A, max_rate_a_per_s=0.0,
                       **EXACT_LEAD)
    reach = core.drive.inverse.input_range  # the lag's drive: the Joule heating's range in the heating reading
    wanted = GPIInverseStream(MODEL.parameters, MODEL.operators, input_range=reach).run(setpoints)[0]
    kept = math.exp(-dt_s / tau_s)
    state, unclipped = 0.0, 0
    for setpoint, target in zip(setpoints, wanted, strict=True):
        current = core.command(setpoint, None, dt_s)
        drive = lag_input(current, joule_reference_a)
        state = drive + (state - drive) * kept  # the current held for dt_s through tau v' = u - v
        if core.saturated == 0:
            unclipped += 1
            assert state == pytest.approx(target, abs=1e-12)
    # At each reversal the inverse jumps across the loop's width, which the lead cannot follow in one step
    assert unclipped >= 0.95 * len(setpoints)


def test_the_lead_tends_to_v_plus_tau_dv_dt_for_short_steps():
    tau_s, dt_s = 8.0, 0.001
    setpoints = slow_setpoints(20000, dt_s)[10000:]
    wanted = inverse_stream().run(setpoints)[0]
    core = Compensator(lagged(tau_s), LIMIT_A, max_rate_a_per_s=0.0, **EXACT_LEAD)
    currents = np.array([core.command(setpoint, None, dt_s) for setpoint in setpoints])
    expected = wanted[1:] + tau_s * np.diff(wanted) / dt_s
    settled = slice(6000, None)  # the lag starts idle, at 0 A: 6 s to catch up at the current limit
    assert np.max(np.abs(currents[1:][settled] - expected[settled])) < 1e-3 * LIMIT_A


@pytest.mark.parametrize("method", ["exact", "analytic"])
def test_without_lead_or_feedback_the_core_is_the_streaming_inverse(method):
    setpoints = slow_setpoints(500, 1.0)
    core = Compensator(MODEL, LIMIT_A, method, kp=3.0, ki=5.0)
    reference = inverse_stream(method).run(setpoints)[0]
    commands = [core.command(setpoint, None, 1.0) for setpoint in setpoints]
    assert np.array_equal(commands, reference)


def test_anti_windup_stops_the_integral_while_the_command_saturates():
    core = Compensator(MODEL, 2.0, ki=20.0)
    commands = [core.command(1e-4, 0.0, 0.01) for _ in range(400)]
    assert commands[-1] == 2.0 and core.saturated == 1
    wound = core.integral_m
    for _ in range(100):
        core.command(1e-4, 0.0, 0.01)
    assert core.integral_m == wound
    assert core.command(1e-4, 3e-4, 0.01) < 2.0, "the command leaves saturation at once"


def test_anti_windup_also_holds_when_the_lead_saturates():
    core = Compensator(lagged(50.0), LIMIT_A, ki=1.0, max_rate_a_per_s=0.0)
    core.command(0.0, 0.0, 0.1)
    assert core.command(3e-4, 0.0, 0.1) == LIMIT_A and core.saturated == 1
    wound = core.integral_m
    core.command(3e-4, 0.0, 0.1)
    assert core.integral_m == wound


def test_pi_removes_a_constant_offset_of_the_plant():
    offset_m, dt_s = 3e-5, 0.1
    plant = GPIForwardStream(MODEL.parameters, MODEL.operators)
    core = Compensator(MODEL, LIMIT_A, kp=0.5, ki=2.0, max_rate_a_per_s=0.0)
    position = plant.step(0.0) + offset_m
    for _ in range(600):
        position = plant.step(core.command(1e-4, position, dt_s)) + offset_m
    assert position == pytest.approx(1e-4, abs=1e-9)
    held = [core.command(1e-4, plant.step(core.command_a) + offset_m, dt_s) for _ in range(20)]
    assert np.ptp(held) < 1e-9, "the command settles"


@pytest.mark.parametrize("step_m", [3e-5, -3e-5, 8e-5])
def test_the_integral_waits_while_the_model_expects_the_stage_still_on_its_way(step_m):
    """A step on a plant that is the model itself (a two-wire model, heating lags of 3.5-4 s): while the stage is
    short of half the step, the whole error is one the model expects to close, and the integral keeps what the
    step's first command gave it (integrating that error, as before, wound it up by ki e dt every step); the
    stage then settles on the level."""
    model, dt_s = example_two_wire(), 0.2
    plant = drive_for(model, LIMIT_A, "exact")
    core = Compensator(model, LIMIT_A, **imc_gains(model, dt_s))
    start_m = plant.predicted_m
    level_m = start_m + step_m
    core.command(start_m, start_m, 0.0)
    integrals, positions = [], []
    for _ in range(int(120.0 / dt_s)):
        plant.advance(core.command_a, dt_s)
        positions.append(plant.predicted_m)
        core.command(level_m, positions[-1], dt_s)
        integrals.append(core.integral_m)
    short = [integral for integral, position in zip(integrals, positions, strict=True)
             if (position - start_m) / step_m < 0.5]
    assert len(short) > 10 and np.ptp(short) == 0.0
    assert positions[-1] == pytest.approx(level_m, abs=1e-7)


@pytest.mark.parametrize("period_s", [0.1, 0.4])
def test_a_held_setpoint_settles_without_a_limit_cycle(period_s):
    """The shipped model in the loop on the simulator, each level held from rest for 300 s: the last 60 s
    within 1 um peak to peak and the current steady. Before a held setpoint's reversals were kept out of the
    inverse, the same runs cycled 1.3-5.3 um peak to peak, the current swinging at the rate limit."""
    model = load_any_model_file(DEFAULT_MODEL_FILE)
    for seed, level_m in ((0, 1e-4), (1, 2e-4), (2, 4e-4)):
        stage = StageSimulator(seed=seed)
        core = Compensator(model, LIMIT_A, **imc_gains(model, period_s))
        measured, dt_s, positions, currents = stage.state.measured_position_m, 0.0, [], []
        for _ in range(int(300.0 / period_s)):
            currents.append(core.command(level_m, measured, dt_s))
            state = stage.step(currents[-1], period_s)
            measured, dt_s = state.measured_position_m, period_s
            positions.append(state.position_m)
        last = slice(-int(60.0 / period_s), None)
        assert np.ptp(positions[last]) < 1e-6, f"level {level_m}: {1e6 * np.ptp(positions[last]):.2f} um p-p"
        assert abs(np.mean(positions[last]) - level_m) < 2e-7
        assert np.percentile(np.abs(np.diff(currents[last])), 99) < 0.005 * LIMIT_A


def test_a_model_without_a_lag_holds_a_level_without_a_limit_cycle():
    """The shipped GPI without its lag in the loop (kp 0: pure integral action) on the simulator, each level held
    600 s: the last 200 s within 3 um peak to peak (0.2-1.9 um when written). With a held reversal's faster integral
    (REVERSAL_SPEED) applied without proportional action, the same holds cycled 92-331 um peak to peak."""
    gains = imc_gains(MODEL, 0.1)
    assert gains["kp"] == 0.0
    for level_m in (1e-4, 2e-4, 4e-4):
        stage = StageSimulator(seed=0)
        core = Compensator(MODEL, LIMIT_A, **gains)
        measured, dt_s, positions = stage.state.measured_position_m, 0.0, []
        for _ in range(6000):
            state = stage.step(core.command(level_m, measured, dt_s), 0.1)
            measured, dt_s = state.measured_position_m, 0.1
            positions.append(state.position_m)
        assert np.ptp(positions[-2000:]) < 3e-6, f"level {level_m}: {1e6 * np.ptp(positions[-2000:]):.1f} um p-p"


@pytest.mark.parametrize("period_s", [0.1, 0.4])
def test_a_setpoint_that_moves_after_a_hold_starts_from_where_the_stage_is(period_s):
    """The shipped model in the loop on the simulator: 100 um held 300 s (the linear path takes the loop's
    reversals), then a ramp down at 1 um/s for 100 s, tracked within 8 um. Without the model run on the whole
    command during the hold, the inverse resumed from a state that had not seen the linear path's current and the
    ramp began 14-15 um off (4.7 um with it)."""
    model = load_any_model_file(DEFAULT_MODEL_FILE)
    stage = StageSimulator(seed=0)
    core = Compensator(model, LIMIT_A, **imc_gains(model, period_s))
    measured, dt_s, held_steps, errors = stage.state.measured_position_m, 0.0, int(300.0 / period_s), []
    for k in range(held_steps + int(100.0 / period_s)):
        setpoint = 1e-4 - 1e-6 * period_s * max(k - held_steps, 0)
        state = stage.step(core.command(setpoint, measured, dt_s), period_s)
        measured, dt_s = state.measured_position_m, period_s
        if k >= held_steps:
            errors.append(state.position_m - (setpoint - 1e-6 * period_s))
    assert np.max(np.abs(errors)) < 8e-6, f"{1e6 * np.max(np.abs(errors)):.2f} um"


def held_levels_settled(stage: TwoWireModel) -> np.ndarray:
    """The example two-wire model in the loop on `stage`, ten random levels held 60 s each (0.2 s steps): each
    hold's mean error over its last 20 s, as a fraction of the model's reach."""
    model, dt_s = example_two_wire(), 0.2
    plant = drive_for(stage, LIMIT_A, "exact")
    core = Compensator(model, LIMIT_A, **imc_gains(model, dt_s))
    low, high = core.drive.target_bounds
    span = reach_span_m(core.drive)
    levels = (low + high) / 2 + span * np.random.default_rng(3).uniform(-0.35, 0.35, 10)
    core.command(levels[0], plant.predicted_m, 0.0)
    settled = []
    for level in levels:
        errors = []
        for _ in range(int(60.0 / dt_s)):
            plant.advance(core.command_a, dt_s)
            errors.append(plant.predicted_m - level)
            core.command(level, plant.predicted_m, dt_s)
        settled.append(abs(np.mean(errors[-int(20.0 / dt_s):])) / span)
    return np.array(settled)


@pytest.mark.parametrize("wider", [{"hysteresis_a": 0.9, "hysteresis_b": 1.2}, {"centre_a": 1.9, "centre_b": 2.0}])
def test_a_held_levels_reversal_across_a_wider_loop_than_the_models_settles(monkeypatch, wider):
    """A stage whose hysteresis is wider (or whose wires start moving later) than the model's: a held level's reversal
    goes through the linear path, whose mean slope asks too little current of a loop the stage crosses without
    moving; with the integral REVERSAL_SPEED (3) times faster there, every hold settles within 0.03 % of the reach
    (measured when written: 0.009 and 0.018 % at worst); at the plain ki one hold was still 0.12 and 0.08 % off."""
    stage = example_two_wire(**wider)
    assert np.max(held_levels_settled(stage)) < 3e-4
    monkeypatch.setattr(compensator_module, "REVERSAL_SPEED", 1.0)
    assert np.max(held_levels_settled(stage)) > 6e-4


def sine_tracked_um(preview: bool, period_s: float = 0.2) -> float:
    """The shipped model in the loop on the simulator through a 100 s sine of 200 um amplitude (its first 100 s not
    scored), with or without the setpoint preview_s ahead: the RMS error [um]."""
    model = load_any_model_file(DEFAULT_MODEL_FILE)
    stage = StageSimulator(seed=0)
    core = Compensator(model, LIMIT_A, **imc_gains(model, period_s))
    ahead = round(core.preview_s() / period_s) if preview else 0
    t = period_s * np.arange(int(300.0 / period_s) + ahead + 1)
    wanted = 2.5e-4 + 2e-4 * np.sin(2.0 * np.pi * np.maximum(t - 50.0, 0.0) / 100.0)
    measured, dt_s, errors = stage.state.measured_position_m, 0.0, []
    for k in range(int(300.0 / period_s)):
        state = stage.step(core.command(wanted[k], measured, dt_s, ahead_m=wanted[k + ahead] if preview else None),
                           period_s)
        measured, dt_s = state.measured_position_m, period_s
        if t[k] >= 100.0:
            errors.append(state.position_m - wanted[k + 1])
    return 1e6 * float(np.sqrt(np.mean(np.square(errors))))


def test_a_preview_of_the_setpoint_tracks_a_sine_closer():
    """The loop's lead leaves the stage a lag of tau / lead_limit (3.3 s for the shipped model); the setpoint that far
    ahead undoes it: 7.4 um RMS without, 4.2 um with (measured when written)."""
    core = Compensator(load_any_model_file(DEFAULT_MODEL_FILE), LIMIT_A)
    assert core.preview_s() == pytest.approx(core.tau_s / core.lead_limit)
    assert core.preview_s(feedback=False) == pytest.approx(core.tau_s / core.feedforward_lead_limit)
    without = sine_tracked_um(preview=False)
    with_preview = sine_tracked_um(preview=True)
    assert with_preview < 0.7 * without, (with_preview, without)


def test_a_previewed_step_is_taken_when_it_comes_not_before():
    """A jump of the setpoint ahead faster than the model's lag lets the stage follow is a step: the commands are
    those without a preview (a step taken early would only leave the level early)."""
    model = load_any_model_file(DEFAULT_MODEL_FILE)
    levels = np.repeat([1e-4, 3e-4, 2e-4, 4e-4], 150)
    ahead = 16
    runs = []
    for preview in (False, True):
        core = Compensator(model, LIMIT_A, **imc_gains(model, 0.2))
        stage = StageSimulator(seed=0)
        measured, currents = stage.state.measured_position_m, []
        for k in range(levels.size - ahead):
            currents.append(core.command(levels[k], measured, 0.2 if k else 0.0,
                                         ahead_m=levels[k + ahead] if preview else None))
            measured = stage.step(currents[-1], 0.2).measured_position_m
        runs.append(currents)
    assert runs[0] == runs[1]


def test_with_a_preview_the_loops_error_is_against_the_setpoint_now():
    """A stage exactly at the setpoint now while the setpoint ahead moves on: nothing to integrate."""
    core = Compensator(lagged(10.0), LIMIT_A, kp=0.5, ki=0.2)
    for k in range(50):
        now = 1e-4 + 1e-7 * k
        core.command(now, now, 0.1, ahead_m=now + 3e-7)
    assert core.integral_m == 0.0


@pytest.mark.parametrize(("call", "name"), [
    (lambda core: core.command(float("nan")), "setpoint_m"),
    (lambda core: core.command(1e-4, 1e-4, 0.1, ahead_m=float("nan")), "ahead_m"),
    (lambda core: core.command(1e-4, float("inf"), 0.1), "measured_m"),
    (lambda core: core.command(1e-4, None, -0.1), "dt_s"),
    (lambda core: setattr(core, "ki", float("nan")), "ki"),
    (lambda core: Compensator(MODEL, LIMIT_A, kp=-2.0), "kp"),
    (lambda core: Compensator(MODEL, -1.0), "max_current_a"),
    (lambda core: Compensator(MODEL, LIMIT_A, lead_limit=0.5), "lead_limit"),
    (lambda core: Compensator(MODEL, LIMIT_A, feedforward_lead_limit=float("nan")), "feedforward_lead_limit"),
    (lambda core: Compensator(MODEL, LIMIT_A, feedforward_step_lead_limit=0.5), "feedforward_step_lead_limit"),
    (lambda core: setattr(core, "feedforward_step_lead_limit", float("inf")), "feedforward_step_lead_limit"),
    (lambda core: setattr(core, "deadband_m", -1e-6), "deadband_m"),
    (lambda core: Compensator("not a model"), "a GPI, a two-wire or a Bouc-Wen model"),
    (lambda core: Compensator(MODEL, LIMIT_A, ""), "inverse method"),  # fuzzing: was an AttributeError
    (lambda core: core.set_model(IdentifiedModel(MODEL.parameters.replace(output_unit="mm"), MODEL.operators)),
     "output unit"),
    (lambda core: Effect("thermal_lag", {"tau_s": -2.0}), "tau_s"),
])
def test_bad_input_is_refused_with_one_line(call, name):
    core = Compensator(MODEL, LIMIT_A)
    with pytest.raises(InputError) as excinfo:
        call(core)
    assert name in str(excinfo.value) and "\n" not in str(excinfo.value)


def test_a_refused_model_leaves_the_model_in_force():
    core = Compensator(MODEL, LIMIT_A)
    with pytest.raises(InputError):
        core.set_model(IdentifiedModel(MODEL.parameters.replace(a10=-1.0), MODEL.operators))
    assert core.model is MODEL


def test_the_drift_is_taken_off_the_target_as_the_model_runs_on():
    drift = Effect("drift", {"drift_m_per_s": 2e-7})
    plain, drifting = (Compensator(MODEL, LIMIT_A, max_rate_a_per_s=0.0),
                       Compensator(with_effects(drift), LIMIT_A, max_rate_a_per_s=0.0))
    reference = inverse_stream()
    for step in range(1, 301):
        command = drifting.command(1e-4, None, 1.0)
        plain.command(1e-4 - 2e-7 * step, None, 1.0)
        assert command == plain.command_a == reference.step(1e-4 - 2e-7 * step)


def test_the_model_runs_on_from_the_state_it_carries():
    """Given the model with the state a record left, the compensator starts where the stage is: its inverse
    holds the record's operator states and its lead the lag's state (a model without one starts at rest)."""
    t = np.arange(0.0, 300.0, 1.0)
    model = lagged(6.0)
    _, state = model.run(t, 4.0 * np.sin(2.0 * np.pi * t / 250.0))
    carried = Compensator(replace(model, state=state), LIMIT_A)
    assert carried.drive.thermal.seen == state.effects[0].values[0] != 0.0
    assert np.array_equal(carried.drive.inverse.states, np.array(state.operators)) and np.any(carried.drive.inverse.states)
    fresh = Compensator(model, LIMIT_A)
    assert fresh.drive.thermal.seen == 0.0 and not np.any(fresh.drive.inverse.states)


@pytest.mark.parametrize("measured_m", [None, 0.0], ids=["feedforward", "loop"])
def test_the_lead_limit_bounds_the_lead_and_the_lag_then_follows_with_tau_over_the_limit(measured_m):
    """lead_limit bounds the lead with a measurement (the loop; kp = ki = 0 here), feedforward_step_lead_limit
    without one after a step."""
    tau_s, dt_s, limit, other = 10.0, 0.1, 3.0, 7.0
    limits = {"lead_limit": other, "feedforward_lead_limit": other, "feedforward_step_lead_limit": limit} \
        if measured_m is None else {"lead_limit": limit, "feedforward_lead_limit": other,
                                    "feedforward_step_lead_limit": other}
    core = Compensator(lagged(tau_s), LIMIT_A, max_rate_a_per_s=0.0, deadband_m=0.0, **limits)
    core.command(0.0, measured_m, 0.0)
    target = GPIInverseStream(MODEL.parameters, MODEL.operators, input_range=(-LIMIT_A, LIMIT_A)).step(1e-4)
    current = core.command(1e-4, measured_m, dt_s)
    assert current == pytest.approx(limit * target, rel=1e-12), "s + g (v* - s) from s = 0, g at the limit"
    states = []
    for _ in range(400):
        core.command(1e-4, measured_m, dt_s)
        states.append(core.drive.thermal.seen)
    gap = target - np.array(states)
    rate = -np.log(gap[200] / gap[100]) / (100 * dt_s)  # the gap decays as exp(-t limit / tau)
    assert rate == pytest.approx(limit / tau_s, rel=0.02)


def test_the_lead_works_over_the_hold_it_is_given_not_the_time_since_the_last_call():
    """A setpoint that arrives between two control ticks is held until the next tick: the lead brings the
    lag's state to v* over hold_s, whatever the time since the previous call."""
    tau_s, hold_s = 10.0, 5.0
    target = GPIInverseStream(MODEL.parameters, MODEL.operators, input_range=(-LIMIT_A, LIMIT_A)).step(1e-4)
    for since_s in (0.0, 0.01, 0.7):
        core = Compensator(lagged(tau_s), LIMIT_A, max_rate_a_per_s=0.0, **EXACT_LEAD)
        current = core.command(1e-4, None, since_s, hold_s=hold_s)
        assert current == pytest.approx(target / (1.0 - math.exp(-hold_s / tau_s)), rel=1e-12), since_s
        assert current < LIMIT_A
    by_default, given = (Compensator(lagged(tau_s), LIMIT_A, max_rate_a_per_s=0.0, **EXACT_LEAD)
                         for _ in range(2))
    assert by_default.command(1e-4, None, 3.0) == given.command(1e-4, None, 3.0, hold_s=3.0), "default: dt_s"


def test_feedforward_does_not_overshoot_a_step_and_the_lag_then_follows_with_its_own_tau():
    """After a step of the setpoint (and while it holds) the feedforward lead is at feedforward_step_lead_limit,
    1 by default: the current goes to v* and stays there, and the lag's state approaches it with tau."""
    tau_s, dt_s = 10.0, 0.1
    core = Compensator(lagged(tau_s), LIMIT_A, max_rate_a_per_s=0.0)
    target = inverse_stream().step(1e-4)
    core.command(0.0, None, 0.0)
    currents, states = [], []
    for _ in range(400):
        currents.append(core.command(1e-4, None, dt_s))
        states.append(core.drive.thermal.seen)
    assert np.max(currents) == pytest.approx(target, rel=1e-12)
    assert np.min(currents) == pytest.approx(target, rel=1e-12)
    gap = target - np.array(states)
    assert -np.log(gap[200] / gap[100]) / (100 * dt_s) == pytest.approx(1.0 / tau_s, rel=0.02)


@pytest.mark.parametrize("every", [1, 5], ids=["each call", "every fifth call"])
def test_feedforward_leads_a_moving_setpoint_at_its_own_limit_also_when_published_slower_than_the_loop(every):
    """A setpoint whose changes agree in sign and rate moves: the lead is at feedforward_lead_limit, as if it
    were the only limit; published at a fifth of the loop's rate it still moves between its changes."""
    tau_s, dt_s, steps = 10.0, 0.1, 600
    ramp = 2e-7 * every * (np.arange(steps) // every)
    gated = Compensator(lagged(tau_s), LIMIT_A, max_rate_a_per_s=0.0)
    always = Compensator(lagged(tau_s), LIMIT_A, max_rate_a_per_s=0.0, feedforward_step_lead_limit=10.0)
    gated_a = np.array([gated.command(setpoint, None, dt_s) for setpoint in ramp])
    always_a = np.array([always.command(setpoint, None, dt_s) for setpoint in ramp])
    settled = slice(200, None)  # what the first changes (no rates to compare yet) left behind has decayed
    assert np.allclose(gated_a[settled], always_a[settled], rtol=1e-6, atol=0.0)
    assert np.max(gated_a - inverse_stream().run(ramp)[0]) > 0.05, "a lead, not the inverse alone"


def test_a_moving_setpoint_that_stops_is_a_step_again():
    """Held for more than half of MOTION_WINDOW_S, the setpoint no longer moves: the lead drops to
    feedforward_step_lead_limit, and the current to the inverse's output."""
    tau_s, dt_s = 10.0, 0.1
    core = Compensator(lagged(tau_s), LIMIT_A, max_rate_a_per_s=0.0)
    for k in range(50):
        core.command(2e-6 * k, None, dt_s)
    led = core.command(2e-6 * 50, None, dt_s)
    held = [core.command(2e-6 * 50, None, dt_s) for _ in range(10)]
    target = inverse_stream().run(2e-6 * np.arange(51))[0][-1]
    assert led > target + 0.01
    assert held[0] > target, "one control period after the last change it still moves"
    assert held[-1] == pytest.approx(target, rel=1e-12)


def test_a_moving_setpoint_is_told_from_a_step_whenever_its_messages_arrive():
    """A ramp published every 0.1 s whose messages reach the core up to one period late (two at one
    instant, then a gap of two periods, as through a busy executor) moves all along: the same commands as
    with the lead at feedforward_lead_limit always."""
    tau_s, period_s, rate_m_s = 10.0, 0.1, 2e-6
    arrival_ticks = np.arange(1500) + np.random.default_rng(3).integers(0, 2, size=1500)
    published_s = period_s * np.arange(1500)
    gaps = period_s * np.diff(arrival_ticks, prepend=0)
    gated = Compensator(lagged(tau_s), LIMIT_A, max_rate_a_per_s=0.0)
    always = Compensator(lagged(tau_s), LIMIT_A, max_rate_a_per_s=0.0, feedforward_step_lead_limit=10.0)
    commands = np.array([[core.command(rate_m_s * t, None, gap, hold_s=period_s) for core in (gated, always)]
                         for t, gap in zip(published_s, gaps, strict=True)])
    settled = published_s > 30.0
    assert np.allclose(commands[settled, 0], commands[settled, 1], rtol=1e-6, atol=0.0)


@pytest.mark.parametrize("method", ["exact", "analytic"])
def test_finite_but_absurd_positions_give_a_command_within_the_limit(method):
    """A setpoint or measurement of 1e308 (any publisher can send one) is beyond reach, not an overflow: the
    command goes to the limit on the side of the target (the analytic inverse once gave NaN there, and the
    clip turned it into full reverse current)."""
    assert Compensator(MODEL, LIMIT_A, method).command(8.2e307) == LIMIT_A
    assert Compensator(MODEL, LIMIT_A, method).command(-1.7e308) == -LIMIT_A
    looped = Compensator(MODEL, LIMIT_A, method, kp=2.0, ki=1.0, max_rate_a_per_s=0.0)
    assert looped.command(1e308, 0.0, 0.1) == LIMIT_A
    assert looped.command(1e-4, 1e308, 0.1) == -LIMIT_A, "measured far above: drive down"
    assert looped.command(1e-4, -1e308, 0.1) == LIMIT_A
    assert math.isfinite(looped.integral_m)


def test_the_loops_target_reverses_only_beyond_the_deadband():
    core = Compensator(MODEL, LIMIT_A, kp=1.0, deadband_m=1e-6, max_rate_a_per_s=0.0)
    first = core.command(1e-4, 1e-4, 0.1)
    wiggles = [core.command(1e-4, 1e-4 + noise, 0.1) for noise in (0.8e-6, -0.8e-6, 0.5e-6, -0.9e-6)]
    assert all(current == first for current in wiggles) and core.target_m == 1e-4, "noise does not reverse it"
    assert core.command(1e-4, 1e-4 - 5e-6, 0.1) > first, "a real error moves the target on"


def test_imc_gains_follow_the_identified_lag_and_the_control_period():
    gains = imc_gains(lagged(9.0), 0.1, lead_limit=3.0, slew_s=0.0)
    assert gains == pytest.approx({"kp": 3.0 / 2.2, "ki": 1.0 / 2.2}), "lambda 0.7 of the 3 s lag the lead leaves"
    assert imc_gains(MODEL, 0.5, slew_s=0.0) == {"kp": 0.0, "ki": 2.0}, "no lag: integral action over the dead time"


def test_imc_gains_close_the_loop_no_faster_than_the_rate_limit_moves_the_current():
    assert slew_time_s(5.0, 1.0) == 2.5 and slew_time_s(5.0, 0.0) == 0.0
    assert imc_gains(lagged(9.0), 0.1, lead_limit=3.0, slew_s=2.5) == pytest.approx({"kp": 3.0 / 2.6, "ki": 1.0 / 2.6})
    assert imc_gains(lagged(0.3), 0.2) == pytest.approx({"kp": 0.1 / 2.7, "ki": 1.0 / 2.7}), "the default: 2.5 s"
    assert imc_gains(lagged(30.0), 0.2) == imc_gains(lagged(30.0), 0.2, slew_s=0.0), "a slow lag sets it alone"
    with pytest.raises(InputError, match="slew_s"):
        imc_gains(MODEL, 0.2, slew_s=-1.0)
    with pytest.raises(InputError, match="control_period_s"):
        imc_gains(MODEL, 0.0)


def test_the_current_changes_by_at_most_the_rate_limit_per_step():
    core = Compensator(lagged(10.0), LIMIT_A, max_rate_a_per_s=1.0)
    first = core.command(0.0, None, 0.0)
    currents = [first] + [core.command(3e-4, None, 0.1) for _ in range(100)]
    assert np.max(np.abs(np.diff(currents))) <= 0.1 + 1e-12
    assert currents[-1] > currents[1] + 2.0, "it gets there, 0.1 A per 0.1 s step"


def wires_moving_beyond(centre: float) -> TwoWireModel:
    """A two-wire model whose wires move the stage only when heated beyond `centre` (heating units)."""
    return example_two_wire(centre_a=centre, centre_b=centre)


def test_the_dead_band_is_where_no_wire_moves_the_stage_in_the_model():
    assert dead_band_a(load_model_file(DEFAULT_MODEL_FILE), LIMIT_A) == (0.0, 0.0), "the simulator's GPI has none"
    low, high = dead_band_a(wires_moving_beyond(3.0), LIMIT_A)
    assert -1.5 <= low <= -1.0 and 1.0 <= high <= 1.5
    assert dead_band_a(wires_moving_beyond(1.6), LIMIT_A) == (0.0, 0.0)


def test_the_rate_limit_counts_the_current_beyond_the_dead_band_and_crosses_the_band_at_once():
    """From wire a to wire b at 1 A/s: every step moves the current beyond the band by at most 0.1 A, and one
    step hands over across the band (no time lost where nothing moves)."""
    model = wires_moving_beyond(3.0)
    low, high = dead_band_a(model, LIMIT_A)
    core = Compensator(model, LIMIT_A, max_rate_a_per_s=1.0)
    bottom, top = core.drive.target_bounds
    reach = (bottom + top) / 2 + np.array([-0.5, 0.5]) * reach_span_m(core.drive)
    currents = [core.command(reach[1], None, 0.0)] + [core.command(reach[1], None, 0.1) for _ in range(100)]
    assert currents[-1] > high + 1.0
    currents += [core.command(reach[0], None, 0.1) for _ in range(100)]
    assert currents[-1] < low - 1.0
    beyond = np.array([c - high if c > high else c - low if c < low else 0.0 for c in currents])
    assert np.max(np.abs(np.diff(beyond[1:]))) <= 0.1 + 1e-12
    assert np.max(np.abs(np.diff(currents[1:]))) >= high - low, "the band crossed in one step"


@pytest.mark.parametrize("feedback", [False, True])
def test_while_the_setpoint_moves_the_rate_limit_holds_within_the_band_but_at_the_relays_switch(feedback):
    """A triangle across the reach (40 s a way) at 1 A/s, commanded every 0.1 s: away from its turning points (where
    the setpoint stops moving) the current changes by at most 0.1 A a step on either wire's side, dead band and 0 A
    included; only a switch of the relay crosses the band in one step."""
    model = wires_moving_beyond(3.0)
    low, high = dead_band_a(model, LIMIT_A)
    t, currents = triangle_currents(model, feedback, 40.0)
    change, after = np.abs(np.diff(currents)), currents[1:]
    switch = np.sign(currents[:-1]) * np.sign(after) < 0
    turning = np.abs((t[1:] + 20.0) % 40.0 - 20.0) > 17.0
    steady = ~switch & ~turning & (t[1:] > 5.0)
    assert np.any(switch) and np.min(change[switch]) > 0.5, "a switch of the relay crosses the band at once"
    assert np.max(change[steady]) <= 0.1 + 1e-12
    assert np.any(steady & (np.abs(after) < high)), "the band was crossed at the rate limit, not skipped"


def triangle_currents(model: TwoWireModel, feedback: bool, period_s: float) -> tuple[np.ndarray, np.ndarray]:
    """A triangle over 80 % of the reach (period_s a way, two periods) at 1 A/s, commanded every 0.1 s, the stage the
    model itself: the times [s] and the currents [A] commanded."""
    core = Compensator(model, LIMIT_A, max_rate_a_per_s=1.0, **(imc_gains(model, 0.1) if feedback else {}))
    bottom, top = core.drive.target_bounds
    t = 0.1 * np.arange(round(4 * period_s / 0.1))
    setpoints = (bottom + top) / 2 + 0.4 * reach_span_m(core.drive) * (2.0 * np.abs((t / period_s) % 2.0 - 1.0) - 1.0)
    stage = copy.deepcopy(core.drive)
    currents = []
    for k, setpoint in enumerate(setpoints):
        currents.append(core.command(setpoint, stage.predicted_m if feedback else None, 0.1 if k else 0.0))
        stage.advance(currents[-1], 0.1)
    return t, np.array(currents)


def beyond_band_after_switches(model: TwoWireModel, feedback: bool, period_s: float) -> np.ndarray:
    """How far [A] beyond the dead band each switch of the relay puts the new wire's current on triangle_currents'
    triangle (negative: within the band)."""
    low, high = dead_band_a(model, LIMIT_A)
    _, currents = triangle_currents(model, feedback, period_s)
    after = currents[1:][np.sign(currents[:-1]) * np.sign(currents[1:]) < 0]
    return np.where(after > 0.0, after - high, low - after)


@pytest.mark.parametrize("model", [wires_moving_beyond(3.0), example_two_wire()], ids=["dead band", "none"])
def test_in_the_loop_a_moving_setpoints_hand_over_takes_the_new_wire_beyond_the_band_at_once(monkeypatch, model):
    """At a switch of the relay while the setpoint moves (4 % of the reach per RELAY_HOLD_S), the loop takes the new
    wire's current beyond the dead band (beyond 0 A without one) by more than the rate limit's step and at most by
    what the rate limit adds over the relay's hold; feedforward, and the loop on a setpoint slower than
    HANDOVER_SPEED_FRACTION of the reach per hold, by one step of the rate limit at most."""
    looped = beyond_band_after_switches(model, True, 40.0)
    assert looped.size >= 3 and 0.5 < np.max(looped) <= 1.0 * RELAY_HOLD_S + 1e-9
    assert np.max(beyond_band_after_switches(model, False, 40.0)) <= 0.1 + 1e-9
    monkeypatch.setattr(compensator_module, "HANDOVER_SPEED_FRACTION", 0.05)
    assert np.max(beyond_band_after_switches(model, True, 40.0)) <= 0.1 + 1e-9


@pytest.mark.parametrize("hold_s", [0.0, RELAY_HOLD_S])
def test_the_relay_switches_back_no_sooner_than_its_hold(monkeypatch, hold_s):
    """A target flipping between the ends of the reach every 0.1 s: the current's sign (the wire the relay feeds)
    changes at most once per RELAY_HOLD_S, and between switches the current asked of the other wire is held within
    the dead band. With no hold it switches at every step."""
    monkeypatch.setattr(compensator_module, "RELAY_HOLD_S", hold_s)
    model = wires_moving_beyond(3.0)
    low, high = dead_band_a(model, LIMIT_A)
    core = Compensator(model, LIMIT_A, max_rate_a_per_s=0.0)
    bottom, top = core.drive.target_bounds
    ends = (bottom + top) / 2 + np.array([0.4, -0.4]) * reach_span_m(core.drive)
    steps = round(6.0 * max(RELAY_HOLD_S, 1.0) / 0.1)
    currents = np.array([core.command(ends[k % 2], None, 0.1 if k else 0.0) for k in range(steps)])
    signs = np.sign(currents[currents != 0.0])
    switches = np.nonzero(np.diff(signs))[0]
    if hold_s == 0.0:
        assert switches.size >= steps - 10
        return
    assert 3 <= switches.size <= 6 and np.min(np.diff(switches)) >= round(RELAY_HOLD_S / 0.1)
    in_band = (currents >= low) & (currents <= high)
    assert np.sum(in_band) >= steps // 3, "the current asked of the other wire within a hold stays in the dead band"


def test_a_core_that_continues_another_moves_the_current_from_its_last_command_within_the_rate_limit():
    """A model swapped in while tracking (its states from where the stage is) continues the loop of the old core:
    the current moves from the last command by at most the rate limit, and the integral carries on."""
    old = Compensator(lagged(10.0), LIMIT_A, kp=0.5, ki=0.2, max_rate_a_per_s=1.0)
    for _ in range(300):
        old.command(2e-4, 1.9e-4, 0.1)
    other = lagged(4.0)
    jumping = Compensator(other, LIMIT_A, kp=0.5, ki=0.2, max_rate_a_per_s=1.0)
    assert abs(jumping.command(2e-4, 1.9e-4, 0.1) - old.command_a) > 0.5, "without it, the first command jumps"
    swapped = Compensator(other, LIMIT_A, kp=0.5, ki=0.2, max_rate_a_per_s=1.0)
    swapped.continue_from(old)
    assert abs(swapped.command(2e-4, 1.9e-4, 0.1) - old.command_a) <= 0.1 + 1e-12


@pytest.mark.parametrize("tau_s", [0.0, 4.0])
def test_a_model_that_has_the_load_in_it_takes_over_the_loop_without_undoing_the_integral_first(tau_s):
    """The loop tracks a plant offset from its model (a load step); its integral holds the offset. A model fitted
    since, with the offset in it and its states where the stage is, takes over: the error stays at the loop's,
    where carrying the integral whole would add the offset a second time and the loop take its integral time
    to undo it."""
    load_m, dt_s, steps = 4e-5, 0.1, 1500
    offset = Effect("drift", {"drift_m_per_s": 0.0, "creep_m": -load_m, "creep_tau_s": 1e-6})  # constant after 1 us
    lag = (Effect("thermal_lag", {"tau_s": tau_s}),) if tau_s else ()
    old_model, new_model = with_effects(*lag), with_effects(*lag, offset)
    plant = Compensator(old_model, LIMIT_A)  # its model followed with the applied current: the stage's positions
    setpoints = slow_setpoints(2 * steps, dt_s)
    gains = {"kp": 0.5, "ki": 0.5, "max_rate_a_per_s": 1.0}
    old, new = Compensator(old_model, LIMIT_A, **gains), Compensator(new_model, LIMIT_A, **gains)
    position, before = plant.drive.predicted_m - load_m, []
    for setpoint in setpoints[:steps]:
        current = old.command(setpoint, position, dt_s)
        plant.follow_applied(current, dt_s)
        new.follow_applied(current, dt_s)  # the identification node's carried state
        position = plant.drive.predicted_m - load_m
        before.append(setpoint - position)
    assert old.integral_m == pytest.approx(load_m, rel=0.1), "the loop holds the load in its integral"
    new.continue_from(old)
    errors = []
    for setpoint in setpoints[steps:]:
        current = new.command(setpoint, position, dt_s)
        plant.follow_applied(current, dt_s)
        position = plant.drive.predicted_m - load_m
        errors.append(setpoint - position)
    # carrying the integral whole: 9.6 um (no lag) and 10.2 um (4 s lag) in the first 30 s
    assert np.max(np.abs(errors)) <= 1.1 * np.max(np.abs(before[-300:])) + 0.05 * load_m, np.max(np.abs(errors))


def test_following_the_applied_current_keeps_the_model_where_the_stage_is():
    """Currents the compensator did not command (an excitation) step its lag (each held over its step) and
    its operators (driven by the lag's state), so its next command starts where the stage is."""
    tau_s, dt_s = 6.0, 1.0
    u = 4.0 * np.sin(2.0 * np.pi * np.arange(300) / 250.0)
    following = Compensator(lagged(tau_s), LIMIT_A)
    state, forward = 0.0, GPIForwardStream(MODEL.parameters, MODEL.operators)
    for k, current in enumerate(u):
        following.follow_applied(current, dt_s if k else 0.0)
        if k:
            state = current + (state - current) * math.exp(-dt_s / tau_s)
        forward.step(state)
    assert following.drive.thermal.seen == pytest.approx(state, abs=1e-12)
    assert np.allclose(following.drive.inverse.states, forward.states, rtol=0.0, atol=1e-15)
    assert following.integral_m == 0.0 and following.command_a == u[-1]


def test_a_step_too_short_to_move_the_lag_gives_the_limited_lead_not_a_division_by_zero():
    """Fuzzing found it: a dt of 8.9e-213 s made the exact lead divide by 1 - exp(-dt / tau) = 0."""
    core = Compensator(lagged(10.0), LIMIT_A, max_rate_a_per_s=0.0, feedforward_step_lead_limit=3.0)
    target = GPIInverseStream(MODEL.parameters, MODEL.operators, input_range=(-LIMIT_A, LIMIT_A)).step(1e-4)
    assert core.command(1e-4, None, 8.857633019452313e-213) == pytest.approx(min(3.0 * target, LIMIT_A))


def test_a_huge_control_step_bounds_the_integral_instead_of_overflowing():
    """Fuzzing found it: ki 83 /s over dt 1.77e308 s overflowed the integral and the core refused finite input."""
    core = Compensator(MODEL, LIMIT_A, ki=83.0, max_rate_a_per_s=0.0)
    current = core.command(0.0, 1.0, 1.7724361384671202e308)
    assert current == -LIMIT_A and math.isfinite(core.integral_m)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_wires_lead_brings_their_temperature_difference_to_the_target_in_one_held_step(seed):
    """wire_thermal: from any wire temperatures, the lead's held current (unlimited) moves the difference of
    the two wires, stepped by the forward model's own lag, exactly to the target; the current's sign says
    which wire it heats, and a larger target never asks for less current."""
    rng = np.random.default_rng(seed)
    effect = Effect("wire_thermal", {"tau_a_s": 2.0, "tau_b_s": 7.0, "joule_reference_a": 5.0})
    hold = 0.1
    for _ in range(50):
        wires = rng.uniform(0.0, 5.0, 2)
        state = EffectState(0.0, (wires[0], 0.0, wires[1], 0.0))
        target = (wires[0] - wires[1]) + rng.uniform(-0.2, 0.2)
        thermal = ThermalState(effect, state)
        current = thermal.current(thermal.lead(target, hold, math.inf))
        thermal.advance(current, hold)
        assert thermal.seen == pytest.approx(target, abs=1e-9)
        heated_a = lag_step(wires[0], max(current, 0) ** 2 / 5.0, max(current, 0) ** 2 / 5.0, hold, 2.0)
        heated_b = lag_step(wires[1], min(current, 0) ** 2 / 5.0, min(current, 0) ** 2 / 5.0, hold, 7.0)
        assert heated_a - heated_b == pytest.approx(target, abs=1e-9)
    start = ThermalState(effect, EffectState(0.0, (1.0, 0.0, 2.0, 0.0)))
    currents = [start.current(start.lead(target, hold, math.inf)) for target in np.linspace(-1.5, -0.5, 21)]
    assert np.all(np.diff(currents) >= 0.0)


def test_building_the_core_loads_its_inverse_kernels_before_the_first_command():
    """A compensator's first command must not wait for numba (seconds on a cold cache: a node's first current_cmd
    came 4-5 s late): the core's construction runs the inverse once. Checked in a fresh interpreter."""
    script = """
import sys
sys.path.insert(0, "test")
from test_two_wire import example_model
from sma_stage.control import Compensator
from sma_stage.model import _kernels, load_model_file, two_wire
from sma_stage.nodes.launch import DEFAULT_MODEL_FILE
Compensator(example_model(), 5.0)
Compensator(load_model_file(DEFAULT_MODEL_FILE), 5.0)
print(len(two_wire._command_for.signatures), len(_kernels.exact_inverse_step.signatures))
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300,
                          cwd=Path(__file__).resolve().parent.parent, check=True)
    assert [int(count) for count in done.stdout.split()] == [1, 1], done.stdout + done.stderr
