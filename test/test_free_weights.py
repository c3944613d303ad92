"""The GPI with free density weights: the model file, the forward and both inverses with any positive weights,
and the weights fitted by bounded least squares where the exponential density cannot follow the data."""

import warnings
from dataclasses import replace

import numpy as np
import pytest

from sma_stage.errors import InputError
from sma_stage.identify import free_weights as free_weights_module
from sma_stage.identify.fit import fit_gpi
from sma_stage.identify.free_weights import fit_free_weights
from sma_stage.model import GPIParameters, IdentifiedModel, forward, inverse, load_model_file
from sma_stage.model.effects import Effect
from sma_stage.model.identified import Start
from sma_stage.signals import paper_identification_signal, paper_validation_signal

OPERATORS = 10
BIMODAL = (0.30, 0.02, 0.0, 0.05, 0.25, 0.01, 0.0, 0.12, 0.0, 0.08)  # no exponential density follows it
FREE = GPIParameters(a1=0.5e-3, a2=0.6, a3=0.1, a4=0.0, a5=0.5e-3, a6=0.6, a7=-0.2, a8=0.05e-3, a9=0.05e-3,
                     a10=0.2, a11=5e3, weights=BIMODAL)


def _bimodal_record() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t [s], u [A], y [m]): the paper's identification signal through the bimodal GPI, a little noise."""
    rng = np.random.default_rng(3)
    t = np.linspace(0.0, 1000.0, 3000)
    u = paper_identification_signal(t)
    return t, u, forward(u, FREE, OPERATORS) + rng.normal(0.0, 1e-7, t.size)


def test_free_weights_stand_for_the_density_in_the_forward_model():
    v = paper_validation_signal(np.linspace(0.0, 800.0, 600))
    r = FREE.thresholds(OPERATORS)
    z, out = np.zeros(OPERATORS), []
    for vk in v:
        z = np.maximum(FREE.envelope_left(vk) - r, np.minimum(FREE.envelope_right(vk) + r, z))
        out.append(np.array(BIMODAL) @ z)
    np.testing.assert_allclose(forward(v, FREE, OPERATORS), out, rtol=0, atol=1e-15)


@pytest.mark.parametrize("method", ["exact", "analytic"])
def test_both_inverses_take_free_weights(method):
    same = FREE.replace(a5=FREE.a1, a6=FREE.a2, a7=FREE.a3, a8=FREE.a4)  # the analytic inverse is exact then
    y = forward(paper_identification_signal(np.linspace(0.0, 1000.0, 1500)), same, OPERATORS)
    result = inverse(y, same, OPERATORS, method=method, input_range=(-5.0, 5.0), full_output=True)
    assert not result.any_clipped
    np.testing.assert_allclose(result.output, y, rtol=0, atol=1e-9 * np.ptp(y))


def test_a_free_weight_model_file_round_trips_exactly(tmp_path):
    model = IdentifiedModel(FREE, OPERATORS, (Effect("thermal_lag", {"tau_s": 9.5}),))
    model.save(tmp_path / "model.yaml")
    loaded = load_model_file(tmp_path / "model.yaml")
    assert loaded == model and loaded.parameters.weights == BIMODAL


@pytest.mark.parametrize(("weights", "message"), [((-0.1,) + BIMODAL[1:], "at least 0"),
                                                  ((0.0,) + BIMODAL[1:], "first weight above 0"),
                                                  ((float("nan"),) + BIMODAL[1:], "finite"),
                                                  (("x",) + BIMODAL[1:], "must be a number"), ((), "at least one")])
def test_bad_weights_are_refused_in_one_line(weights, message):
    with pytest.raises(InputError, match=message) as refused:
        GPIParameters(**{**FREE.to_dict(), "weights": weights})
    assert "\n" not in str(refused.value)


def test_weights_that_do_not_match_the_operators_or_go_with_the_rate_effect_are_refused():
    with pytest.raises(InputError, match="10 free weights and 12 operators"):
        IdentifiedModel(FREE, 12)
    with pytest.raises(InputError, match="rate effect"):
        IdentifiedModel(FREE, OPERATORS, (Effect("rate", {"rate_gain_s_per_A": 0.1}),))


def test_free_weights_fitted_where_the_exponential_density_cannot_follow():
    """Data made by a GPI with a bimodal density: the exponential-density fit misses it; the free weights fitted
    on its envelopes and thresholds recover the record far better, on the identification record and on another
    signal."""
    t, u, y = _bimodal_record()
    exponential = fit_gpi(u, y, operators=OPERATORS)
    plain = IdentifiedModel(exponential.parameters, OPERATORS)
    free = fit_free_weights(plain, t, u, y)
    assert free.parameters.weights is not None and all(w >= 0.0 for w in free.parameters.weights)
    other = paper_validation_signal(t)
    truth = forward(other, FREE, OPERATORS)
    error = {name: np.sqrt(np.mean((model.predict(t, other) - truth) ** 2)) for name, model in
             (("exponential", plain), ("free", free))}
    assert error["free"] < 0.5 * error["exponential"], error


def test_a_trial_the_model_refuses_does_not_end_the_search(monkeypatch):
    """A trial the model refuses (here the search's third evaluation) counts as worse than the start and the
    search goes on to the same fit; before, the first such trial ended it where it began."""
    t, u, y = _bimodal_record()
    plain = IdentifiedModel(fit_gpi(u, y, operators=OPERATORS).parameters, OPERATORS)
    searched = fit_free_weights(plain, t, u, y)
    calls = {"count": 0}
    outputs = free_weights_module.operator_outputs

    def refusing(*args: object) -> np.ndarray:
        calls["count"] += 1
        if calls["count"] == 3:
            raise InputError("a refused trial")
        return outputs(*args)

    monkeypatch.setattr(free_weights_module, "operator_outputs", refusing)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        refused_once = fit_free_weights(plain, t, u, y)
    assert calls["count"] > 3
    start = replace(plain, parameters=plain.parameters.replace(
        weights=tuple(free_weights_module._weights(outputs(plain, t, u, Start("rest")), y, 1.0))))
    errors = {name: float(np.sqrt(np.mean((model.predict(t, u) - y) ** 2)))
              for name, model in (("searched", searched), ("refused once", refused_once), ("start", start))}
    assert errors["refused once"] < 0.9 * errors["start"], errors
    assert errors["refused once"] < 1.1 * errors["searched"], errors


def test_a_trial_whose_density_overflows_gives_the_operators_outputs_quietly():
    """The free weights replace the density a10 exp(-a11 r), so a trial threshold step that overflows it (here
    exp(900)) still gives each operator's output, with no warning on the user's screen; before, it printed numpy's
    overflow warning and refused the trial."""
    t, u, _ = _bimodal_record()
    overflowing = IdentifiedModel(FREE.replace(weights=None, a11=-2e3, a9=0.05), OPERATORS)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        columns = free_weights_module.operator_outputs(overflowing, t, u, Start("rest"))
    assert columns.shape == (t.size, OPERATORS) and np.all(np.isfinite(columns))
    assert np.ptp(columns[:, 0]) > 0.0
