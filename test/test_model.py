"""The GPI model core: forward (eqs 1-5), exact and analytic inverses, parameters and model files."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sma_stage.errors import InputError
from sma_stage.model import (
    GPIForwardStream,
    GPIInverseStream,
    GPIParameters,
    IdentifiedModel,
    forward,
    forward_with_states,
    inverse,
    load_model_file,
)
from sma_stage.signals import paper_identification_signal, paper_validation_signal

STAGE = GPIParameters(a1=0.5e-3, a2=0.6, a3=0.1, a4=0.0, a5=0.5e-3, a6=0.6, a7=-0.2, a8=0.05e-3,
                      a9=0.05e-3, a10=0.2, a11=5e3)
OPERATORS = 10


def reference_forward(v, params, operators, initial=None):
    """Eqs 1-5 written out sample by sample, independent of the compiled kernel."""
    r = params.a9 * np.arange(operators)
    p = params.a10 * np.exp(-params.a11 * r)
    z = np.zeros(operators) if initial is None else np.array(initial, dtype=float)
    out = []
    for vk in v:
        gl = params.a1 * np.tanh(params.a2 * vk + params.a3) + params.a4
        gr = params.a5 * np.tanh(params.a6 * vk + params.a7) + params.a8
        z = np.maximum(gl - r, np.minimum(gr + r, z))
        out.append(p @ z)
    return np.array(out)


inputs = st.lists(st.floats(-6.0, 6.0, allow_nan=False), min_size=1, max_size=60)


def test_forward_matches_the_equations_written_out():
    v = paper_validation_signal(np.linspace(0.0, 600.0, 700))
    np.testing.assert_allclose(forward(v, STAGE, OPERATORS), reference_forward(v, STAGE, OPERATORS),
                               rtol=0, atol=1e-15)


def test_default_initial_state_is_s_of_v0_and_zero():
    v0 = 2.0
    r = STAGE.thresholds(OPERATORS)
    z0 = np.maximum(STAGE.envelope_left(v0) - r, np.minimum(STAGE.envelope_right(v0) + r, 0.0))
    _, states = forward_with_states([v0], STAGE, OPERATORS)
    np.testing.assert_allclose(states, z0, atol=1e-15)


@given(inputs)
@settings(max_examples=60, deadline=None)
def test_operator_states_stay_within_their_band(v):
    r = STAGE.thresholds(OPERATORS)
    _, states = forward_with_states(v, STAGE, OPERATORS)
    low = STAGE.envelope_left(v[-1]) - r
    high = STAGE.envelope_right(v[-1]) + r
    assert np.all(states >= low - 1e-15)
    assert np.all(states <= np.maximum(high, low) + 1e-15)


@given(inputs, st.integers(2, 6))
@settings(max_examples=60, deadline=None)
def test_output_does_not_depend_on_how_the_path_is_sampled(v, refinement):
    """Rate independence: inserting intermediate points on each monotone segment changes nothing at the
    original samples."""
    dense = [v[0]]
    for start, end in zip(v[:-1], v[1:], strict=True):
        dense.extend(np.linspace(start, end, refinement + 1)[1:])
    coarse_output = forward(v, STAGE, OPERATORS)
    dense_output = forward(dense, STAGE, OPERATORS)[::refinement]
    np.testing.assert_allclose(dense_output, coarse_output, atol=1e-15)


@given(inputs, st.floats(0.0, 6.0))
@settings(max_examples=60, deadline=None)
def test_a_larger_excursion_wipes_out_the_memory_of_smaller_ones(history, peak):
    """Wiping out: after the input visits a value above everything before it, the state no longer
    depends on what came before (from any history starting below)."""
    top = max(max(history), peak) + 20.0
    _, after_history = forward_with_states(history + [top], STAGE, OPERATORS)
    _, after_nothing = forward_with_states([history[0], top], STAGE, OPERATORS)
    np.testing.assert_allclose(after_history, after_nothing, atol=1e-15)


def test_streaming_forward_equals_batch_and_continues_from_its_states():
    v = paper_identification_signal(np.linspace(0.0, 1000.0, 500))
    stream = GPIForwardStream(STAGE, OPERATORS)
    streamed = np.array([stream.step(value) for value in v])
    np.testing.assert_allclose(streamed, forward(v, STAGE, OPERATORS), atol=1e-15)
    first, states = forward_with_states(v[:200], STAGE, OPERATORS)
    rest = forward(v[200:], STAGE, OPERATORS, initial=states)
    np.testing.assert_allclose(np.concatenate([first, rest]), forward(v, STAGE, OPERATORS), atol=1e-15)


@pytest.mark.parametrize("method", ["exact", "analytic"])
def test_streaming_inverse_equals_batch(method):
    y = forward(paper_validation_signal(np.linspace(0.0, 800.0, 400)), STAGE, OPERATORS)
    stream = GPIInverseStream(STAGE, OPERATORS, method=method)
    streamed = np.array([stream.step(target) for target in y])
    np.testing.assert_allclose(streamed, inverse(y, STAGE, OPERATORS, method=method), atol=1e-12)


@given(inputs)
@settings(max_examples=80, deadline=None)
def test_exact_inverse_reproduces_every_reachable_output(v):
    v = np.clip(v, -5.0, 5.0)
    y = forward(v, STAGE, OPERATORS)
    result = inverse(y, STAGE, OPERATORS, input_range=(-5.0, 5.0), full_output=True)
    span = STAGE.a10 * np.sum(np.exp(-STAGE.a11 * STAGE.thresholds(OPERATORS))) * 2 * STAGE.a1
    assert not result.any_clipped
    np.testing.assert_allclose(result.output, y, rtol=0, atol=1e-9 * span)


def test_exact_inverse_clips_unreachable_targets_and_says_so():
    y_top = forward([5.0], STAGE, OPERATORS)[0]
    y_bottom = forward([-5.0], STAGE, OPERATORS)[0]
    result = inverse([y_top * 2.0, 0.0, y_bottom - 1.0], STAGE, OPERATORS, input_range=(-5.0, 5.0),
                     full_output=True)
    np.testing.assert_array_equal(result.clipped, [1, 0, -1])
    assert result.input[0] == 5.0 and result.input[2] == -5.0
    assert result.any_clipped


def test_analytic_inverse_is_exact_when_the_envelopes_coincide():
    same = STAGE.replace(a5=STAGE.a1, a6=STAGE.a2, a7=STAGE.a3, a8=STAGE.a4)
    v = paper_identification_signal(np.linspace(0.0, 1000.0, 2000))
    y = forward(v, same, OPERATORS)
    result = inverse(y, same, OPERATORS, method="analytic", full_output=True)
    np.testing.assert_allclose(result.output, y, atol=1e-12 * np.ptp(y))


def test_analytic_inverse_departs_from_exact_when_the_envelopes_differ():
    y = forward(paper_identification_signal(np.linspace(0.0, 1000.0, 2000)), STAGE, OPERATORS)
    error = inverse(y, STAGE, OPERATORS, method="analytic", full_output=True).output - y
    assert 1e-4 < np.max(np.abs(error)) / np.ptp(y) < 0.2


@pytest.mark.parametrize("bad", [[0.0, np.nan], [np.inf], [], [[1.0, 2.0]], "abc"])
def test_forward_refuses_bad_input_in_one_line(bad):
    with pytest.raises(InputError) as error:
        forward(bad, STAGE, OPERATORS)
    assert "\n" not in str(error.value)


def test_inverse_refuses_mismatched_initial_state_and_non_invertible_models():
    with pytest.raises(InputError, match="expected 10"):
        forward([0.0], STAGE, OPERATORS, initial=np.zeros(3))
    with pytest.raises(InputError, match="not invertible"):
        inverse([0.0], STAGE.replace(a10=-1.0), OPERATORS)
    with pytest.raises(InputError, match="method"):
        inverse([0.0], STAGE, OPERATORS, method="newton")
    with pytest.raises(InputError, match="input range"):
        inverse([0.0], STAGE, OPERATORS, input_range=(1.0, -1.0))
    with pytest.raises(InputError, match="finite"):
        GPIInverseStream(STAGE, OPERATORS).step(float("nan"))


@pytest.mark.parametrize("changes, message", [
    ({"a9": 0.0}, "a9"), ({"a3": float("nan")}, "a3"), ({"a1": "x"}, "a1"),
    ({"output_unit": ""}, "output_unit"),
])
def test_parameters_are_validated_on_construction(changes, message):
    with pytest.raises(InputError, match=message):
        STAGE.replace(**changes)


@pytest.mark.parametrize("operators", [0, -3, 2.5, True])
def test_operator_count_is_validated(operators):
    with pytest.raises(InputError, match="operator count"):
        forward([0.0], STAGE, operators)


def test_model_file_round_trip_is_exact(tmp_path):
    path = tmp_path / "model.yaml"
    IdentifiedModel(STAGE, 12, metadata={"source": "test"}).save(path)
    loaded = load_model_file(path)
    assert loaded.parameters == STAGE and loaded.operators == 12 and loaded.metadata == {"source": "test"}


@pytest.mark.parametrize("text, message", [
    ("parameters: [1, 2]", "mapping of a1..a11"),
    ("kind: gpi\nparameters: {a1: 1}", "missing"),
    ("kind: preisach\nparameters: {}", "not supported"),
    ("parameters: {", "not valid YAML"),
    ("- just a list", "expected a mapping"),
])
def test_malformed_model_files_give_one_line_errors(tmp_path, text, message):
    path = tmp_path / "model.yaml"
    path.write_text(text)
    with pytest.raises(InputError, match=message) as error:
        load_model_file(path)
    assert "\n" not in str(error.value)


def test_a_failed_save_leaves_the_old_file_in_place(tmp_path):
    path = tmp_path / "model.yaml"
    IdentifiedModel(STAGE).save(path)
    before = path.read_text()
    with pytest.raises(InputError):
        IdentifiedModel(STAGE, operators=0).save(path)
    assert path.read_text() == before
    assert [item.name for item in tmp_path.iterdir()] == ["model.yaml"]


def test_inverse_tolerance_comes_from_the_output_span():
    """The solver's tolerance is 1e-10 of what the output really spans over the input range, even when the
    envelopes lie far apart (gr 1 m above gl: the output barely moves, the envelopes span a metre)."""
    from sma_stage.model.inverse import output_span

    far = STAGE.replace(a8=1.0)
    sweep = np.concatenate([np.linspace(-5.0, 5.0, 201), np.linspace(5.0, -5.0, 201)])
    assert output_span(far, OPERATORS, (-5.0, 5.0)) == pytest.approx(np.ptp(forward(sweep, far, OPERATORS)))
    assert output_span(far, OPERATORS, (-5.0, 5.0)) < 1e-2
