"""The models in force (sma_stage.identify.history): the history keeps the last N and moves a model seen again to
the end; a candidate replaces the model in force only when it predicts the held-out tail better; a refit of the
hysteresis alone holds the model's dynamics."""

from dataclasses import replace

import numpy as np
import pytest
from test_two_wire import example_model

from sma_stage.errors import InputError
from sma_stage.identify.history import ModelHistory, judge_swap, started_from
from sma_stage.identify.pipeline import dynamics_held_refusal, refit_hysteresis
from sma_stage.io.series import make_series
from sma_stage.model.effects import Effect
from sma_stage.model.identified import load_model_file
from sma_stage.plant import Effects, simulate


def models(count: int) -> list:
    """Distinct two-wire models (their offsets differ)."""
    base = example_model()
    return [type(base)(type(base.parameters)({**base.parameters.values, "offset": 1e-5 * k},
                                             base.parameters.weights_a, base.parameters.weights_b,
                                             base.parameters.output_weights)) for k in range(count)]


def test_the_history_keeps_the_last_n_models_and_a_model_seen_again_moves_to_the_end():
    history, seven = ModelHistory(5), models(7)
    for number, model in enumerate(seven):
        assert history.note(model, f"source {number}", "pushed", float(number)) is not None
    assert [entry.source for entry in history.entries] == [f"source {k}" for k in range(2, 7)]
    assert history.note(seven[6], "again", "republished", 7.0) is None, "the model in force published again"
    assert history.previous.model == seven[5]
    restored = history.note(seven[5], "rollback", "~/rollback", 8.0)
    assert restored is not None and restored.since_s == 8.0
    assert [entry.model for entry in history.entries] == [seven[2], seven[3], seven[4], seven[6], seven[5]]
    assert history.previous.model == seven[6], "a second rollback goes back to the model rolled back from"


def test_a_model_with_another_carried_state_is_the_same_model():
    history, (model,) = ModelHistory(2), models(1)
    t, u = np.arange(0.0, 100.0, 0.5), np.full(200, 2.0)
    history.note(model, "file", "start", 0.0)
    assert history.note(started_from(model, t, u), "pushed", "refit", 1.0) is None


def test_a_history_too_short_to_roll_back_is_refused():
    with pytest.raises(InputError, match="at least 2"):
        ModelHistory(1)


def record(model, seconds: float = 600.0):
    rng = np.random.default_rng(4)
    t = np.arange(0.0, seconds, 0.5)
    u = 4.0 * np.sin(2 * np.pi * t / 100.0)
    return make_series(t, u, model.predict(t, u) + rng.normal(0.0, 2e-7, t.size), "test")


def test_a_candidate_that_predicts_the_held_out_tail_worse_is_not_swapped_in():
    truth, other = models(2)
    series = record(truth)
    kept = judge_swap(other, truth, series, 900)
    assert not kept.swap and kept.candidate.rms_pct > kept.in_force.rms_pct and "kept" in kept.reason
    taken = judge_swap(truth, other, series, 900)
    assert taken.swap and taken.candidate.rms_pct < taken.in_force.rms_pct and "swapped in" in taken.reason
    assert "\n" not in taken.reason


SHIPPED = load_model_file("config/model_default.yaml")


def stage_record(load_n: float, seed: int, seconds: float = 1200.0):
    """The stage simulator (not a GPI), load_n [N] heavier than by default, driven by a slow sine of current as a
    tracking loop drives it."""
    t = np.arange(0.0, seconds, 0.5)
    u = 1.0 + 3.5 * np.sin(2 * np.pi * t / 100.0)
    stage = simulate(u, 0.5, effects=Effects(load_change_n=load_n), seed=seed)
    return make_series(t, u, stage.position_m, f"the stage {load_n:g} N heavier")


def test_a_hysteresis_refit_holds_the_dynamics_and_follows_a_load_step():
    in_force = refit_hysteresis(stage_record(0.0, seed=1), SHIPPED, 0.25).model
    loaded = stage_record(8.0, seed=3)
    found = refit_hysteresis(loaded, in_force, 0.25)
    assert found.model.effects == in_force.effects == SHIPPED.effects, "the thermal lag is held"
    kept = [(found.model.parameters.a2, found.model.parameters.a6), (in_force.parameters.a2, in_force.parameters.a6)]
    assert kept[0] == kept[1] and found.model.parameters.a3 != in_force.parameters.a3, "the envelopes' slopes held"
    decision = judge_swap(found.model, in_force, loaded, found.scored_from)
    assert decision.swap and decision.candidate.rms_pct < 0.5 * decision.in_force.rms_pct, decision.reason
    assert found.model.metadata["held_out_rms"] > 0.0 and "held" in found.report["refit"]


def test_a_model_whose_hysteresis_cannot_be_refitted_alone_is_refused_in_one_line():
    drifting = replace(SHIPPED, effects=SHIPPED.effects + (Effect("drift", {"drift_m_per_s": 1e-9}),))
    assert dynamics_held_refusal(SHIPPED) is None
    assert "two_wire model" in dynamics_held_refusal(example_model())
    with pytest.raises(InputError, match="the drift effect") as refused:
        refit_hysteresis(stage_record(0.0, seed=1, seconds=300.0), drifting, 0.25)
    assert "\n" not in str(refused.value)
