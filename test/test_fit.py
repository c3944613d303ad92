"""GPI fit: parameter recovery, standard errors, the paper's procedure, the analytic Jacobian,
regressors (offset, drift), refused input, and well-scaled parameters on data that once drove the fit
to envelopes computed by cancellation."""

import math

import numpy as np
import pytest

from sma_stage.errors import InputError
from sma_stage.identify import fit as fit_module
from sma_stage.identify import projection
from sma_stage.identify._sensitivity import householder_r
from sma_stage.identify.checks import check_motion
from sma_stage.identify.effects import base as effects_base
from sma_stage.identify.effects.base import SCREEN_SAMPLES, Refits, cold_fit
from sma_stage.identify.fit import (
    FitResult,
    fit_gpi,
    information_criterion,
    normalized,
    predict,
    scale_problems,
)
from sma_stage.identify.least_squares import levenberg_marquardt
from sma_stage.identify.projection import SCALE_LIMIT, scale_limit
from sma_stage.identify.uncertainty import model_jacobian
from sma_stage.model import GPIParameters, forward, inverse
from sma_stage.plant import simulate
from sma_stage.signals import paper_identification_signal, paper_validation_signal

OPERATORS = 10
# A stage with a ~1 mm stroke [m], a loop of visible width, gl <= gr (checked below).
RAW_TRUTH = GPIParameters(a1=0.55e-3, a2=0.55, a3=0.1, a4=0.45e-3, a5=0.5e-3, a6=0.5, a7=-0.05,
                          a8=0.56e-3, a9=0.012e-3, a10=0.25, a11=1.0 / 0.06e-3)
TRUTH = normalized(RAW_TRUTH, OPERATORS)


def identification_data(samples=2001, noise=0.0, seed=0):
    t = np.linspace(0.0, 1000.0, samples)
    u = paper_identification_signal(t)
    y = forward(u, RAW_TRUTH, OPERATORS)
    rng = np.random.default_rng(seed)
    return t, u, y + rng.normal(0.0, noise, samples)


def relative_errors(found: GPIParameters, expected: GPIParameters) -> np.ndarray:
    return np.abs(found.as_array() / expected.as_array() - 1.0)


def test_truth_is_a_realistic_stage():
    v = np.linspace(-6, 6, 1001)
    assert np.all(TRUTH.envelope_left(v) <= TRUTH.envelope_right(v))
    _, u, y = identification_data()
    assert 0.7e-3 < np.ptp(y) < 1.3e-3
    assert math.isclose(TRUTH.densities(OPERATORS).sum(), 1.0)
    assert np.allclose(forward(u, TRUTH, OPERATORS), y, rtol=0, atol=1e-15)


def test_recovers_known_parameters_from_the_data_derived_guess():
    _, u, y = identification_data()
    result = fit_gpi(u, y, operators=OPERATORS)
    assert isinstance(result, FitResult) and result.success
    assert np.max(relative_errors(result.parameters, TRUTH)) < 1e-6
    assert result.identification.max_pct < 1e-5


def test_recovers_known_parameters_from_a_perturbed_start():
    _, u, y = identification_data()
    factors = 1.0 + 0.15 * np.where(np.arange(11) % 2 == 0, 1.0, -1.0)
    start = GPIParameters.from_array(RAW_TRUTH.as_array() * factors)
    result = fit_gpi(u, y, operators=OPERATORS, initial=start)
    assert np.max(relative_errors(result.parameters, TRUTH)) < 1e-6


def test_held_parameters_keep_the_start_values_and_the_others_are_still_found():
    _, u, y = identification_data(noise=5e-6, seed=1)
    factors = 1.0 + 0.15 * np.where(np.arange(11) % 2 == 0, 1.0, -1.0)
    start = GPIParameters.from_array(RAW_TRUTH.as_array() * factors).replace(a2=RAW_TRUTH.a2, a6=RAW_TRUTH.a6)
    result = fit_gpi(u, y, operators=OPERATORS, initial=start, hold=("a2", "a6"))
    assert (result.parameters.a2, result.parameters.a6) == (RAW_TRUTH.a2, RAW_TRUTH.a6)
    moved = [name for name in ("a3", "a4", "a5", "a7", "a8", "a9") if getattr(result.parameters, name) != getattr(start, name)]
    assert len(moved) == 6
    assert result.standard_errors["a2"] == result.standard_errors["a6"] == 0.0
    free = [name for name in TRUTH.to_dict() if name not in ("a2", "a6")]
    errors = np.array([result.standard_errors[name] for name in free])
    assert np.all(np.isfinite(errors)) and np.all(errors > 0)
    deviation = [abs(getattr(result.parameters, name) - getattr(TRUTH, name)) for name in free] / errors
    assert np.max(deviation) < 4.0
    assert result.parameter_count == 8 and "Held at the warm start: a2, a6" in result.message
    wrong = fit_gpi(u, y, operators=OPERATORS, initial=start.replace(a2=0.8 * RAW_TRUTH.a2), hold=("a2",))
    assert wrong.parameters.a2 == 0.8 * RAW_TRUTH.a2 and wrong.cost > 2.0 * result.cost


def test_noisy_fit_lies_within_a_few_standard_errors():
    _, u, y = identification_data(noise=5e-6, seed=1)
    result = fit_gpi(u, y, operators=OPERATORS)
    errors = np.array([result.standard_errors[name] for name in TRUTH.to_dict()])
    assert np.all(np.isfinite(errors)) and np.all(errors > 0)
    deviation = np.abs(result.parameters.as_array() - TRUTH.as_array()) / errors
    assert np.max(deviation) < 4.0
    assert result.parameter_count == 10
    assert math.isclose(np.std(result.residual), 5e-6, rel_tol=0.1)


def test_paper_procedure_identify_on_decaying_sine_validate_on_two_cosines():
    _, u, y = identification_data(noise=2e-6, seed=2)
    result = fit_gpi(u, y)
    t = np.linspace(0.0, 1000.0, 2001)
    u_validation = paper_validation_signal(t)
    y_validation = forward(u_validation, RAW_TRUTH, OPERATORS) + np.random.default_rng(3).normal(0, 2e-6, t.size)
    from sma_stage.identify.metrics import error_metrics

    validation = error_metrics(y_validation, predict(result, u_validation))
    assert result.operators in (5, 10, 15, 20)
    assert validation.max_pct < 4.0
    assert validation.rms_pct < 1.0


def test_operator_count_is_chosen_from_the_data_with_progress_reported():
    _, u, y = identification_data(samples=1201)
    lines = []
    result = fit_gpi(u, y, progress=lines.append)
    assert result.operators == OPERATORS
    assert "Operators chosen: 10" in result.message
    assert lines and all(isinstance(line, str) for line in lines)
    assert any("surveyed" in line for line in lines)


def test_given_start_points_are_used():
    _, u, y = identification_data(samples=801)
    far = RAW_TRUTH.replace(a2=3.0, a6=3.0, a9=0.2e-3)
    near = RAW_TRUTH.replace(a2=0.6, a11=1.2 / 0.06e-3)
    result = fit_gpi(u, y, operators=OPERATORS, starts=[far, near])
    assert np.max(relative_errors(result.parameters, TRUTH)) < 1e-6
    with pytest.raises(InputError):
        fit_gpi(u, y, operators=OPERATORS, starts=["a1"])


def test_jacobian_matches_central_differences():
    _, u, _ = identification_data(samples=801)
    y, jac = model_jacobian(u, TRUTH, OPERATORS)
    assert np.allclose(y, forward(u, TRUTH, OPERATORS), rtol=0, atol=1e-15)
    theta = TRUTH.as_array()
    for j in range(11):
        step = 1e-6 * abs(theta[j])
        up, down = theta.copy(), theta.copy()
        up[j] += step
        down[j] -= step
        difference = (forward(u, GPIParameters.from_array(up), OPERATORS)
                      - forward(u, GPIParameters.from_array(down), OPERATORS)) / (2 * step)
        assert np.linalg.norm(jac[:, j] - difference) <= 1e-6 * np.linalg.norm(difference), TRUTH.to_dict()


@pytest.mark.parametrize("samples, columns", [(500, 11), (97, 1), (97, 2), (97, 6), (40, 13)])
def test_the_compiled_qr_gives_lapacks_r_of_the_chosen_columns(samples, columns):
    rng = np.random.default_rng(columns)
    rows = rng.standard_normal((columns + 2, samples))
    order = rng.permutation(columns + 2)[:columns].astype(np.int64)
    if columns > 3:
        rows[order[2]] = 0.0  # a column with nothing left to reflect
    expected = np.linalg.qr(rows[order].T, mode="r")
    found = householder_r(rows.copy(), order)
    signs = np.where(np.sign(np.diag(found)) == np.sign(np.diag(expected)), 1.0, -1.0)
    assert np.allclose(found, signs[:, None] * expected, rtol=0, atol=1e-12 * np.abs(expected).max())
    assert np.all(found == np.triu(found))


def test_regressors_recover_a_linear_drift_and_predict_applies_them():
    t, u, y = identification_data()
    drift = np.column_stack([t / 1000.0])
    result = fit_gpi(u, y + 0.2e-3 * drift[:, 0], operators=OPERATORS, regressors=drift)
    assert result.regressor_coefficients == pytest.approx([0.2e-3], rel=1e-6)
    assert np.max(relative_errors(result.parameters, TRUTH)) < 1e-6
    assert result.parameter_count == 11
    assert np.allclose(predict(result, u, drift), result.predicted, rtol=0, atol=1e-15)
    with pytest.raises(InputError):
        predict(result, u)


def test_an_offset_column_is_flagged_as_confounded_with_the_envelope_offsets():
    t, u, y = identification_data()
    columns = np.column_stack([np.ones_like(t), t / 1000.0])
    result = fit_gpi(u, y + 0.1e-3 - 0.05e-3 * columns[:, 1], operators=OPERATORS, regressors=columns)
    assert result.identification.rms_pct < 1e-4
    assert result.regressor_coefficients[1] == pytest.approx(-0.05e-3, rel=1e-4)
    assert math.isinf(result.regressor_standard_errors[0]) and np.isfinite(result.regressor_standard_errors[1])
    assert math.isinf(result.standard_errors["a4"]) and math.isinf(result.standard_errors["a8"])
    assert np.isfinite(result.standard_errors["a2"])
    with pytest.raises(InputError, match="dependent"):
        fit_gpi(u, y, operators=OPERATORS, regressors=np.column_stack([np.ones_like(t), 2 * np.ones_like(t)]))


def test_information_criterion_follows_its_formula():
    _, u, y = identification_data(noise=5e-6, seed=4)
    result = fit_gpi(u, y, operators=OPERATORS, initial=RAW_TRUTH)
    n = result.samples
    assert information_criterion(result.cost, result.samples, result.parameter_count, "aic") == pytest.approx(n * math.log(result.cost / n) + 2 * 10)
    assert information_criterion(result.cost, result.samples, result.parameter_count) == pytest.approx(n * math.log(result.cost / n) + math.log(n) * 10)
    with pytest.raises(InputError):
        information_criterion(result.cost, result.samples, result.parameter_count, "hqc")


def test_quasi_static_data_fit_without_time():
    u = paper_identification_signal(np.linspace(0.0, 1000.0, 161))  # 40 points a cycle, index as time
    y = forward(u, RAW_TRUTH, OPERATORS)
    result = fit_gpi(u, y, operators=OPERATORS)
    assert np.max(relative_errors(result.parameters, TRUTH)) < 1e-6


@pytest.mark.parametrize(
    "u, y, words",
    [
        (np.r_[np.nan, np.ones(49)], np.arange(50.0), "non-finite"),
        (np.arange(50.0), np.arange(49.0), "length"),
        (np.arange(10.0), np.arange(10.0), "too few"),
        (np.ones(50), np.arange(50.0), "no excitation"),
        (np.sin(np.arange(50.0)), np.zeros(50), "no excitation"),
        (np.sin(np.arange(50.0)), -np.sin(np.arange(50.0)), "falls"),
    ],
)
def test_bad_data_is_refused(u, y, words):
    with pytest.raises(InputError, match=words):
        fit_gpi(u, y, operators=5)


def test_a_record_that_moved_the_stage_once_is_refused_for_that_and_not_for_its_direction():
    """A stage that only the first rise of the input moved (then many cycles, nothing): the output moves over 5 % of
    its span in one part of the record of 50. Its covariance with the input is negative (it rose while the input
    did, then stayed up through every cycle), which the direction check used to read as an output that falls."""
    t = np.arange(1000.0)
    u = 4.0 * np.sin(2.0 * np.pi * t / 100.0)
    y = np.minimum(t / 15.0, 1.0) + 1e-4 * np.sin(7.0 * t)
    assert np.cov(u, y)[0, 1] < 0.0
    with pytest.raises(InputError, match=r"^no excitation: the output moved over 5 % of its span in only 2 % of the "
                                         r"record \(1 of 50 parts\); excite over a wider current range"):
        fit_gpi(u, y, operators=5)


def test_a_record_that_moves_in_a_tenth_of_its_parts_excites_the_stage():
    moving = np.sin(np.pi * np.arange(10.0) / 4.5)  # one part of ten samples spanning the whole record's range
    check_motion(np.r_[np.tile(moving, 5), np.zeros(450)])  # 5 of 50 parts move: passes
    with pytest.raises(InputError, match=r"in only 8 % of the record \(4 of 50 parts\)"):
        check_motion(np.r_[np.tile(moving, 4), np.zeros(460)])


def test_bad_options_are_refused():
    _, u, y = identification_data(samples=101)
    for options in ({"operators": 0}, {"regressors": np.ones((5, 1))}, {"starts": 0}, {"max_iterations": 0},
                    {"initial": {"a1": 1.0}}, {"tolerance": 0.0}, {"tolerance": 1.0}, {"tolerance": True},
                    {"tolerance": float("nan")}, {"hold": ("a2",)}, {"hold": ("a1",), "initial": RAW_TRUTH},
                    {"hold": ("a10",), "initial": RAW_TRUTH}):
        with pytest.raises(InputError):
            fit_gpi(u, y, **options)


def test_a_looser_tolerance_stops_sooner_near_the_same_minimum():
    """PROFILE_TOLERANCE (the effect searches' cost comparisons) spends fewer evaluations than the fit's
    own TOLERANCE from the same start, and its cost is within 1e-4 of the tight one."""
    _, u, y = identification_data(samples=1001, noise=2e-6)
    start = TRUTH.replace(a2=1.3 * TRUTH.a2, a6=0.8 * TRUTH.a6, a9=1.2 * TRUTH.a9)
    tight = fit_gpi(u, y, operators=OPERATORS, initial=start)
    loose = fit_gpi(u, y, operators=OPERATORS, initial=start, tolerance=fit_module.PROFILE_TOLERANCE)
    assert loose.iterations < tight.iterations
    assert tight.cost <= loose.cost <= (1.0 + 1e-4) * tight.cost


def exponential_data():
    """0.1 mm exp(u [A]) on the paper's decaying sine: the exponential tail of a saturated tanh, which an
    unbounded fit reaches only as a1 and -a4 grow without end (a1 was 1e7 output spans with one operator)."""
    u = paper_identification_signal(np.linspace(0.0, 1000.0, 1001))
    return u, 1e-4 * np.exp(u)


def nearly_linear_data():
    """A straight line with 0.01 % noise (a5 was 4e3 output spans with five operators)."""
    u = paper_identification_signal(np.linspace(0.0, 1000.0, 1001))
    return u, 1e-4 * u + np.random.default_rng(0).normal(0.0, 1e-7, u.size)


def stage_simulator_data():
    """The stage simulator on the paper's identification signal, 750 s at 1 s steps, as the node's refit sees
    it (with the simulator as of commit cae2403 this fit gave a1 = 1.4e7 output spans)."""
    u = paper_identification_signal(np.arange(0.0, 750.0, 1.0))
    return u, simulate(u, 1.0, seed=0).measured_position_m


@pytest.mark.parametrize("make_data, operators, max_rms_pct", [
    (exponential_data, 1, 0.01), (exponential_data, 5, 0.01), (nearly_linear_data, 5, 0.05),
    (stage_simulator_data, 10, 25.0),
])
def test_parameters_stay_well_scaled_and_the_exact_inverse_reproduces_the_fit(make_data, operators,
                                                                               max_rms_pct):
    u, y = make_data()
    result = fit_gpi(u, y, operators=operators)
    params, span = result.parameters, np.ptp(y)
    assert max(abs(params.a1), abs(params.a5), params.a9 * (operators - 1)) <= SCALE_LIMIT * span * (1 + 1e-9)
    assert scale_problems(params, operators, y) == []
    assert result.identification.rms_pct < max_rms_pct
    inputs = inverse(result.predicted, params, operators, input_range=(-5.0, 5.0))
    assert np.max(np.abs(forward(inputs, params, operators) - result.predicted)) <= 1e-6 * span


def test_scale_problems_name_envelopes_computed_by_cancellation():
    _, _, y = identification_data(samples=201)
    assert scale_problems(TRUTH, OPERATORS, y) == []
    seen = TRUTH.replace(a1=1.1e11, a4=-1.1e11, a9=1.0e11 / (OPERATORS - 1))  # the refit seen in the demo
    problems = " ".join(scale_problems(seen, OPERATORS, y))
    assert "a1 is" in problems and "a4 is" in problems and "a9*(n-1) is" in problems
    assert "a5 is" not in problems and "a8 is" not in problems


def test_badly_scaled_counts_are_passed_over_and_refused_when_none_is_left(monkeypatch):
    _, u, y = identification_data(samples=1201)
    checked = scale_problems
    monkeypatch.setattr(fit_module, "scale_problems",
                        lambda params, operators, data: ["refused here"] if operators == OPERATORS
                        else checked(params, operators, data))
    result = fit_gpi(u, y)
    assert result.operators != OPERATORS
    assert f"Refused as badly scaled: {OPERATORS} operators: refused here" in result.message
    monkeypatch.setattr(fit_module, "scale_problems", checked)
    monkeypatch.setattr(fit_module, "OFFSET_LIMIT", 1e-3)
    with pytest.raises(InputError, match="no well-scaled GPI parameters.*a4 is"):
        fit_gpi(u, y, operators=OPERATORS)


def test_projected_gradient_matches_central_differences_with_the_scale_at_its_bound(monkeypatch):
    _, u, y = identification_data(samples=401)
    start = RAW_TRUTH.replace(a2=0.6, a5=0.55e-3, a8=0.6e-3, a9=0.015e-3)
    monkeypatch.setattr(projection, "SCALE_LIMIT", 0.5)
    for regressors in (np.zeros((u.size, 0)), np.linspace(0.0, 1.0, u.size)[:, None]):
        problem, a1, x, *_ = fit_module._setup(u, y, regressors, OPERATORS, start)
        residual = problem.fun(x)
        gradient = 2.0 * problem.jac(x).T @ residual
        limit, _ = scale_limit(a1, x, OPERATORS, problem.span)
        assert problem.coefficients[-1] == pytest.approx(limit, rel=1e-12)
        for j in range(x.size):
            step = np.zeros_like(x)
            step[j] = 1e-6 * abs(x[j])
            up, down = problem.fun(x + step), problem.fun(x - step)
            difference = (up @ up - down @ down) / (2 * step[j])
            assert gradient[j] == pytest.approx(difference, rel=1e-4)


def test_a_thorough_cold_fit_on_a_long_record_runs_on_a_thinned_copy_and_polishes_only_what_beats_the_warm_fit():
    _, u, y = identification_data(samples=3 * SCREEN_SAMPLES, noise=1e-6)
    good = fit_gpi(u, y, operators=OPERATORS, initial=TRUTH)
    again = cold_fit(u, y, OPERATORS, "m", good)
    assert again is None or again.cost <= 1.001 * good.cost, "no polish, or one that ends at the optimum"
    elsewhere = fit_gpi(u, 0.5 * y, operators=OPERATORS)  # a fit of other data: its output misses this record
    found = cold_fit(u, y, OPERATORS, "m", elsewhere)
    assert found is not None and found.predicted.size == u.size, "polished on every sample"
    assert found.cost <= 1.001 * good.cost, "the data-derived starts reach the optimum"
    short = cold_fit(u[:SCREEN_SAMPLES], y[:SCREEN_SAMPLES], OPERATORS, "m", good)
    assert short is not None and short.predicted.size == SCREEN_SAMPLES, "a short record: the plain cold fit"


def test_refits_compare_costs_at_the_profile_tolerance_and_keep_a_fit_at_the_tight_one(monkeypatch):
    """Refits.cost (the scalar searches' grids and Brent steps) fits at PROFILE_TOLERANCE; a fit asked for
    with Refits.fit, the one an effect keeps, at the fit's own TOLERANCE, warm and cold alike."""
    _, u, y = identification_data(samples=801, noise=1e-6)
    base = fit_gpi(u, y, operators=OPERATORS, initial=TRUTH)
    asked = []

    def recording(*args, **kwargs):
        asked.append(kwargs["tolerance"])
        return fit_gpi(*args, **kwargs)

    monkeypatch.setattr(effects_base, "fit_gpi", recording)
    refits = Refits(lambda gain: gain * u, y, base)
    refits.cost(math.log(1.1), thorough=True)
    assert asked and set(asked) == {fit_module.PROFILE_TOLERANCE}
    profiled = refits.fits[1.1]
    asked.clear()
    kept = refits.fit(1.1, thorough=True)
    assert asked and set(asked) == {fit_module.TOLERANCE}
    assert kept.cost <= profiled.cost, "the tight fit starts where the profile's ended"


def _decays(x):
    """Residual and Jacobian of a * exp(-b t) + c against a known curve, for the optimiser's tests."""
    t = np.linspace(0.0, 4.0, 40)
    target = 2.0 * np.exp(-1.3 * t) + 0.5
    a, b, c = x
    decay = np.exp(-b * t)
    return a * decay + c - target, np.column_stack([decay, -a * t * decay, np.ones_like(t)])


def test_levenberg_marquardt_finds_scipys_minimum_inside_and_on_a_bound():
    """The fit's optimiser against scipy's TRF on a small problem: the same minimum with the bounds slack,
    and the same constrained minimum with c held below its best value by a bound the gradient pushes against."""
    from scipy.optimize import least_squares

    fun, jac = (lambda x: _decays(x)[0]), (lambda x: _decays(x)[1])
    for high in ([10.0, 10.0, 10.0], [10.0, 10.0, 0.3]):
        bounds = (np.array([0.0, 0.0, -1.0]), np.array(high))
        ours = levenberg_marquardt(fun, jac, np.array([1.0, 0.5, 0.0]), bounds, max_nfev=200)
        theirs = least_squares(fun, [1.0, 0.5, 0.0], jac=jac, bounds=bounds, ftol=1e-12, xtol=1e-12, gtol=1e-12)
        assert ours.success and ours.status > 0, ours.message
        assert ours.cost == pytest.approx(theirs.cost, rel=1e-6, abs=1e-14)
        np.testing.assert_allclose(ours.x, theirs.x, rtol=1e-4, atol=1e-8)
    assert ours.x[2] == pytest.approx(0.3, abs=1e-6)


def test_levenberg_marquardt_stops_at_its_evaluation_budget():
    fun, jac = (lambda x: _decays(x)[0]), (lambda x: _decays(x)[1])
    bounds = (np.zeros(3) - 10.0, np.zeros(3) + 10.0)
    found = levenberg_marquardt(fun, jac, np.array([5.0, 5.0, 5.0]), bounds, max_nfev=3, tolerance=0.0)
    assert (found.nfev, found.status, found.success) == (3, 0, False)
    assert found.cost < 0.5 * float(np.sum(fun(np.array([5.0, 5.0, 5.0])) ** 2))


def test_levenberg_marquardt_refuses_a_start_where_the_residual_is_not_finite():
    """As scipy's least_squares does, so that a fit that cannot start is a clear failure, not a NaN cost."""
    bounds = (np.zeros(3) - 10.0, np.zeros(3) + 10.0)
    with pytest.raises(ValueError, match="not finite at the start"):
        levenberg_marquardt(lambda x: np.array([np.nan, 1.0]), lambda x: np.ones((2, 3)), np.zeros(3), bounds, 10)
