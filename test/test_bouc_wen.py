"""The Bouc-Wen baseline family: its model file, forward from rest or a carried state, the exact inverse, the fit,
and the compensator running it."""

import numpy as np
import pytest

from sma_stage.control import Compensator
from sma_stage.errors import InputError
from sma_stage.identify.bouc_wen import fit_bouc_wen
from sma_stage.model.bouc_wen import BoucWenModel, BoucWenParameters
from sma_stage.model.kinds import load_any_model_file
from sma_stage.signals import paper_identification_signal, paper_validation_signal

VALUES = {"tau_s": 6.0, "k_x": 2e-5, "k_w": 1.5e-4, "offset": 3e-5, "beta": 0.6, "gamma": 0.2, "n": 1.5}
MODEL = BoucWenModel(BoucWenParameters(VALUES))


def record(signal, seconds: float = 1000.0, step_s: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(0.0, seconds, step_s)
    return t, signal(t)


def test_a_model_file_round_trips_exactly_with_its_state(tmp_path):
    t, u = record(paper_identification_signal)
    _, state = MODEL.run(t, u)
    carried = BoucWenModel(MODEL.parameters, "m", state, {"source": "test"})
    carried.save(tmp_path / "model.yaml")
    loaded = load_any_model_file(tmp_path / "model.yaml")
    assert loaded == carried and loaded.metadata == {"source": "test"}


def test_a_record_continued_from_its_carried_state_matches_the_whole():
    t, u = record(paper_validation_signal)
    whole = MODEL.predict(t, u)
    first, state = MODEL.run(t[:900], u[:900])
    np.testing.assert_allclose(np.r_[first, MODEL.predict(t[900:], u[900:], state)], whole, rtol=0, atol=1e-15)


def test_the_output_rises_with_the_current_held_over_a_step():
    t, u = record(paper_identification_signal, 400.0)
    stream = MODEL.stream()
    for current in u[::7]:
        state = stream._state.copy()
        ends = []
        for trial in np.linspace(-5.0, 5.0, 41):
            stream._state[:] = state
            ends.append(stream.step(trial, 0.5))
        assert np.all(np.diff(ends) >= -1e-18)
        stream._state[:] = state
        stream.step(current, 0.5)


def test_the_exact_inverse_reaches_every_reachable_target():
    t, u = record(paper_validation_signal, 600.0)
    targets = MODEL.predict(t, u)
    stream = MODEL.stream()
    reached = [stream.step(stream.command_for(target, 0.5), 0.0) for target in targets[1:]]
    span = np.ptp(targets)
    np.testing.assert_allclose(reached, targets[1:], rtol=0, atol=1e-9 * span)


def test_a_fit_recovers_a_bouc_wen_plant():
    t, u = record(paper_identification_signal)
    rng = np.random.default_rng(0)
    y = MODEL.predict(t, u) + rng.normal(0.0, 2e-7, t.size)
    found = fit_bouc_wen(t, u, y)
    tv, uv = record(paper_validation_signal)
    error = found.model.without_state().predict(tv, uv) - MODEL.predict(tv, uv)
    assert np.sqrt(np.mean(error**2)) < 0.01 * np.ptp(MODEL.predict(tv, uv))
    assert found.parameter_count == 7 and np.isfinite(found.bic)


@pytest.mark.parametrize(("changes", "message"), [({"gamma": 0.9}, "at most beta"), ({"beta": 0.0}, "> 0"),
                                                  ({"k_w": -1.0}, ">= 0"), ({"n": 7.0}, "from 1 to 5"),
                                                  ({"tau_s": float("nan")}, "finite"), ({"zeta": 1.0}, "unknown")])
def test_bad_parameters_are_refused_in_one_line(changes, message):
    with pytest.raises(InputError, match=message) as refused:
        BoucWenParameters({**VALUES, **changes})
    assert "\n" not in str(refused.value)


def test_the_compensator_runs_a_bouc_wen_model_and_refuses_the_analytic_inverse():
    core = Compensator(MODEL, 5.0)
    low, high = core.drive.reach
    target = low + 0.6 * (high - low)
    for _ in range(400):
        core.command(target, None, 0.5)
    stream = MODEL.stream()
    for _ in range(400):
        stream.step(core.command_a, 0.5)
    assert abs(stream.output - target) < 1e-3 * (high - low)
    assert "Bouc-Wen" in core.drive.describe()
    with pytest.raises(InputError, match="exact inverse only"):
        Compensator(MODEL, 5.0, "analytic")
