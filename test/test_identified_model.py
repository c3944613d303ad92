"""The identified model: the GPI with its effects, run forward, saved and loaded (one YAML form, read
strictly), continued from the state a record left."""

import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from sma_stage.errors import InputError
from sma_stage.model import Effect, GPIParameters, IdentifiedModel, forward, load_model_file
from sma_stage.model.identified import Start
from sma_stage.signals import paper_identification_signal

STAGE = GPIParameters(a1=0.5e-3, a2=0.6, a3=0.1, a4=0.0, a5=0.5e-3, a6=0.6, a7=-0.2, a8=0.05e-3,
                      a9=0.05e-3, a10=0.2, a11=5e3)
EFFECTS = {
    "none": (),
    "thermal_lag": (Effect("thermal_lag", {"tau_s": 11.3}),),
    "thermal_lag (heating)": (Effect("thermal_lag", {"tau_s": 9.7, "joule_reference_a": 4.8}),),
    "delay": (Effect("delay", {"delay_s": 3.25}),),
    "rate": (Effect("rate", {"rate_gain_s_per_A": 2.5}),),
    "rate (additive)": (Effect("rate", {"rate_shift_m_s_per_A": 2e-6}),),
    "wire_thermal": (Effect("wire_thermal", {"tau_a_s": 8.0, "tau_b_s": 13.0, "joule_reference_a": 5.0}),),
    "wire_thermal + delay": (Effect("wire_thermal", {"tau_a_s": 8.0, "tau_b_s": 13.0, "joule_reference_a": 5.0}),
                             Effect("delay", {"delay_s": 1.5})),
    "drift": (Effect("drift", {"drift_m_per_s": 4e-8}),),
    "drift with creep": (Effect("drift", {"drift_m_per_s": 4e-8, "creep_m": 2e-5, "creep_tau_s": 80.0}),),
    "thermal_lag + delay + drift": (Effect("thermal_lag", {"tau_s": 11.3}), Effect("delay", {"delay_s": 2.0}),
                                    Effect("drift", {"drift_m_per_s": -3e-8})),
}
T = np.arange(0.0, 600.0, 0.5)
U = paper_identification_signal(T, 5.0, 3.6, 250.0, 600.0)


@pytest.mark.parametrize("name", list(EFFECTS))
def test_save_and_load_reproduce_predict_to_1e_12(tmp_path, name):
    model = IdentifiedModel(STAGE, 12, EFFECTS[name], metadata={"source": "test"})
    _, state = model.run(T, U)
    for saved in (model, replace(model, state=state)):
        path = tmp_path / "model.yaml"
        saved.save(path)
        loaded = load_model_file(path)
        assert loaded == saved and loaded.metadata == {"source": "test"}
        assert np.max(np.abs(loaded.predict(T, U) - saved.predict(T, U))) <= 1e-12 * np.ptp(saved.predict(T, U))
        assert IdentifiedModel.from_yaml_text(saved.to_yaml_text()) == saved


@pytest.mark.parametrize("name", list(EFFECTS))
def test_a_record_continued_from_its_state_equals_the_whole_record(name):
    """Exact, except that rate's central difference at the head's last sample cannot see the next one."""
    model = IdentifiedModel(STAGE, 10, EFFECTS[name])
    whole = model.predict(T, U)
    half = T.size // 2
    head, state = model.run(T[:half], U[:half])
    tail = model.predict(T[half:], U[half:], state)
    tolerance = 1e-3 if name.startswith("rate") else 1e-12
    assert np.max(np.abs(np.concatenate((head, tail)) - whole)) <= tolerance * np.ptp(whole)


def test_without_effects_it_is_the_gpi():
    assert np.array_equal(IdentifiedModel(STAGE, 10).predict(T, U), forward(U, STAGE, 10))


@pytest.mark.parametrize(("edit", "message"), [
    (lambda text: text.replace("operators: 10", "operator: 10"), "unknown key 'operator'"),
    (lambda text: text.replace("output_unit: m", "output_units: mm"), "unknown key 'output_units'"),
    (lambda text: text.replace("tau_s", "tau"), "unknown parameter 'tau'"),
    (lambda text: text.replace("kind: thermal_lag", "kind: thermal_lags"), "unknown effect 'thermal_lags'"),
    (lambda text: text.replace("schema_version: 1", "schema_version: 2"), "schema_version 2"),
    (lambda text: text.replace("tau_s: 11.3", "tau_s: -1.0"), "at least 0"),
    (lambda text: text.replace("tau_s: 11.3", "tau_s: .nan"), "finite"),
])
def test_a_misspelt_or_bad_key_is_refused_naming_it(tmp_path, edit, message):
    path = tmp_path / "model.yaml"
    text = IdentifiedModel(STAGE, 10, EFFECTS["thermal_lag"]).to_yaml_text()
    path.write_text(edit(text))
    with pytest.raises(InputError, match=message) as error:
        load_model_file(path)
    assert "\n" not in str(error.value) and str(path) in str(error.value)


def test_a_model_file_without_a_schema_version_is_a_plain_gpi(tmp_path):
    path = tmp_path / "old.yaml"
    path.write_text(yaml.safe_dump({"kind": "gpi", "output_unit": "m", "operators": 7, "parameters": STAGE.to_dict()}))
    assert load_model_file(path) == IdentifiedModel(STAGE, 7)


def test_an_effect_twice_or_a_state_of_the_wrong_size_is_refused():
    with pytest.raises(InputError, match="twice"):
        IdentifiedModel(STAGE, 10, EFFECTS["drift"] * 2)
    _, state = IdentifiedModel(STAGE, 10).run(T, U)
    with pytest.raises(InputError, match="operator states"):
        IdentifiedModel(STAGE, 11, (), state)


@pytest.mark.parametrize("name", ["thermal_lag", "wire_thermal + delay", "thermal_lag + delay + drift"])
def test_a_held_start_is_the_state_a_long_hold_at_the_first_current_leaves(name):
    """Start("held") equals running the model, from rest, over a long hold at the record's first current
    before it (the drift's clock aside: it starts with the record either way)."""
    model = IdentifiedModel(STAGE, 12, EFFECTS[name])
    hold_t = np.arange(-2000.0, 0.0, 0.5)
    _, held_state = model.run(hold_t, np.full(hold_t.size, U[0] if U[0] != 0.0 else 3.0))
    u = U.copy()
    if u[0] == 0.0:
        u[0] = 3.0
    by_hold = model.predict(T, u, held_state)
    started = model.predict_from(T, u, Start("held"))
    drift = model.effect("drift")
    if drift is not None:
        by_hold = by_hold - drift.drift_at(T - T[0] + 2000.0) + drift.drift_at(T - T[0])
    assert np.max(np.abs(started - by_hold)) <= 1e-6 * np.ptp(by_hold)


def test_a_free_start_takes_its_values_by_name_and_refuses_a_wrong_count():
    model = IdentifiedModel(STAGE, 12, EFFECTS["wire_thermal + delay"])
    assert model.free_start_names == ["gpi_turning_point_a", "wire_thermal.wire_a_a", "wire_thermal.wire_b_a",
                                      "delay.held_current_a"]
    state = model.start_state(T, U, Start("free", (-2.0, 4.0, 0.5, 1.0)))
    assert state.effects[0].values[0] == 4.0 and state.effects[0].values[2] == 0.5
    with pytest.raises(InputError, match="takes 4 values"):
        model.start_state(T, U, Start("free", (1.0,)))
    with pytest.raises(InputError, match="unknown start"):
        Start("warm")


@pytest.mark.parametrize(("kind", "parameters", "message"), [
    ("rate", {}, "give rate_gain_s_per_A .multiplicative. or rate_shift_m_s_per_A .additive."),
    ("wire_thermal", {"tau_a_s": 1.0, "tau_b_s": 2.0, "joule_reference_a": 0.0}, "joule_reference_a must be above 0"),
    ("wire_thermal", {"tau_a_s": -1.0, "tau_b_s": 2.0, "joule_reference_a": 5.0}, "'tau_a_s' must be at least 0"),
    ("wire_thermal", {"tau_a_s": 1.0, "joule_reference_a": 5.0}, "'tau_b_s' is missing"),
])
def test_a_bad_new_effect_is_refused_in_one_line(kind, parameters, message):
    with pytest.raises(InputError, match=message) as refused:
        Effect(kind, parameters)
    assert "\n" not in str(refused.value)


SHIPPED_MODEL_TEXT = (Path(__file__).resolve().parent.parent / "config" / "model_default.yaml").read_text()

# YAML that used to end a node with a traceback (TypeError from sorting mixed keys, OverflowError, RecursionError)
HOSTILE_MODEL_TEXTS = {
    "mixed_type_keys": SHIPPED_MODEL_TEXT.replace("parameters:\n", "parameters:\n  1: 0\n", 1),
    "huge_integer": SHIPPED_MODEL_TEXT.replace("operators:", "operators: 1" + "0" * 400 + "\nxoperators:", 1),
    "huge_parameter": "kind: gpi\noperators: 5\nparameters: {a1: 1" + "0" * 400 + ", a2: 1, a3: 0, a4: 0, a5: 1, "
                      "a6: 1, a7: 0, a8: 0, a9: 0.1, a10: 1, a11: 0}\n",
    "deep_nesting": "a: " + "[" * 50000 + "]" * 50000 + "\n",
    "alias_bomb": "a: &a [x, x]\nb: &b [*a, *a]\nc: [*b, *b]\n",
    "too_long": "# " + "x" * (2 << 20) + "\n",
}


@pytest.mark.parametrize("name", list(HOSTILE_MODEL_TEXTS))
def test_hostile_model_yaml_is_one_line_refusal(name, tmp_path):
    text = HOSTILE_MODEL_TEXTS[name]
    with pytest.raises(InputError) as from_text:
        IdentifiedModel.from_yaml_text(text)
    path = tmp_path / "model.yaml"
    path.write_text(text)
    with pytest.raises(InputError) as from_file:
        load_model_file(path)
    for error in (from_text.value, from_file.value):
        assert "\n" not in str(error) and len(str(error)) < 300, str(error)


def test_a_model_file_that_is_not_a_regular_file_is_refused_at_once(tmp_path):
    fifo = tmp_path / "model.fifo"
    os.mkfifo(fifo)
    with pytest.raises(InputError, match="is not a regular file"):
        load_model_file(fifo)
    with pytest.raises(InputError, match="is not a regular file"):
        load_model_file(tmp_path)


def test_gpi_parameters_from_a_mapping_with_mixed_keys_name_them():
    values = {**STAGE.to_dict(), 1: 0.0, "x": 0.0}
    with pytest.raises(InputError, match="unknown GPI parameters: 1, x"):
        GPIParameters.from_dict(values)
    with pytest.raises(InputError, match="must be finite"):
        STAGE.replace(a1=10**400)
