"""Closing the loop: residual tests, candidate effects, and the diagnosis on GPI-plant data with one
effect injected and not declared (test/synthetic.py simulates it independently of effects.py)."""

import functools
import json
import os
from pathlib import Path

import numpy as np
import pytest
from synthetic import DEFAULT_EFFECTS, TRUE_OPERATORS, TRUE_PARAMETERS, make_case

from sma_stage.errors import InputError
from sma_stage.identify import workers as workers_module
from sma_stage.identify.chain import Validation
from sma_stage.identify.diagnosis import diagnose
from sma_stage.identify.effects import EFFECT_NAMES
from sma_stage.identify.effects.delay import delayed_input
from sma_stage.identify.effects.rate import rate_model_output
from sma_stage.identify.effects.thermal_lag import lagged_input
from sma_stage.identify.fit import fit_gpi, predict
from sma_stage.identify.metrics import error_metrics
from sma_stage.identify.residual_tests import TEST_NAMES, residual_tests
from sma_stage.identify.workers import Workers
from sma_stage.io import read_csv
from sma_stage.model import forward
from sma_stage.model.effects import input_rate, rate_forward

FLOOR_FACTOR = 1.5
SEED = 7
# Relative accuracy of the recovered effect parameter (the identification never sees the truth).
PARAMETER_TOLERANCE = 0.05


@functools.cache
def diagnosed(effect: str):
    """(case, diagnosis) for the synthetic plant with `effect` injected; computed once per session."""
    case = make_case(effect, seed=SEED)
    ident, valid = case.identification, case.validation
    return case, diagnose((ident.t, ident.u, ident.y), (valid.t, valid.u, valid.y))


# ---- the diagnosis ------------------------------------------------------------------------------


@pytest.mark.parametrize("effect", [name for name in DEFAULT_EFFECTS if name != "none"])
def test_diagnose_names_the_injected_effect_and_reaches_the_noise_floor(effect):
    case, result = diagnosed(effect)
    floor = case.validation.noise_floor_pct
    assert result.effect == effect, [(c.effect, c.validation.rms_pct, c.reason) for c in result.candidates]
    assert result.effects == [effect], "nothing more is added once the effect is in"
    assert result.before.rms_pct > 3.0 * floor  # the effect mattered to the plain GPI
    assert result.after.rms_pct <= FLOOR_FACTOR * floor
    for name, truth in case.truth.items():
        assert result.parameters[name] == pytest.approx(truth, rel=PARAMETER_TOLERANCE)


def test_diagnose_adds_a_second_effect_in_a_later_round():
    case, result = diagnosed("thermal_lag+drift")
    rounds = [(found.winner.effect if found.winner else None, [(c.effect, c.reason) for c in found.candidates])
              for found in result.rounds]
    assert sorted(result.effects) == ["drift", "thermal_lag"], rounds
    assert result.effect == result.effects[0]
    assert result.after.rms_pct <= FLOOR_FACTOR * case.validation.noise_floor_pct
    assert result.rounds[1].before.rms_pct <= result.rounds[0].winner.validation.rms_pct, "the count step only helps"
    assert result.after.rms_pct < result.rounds[1].before.rms_pct
    assert result.parameters["tau_s"] == pytest.approx(case.truth["tau_s"], rel=PARAMETER_TOLERANCE)
    assert result.parameters["drift_m_per_s"] == pytest.approx(case.truth["drift_m_per_s"], rel=0.1)
    t, u = case.validation.t, case.validation.u
    start = result.starts["validation"].start
    assert np.array_equal(result.chain.model.predict_from(t, u, start), result.validation_predicted_after)
    block = result.to_dict()
    assert block["effects"] == result.effects and [r["added"] for r in block["rounds"]][:2] == result.effects


def test_candidates_are_judged_on_the_validation_record_they_predict_worst():
    """others: each candidate's validation errors are those of the record it predicts worst (a record of a stage
    with a delay instead of a lag, run from rest, beside the held-out one), and it is judged on them."""
    case, other = make_case("thermal_lag", seed=SEED), make_case("delay", seed=SEED + 1)
    ident, valid, second = case.identification, case.validation, other.validation
    result = diagnose((ident.t, ident.u, ident.y), (valid.t, valid.u, valid.y), max_rounds=1, operators=5,
                      others=((second.t, second.u, second.y),))
    validation = Validation(valid.t, valid.u, valid.y)
    worse_elsewhere = []
    for candidate in result.candidates:
        model, start = candidate.model.model, candidate.model.start
        held_out = validation.errors(validation.predict(model, start).predicted).rms_pct
        from_rest = error_metrics(second.y, model.without_state().predict(second.t, second.u)).rms_pct
        assert candidate.validation.rms_pct == pytest.approx(max(held_out, from_rest), rel=1e-12)
        worse_elsewhere.append(from_rest > held_out)
    assert all(worse_elsewhere), "the record of the other stage is the worst for every candidate"
    rate = next(candidate for candidate in result.candidates if candidate.effect == "rate")
    assert not rate.accepted and f"{rate.validation.rms_pct:.3g} % is not below" in rate.reason


def test_candidates_fitted_in_worker_processes_give_the_same_diagnosis():
    case, serial = diagnosed("thermal_lag+drift")
    ident, valid = case.identification, case.validation
    parallel = diagnose((ident.t, ident.u, ident.y), (valid.t, valid.u, valid.y), workers=2)

    def outcome(result) -> list:
        return [[(c.effect, c.parameters, c.validation, c.delta_bic, c.accepted, c.reason) for c in found.candidates]
                + [sorted(found.failures.items())] for found in result.rounds]

    assert parallel.effects == serial.effects and parallel.parameters == serial.parameters
    assert parallel.after == serial.after
    assert outcome(parallel) == outcome(serial)
    assert parallel.chain.model == serial.chain.model


def test_workers_must_be_a_positive_whole_number():
    case, _ = diagnosed("none")
    ident, valid = case.identification, case.validation
    for bad in (0, -1, 1.5, True):
        with pytest.raises(InputError, match="workers must be a positive integer"):
            diagnose((ident.t, ident.u, ident.y), (valid.t, valid.u, valid.y), workers=bad)


def test_workers_started_in_the_background_answer_in_order_and_close():
    """start() launches the worker processes without waiting; run() waits for them and keeps the jobs'
    order; close() stops them, also when no job was run."""
    with Workers(2) as pool:
        pool.start()
        assert pool.run(divmod, [(7, 2), (9, 4), (5, 5)], None, "{}") == [(3, 1), (2, 1), (1, 0)]
    assert pool._executor is None and pool._starting is None
    unused = Workers(2)
    unused.start()
    unused.close()
    assert unused._executor is None and unused._starting is None


START_METHOD_SCRIPT = """
import os, signal, sys, threading
from sma_stage.identify.workers import Workers


def parent(_):
    return os.getppid()


def ended_by_sigterm(_):
    return signal.getsignal(signal.SIGTERM) == signal.SIG_DFL


if __name__ == "__main__":
    if sys.argv[1] == "beside-a-thread":
        threading.Thread(target=threading.Event().wait, daemon=True).start()
    signal.signal(signal.SIGTERM, lambda *_: None)  # gpi_tool's raises Terminated
    with Workers(2) as pool:
        parents = set(pool.run(parent, [(1,), (2,)], None, "{}"))
        print("forked" if parents == {os.getpid()} else "forkserver", all(pool.run(ended_by_sigterm, [(1,), (2,)],
              None, "{}")), pool.run(divmod, [(7, 2), (9, 4)], None, "{}"))
"""


@pytest.mark.parametrize("where, started", [("alone", "forked"), ("beside-a-thread", "forkserver")])
def test_workers_are_forked_only_from_a_process_with_no_other_thread(tmp_path, where, started):
    """gpi_tool forks its workers (no forkserver to start: about 2 s of CPU); a process with other threads (a ROS
    node) starts them from a forkserver, where no other thread's lock is copied into them. Either way SIGTERM
    ends a worker (a forked one that kept gpi_tool's handler raised instead, and a terminated pool could hang)."""
    import subprocess
    import sys

    script = tmp_path / "start_method.py"
    script.write_text(START_METHOD_SCRIPT)
    ran = subprocess.run([sys.executable, str(script), where], capture_output=True, text=True, timeout=120)
    assert ran.returncode == 0 and ran.stdout.split() == [started, "True", "[(3,", "1),", "(2,", "1)]"], ran.stderr


def _niceness(_: int, progress=None) -> int:
    return os.getpriority(os.PRIO_PROCESS, 0)


@pytest.mark.parametrize("niceness", [None, 3, 0])
def test_worker_processes_run_niceness_levels_below_their_parent(niceness):
    """A refit's workers yield the CPU to a stage on the same computer (bench/bench_long_refit.py): 10 levels
    below their parent unless told otherwise, at its priority with 0."""
    pool = Workers(2) if niceness is None else Workers(2, niceness=niceness)
    with pool:
        levels = set(pool.run(_niceness, [(1,), (2,)], None, "{}"))
    assert levels == {min(os.getpriority(os.PRIO_PROCESS, 0) + (10 if niceness is None else niceness), 19)}


@pytest.mark.parametrize("niceness", [-1, 20, 2.5, True, "10"])
def test_a_niceness_out_of_range_is_refused_in_one_line(niceness):
    with pytest.raises(InputError, match=r"^niceness must be an integer from 0 to 19, got .*$"):
        Workers(2, niceness=niceness)


def test_workers_that_cannot_start_give_a_one_line_error(monkeypatch):
    def no_processes(*args, **kwargs):
        raise OSError("[Errno 24] Too many open files")

    monkeypatch.setattr(workers_module, "ProcessPoolExecutor", no_processes)
    with Workers(2) as pool, pytest.raises(InputError, match=r"could not be started \(\[Errno 24\] Too many open"):
        pool.run(divmod, [(7, 2), (9, 4)], None, "{}")


def test_diagnose_answers_none_when_the_gpi_suffices():
    case, result = diagnosed("none")
    assert result.effect == "none", [(c.effect, c.delta_bic, c.validation.rms_pct) for c in result.candidates]
    assert result.effects == [] and len(result.rounds) == 1
    assert result.parameters == {}
    assert result.after.rms_pct <= FLOOR_FACTOR * case.validation.noise_floor_pct
    assert result.before.rms_pct <= FLOOR_FACTOR * case.validation.noise_floor_pct
    assert {c.effect for c in result.candidates} | set(result.failures) == set(EFFECT_NAMES)
    assert not any(c.accepted for c in result.candidates)


def test_diagnosis_block_follows_the_json_contract():
    _, result = diagnosed("delay")
    block = json.loads(json.dumps(result.to_dict()))
    assert block["effect"] == "delay"
    assert set(block["evidence"]) == set(TEST_NAMES)
    assert all(isinstance(text, str) and ("band" in text or "chi2" in text) for text in block["evidence"].values())
    assert set(block["parameters"]) == {"delay_s"}
    for side in ("before", "after"):
        assert set(block[side]["validation"]) == {"rms_pct", "max_pct"}
    assert block["after"]["validation"]["rms_pct"] < block["before"]["validation"]["rms_pct"]
    assert [c["effect"] for c in block["candidates"]] == [c.effect for c in result.candidates]
    assert sum(c["accepted"] for c in block["candidates"]) >= 1


def test_diagnosis_shows_the_residual_whitened_by_the_effect():
    _, result = diagnosed("thermal_lag")
    assert not result.tests_before.checks["whiteness"].passed
    after, before = result.tests_after.checks["whiteness"], result.tests_before.checks["whiteness"]
    assert after.value < 0.05 * before.value


def test_diagnose_refuses_bad_records_with_one_line():
    case = make_case("none", seed=SEED, duration_s=100.0)
    ident, valid = case.identification, case.validation
    bad_y = valid.y.copy()
    bad_y[5] = np.nan
    with pytest.raises(InputError, match="validation"):
        diagnose((ident.t, ident.u, ident.y), (valid.t, valid.u, bad_y))
    with pytest.raises(InputError, match="identification"):
        diagnose((ident.t, ident.u[:-1], ident.y), (valid.t, valid.u, valid.y))
    with pytest.raises(InputError):
        diagnose("not a record", (valid.t, valid.u, valid.y))


# ---- the residual tests ---------------------------------------------------------------------------


def smooth_input(n, seed, dt=1.0):
    """A band-limited random current [A] (a few minutes' correlation time) sampled every dt seconds."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    frequencies = rng.uniform(0.002, 0.02, 6)
    phases = rng.uniform(0.0, 2.0 * np.pi, 6)
    return t, np.sum(np.sin(2.0 * np.pi * np.outer(t, frequencies) + phases), axis=1)


def test_white_residual_passes_whiteness_at_its_nominal_rate():
    rng = np.random.default_rng(1)
    t, u = smooth_input(500, seed=1)
    failures = [not residual_tests(rng.normal(0.0, 1e-6, t.size), u, t).checks["whiteness"].passed
                for _ in range(200)]
    assert 0.01 <= np.mean(failures) <= 0.10  # 95 % band: about 5 % false alarms


def test_white_residual_passes_every_test():
    t, u = smooth_input(1000, seed=2)
    passes = [residual_tests(np.random.default_rng(seed).normal(0.0, 1e-6, t.size), u, t).passed
              for seed in range(40)]
    assert np.mean(passes) >= 0.65  # five tests at 95 % (the lagged one Bonferroni-widened): ~80 % pass all


@pytest.mark.parametrize("lag_samples", [7, -4])
def test_lagged_copy_of_the_input_is_found_at_its_lag(lag_samples):
    dt = 0.5
    t, u = smooth_input(1200, seed=3, dt=dt)
    e = 1e-6 * np.roll(u, lag_samples) + np.random.default_rng(4).normal(0.0, 1e-7, t.size)
    checks = residual_tests(e[50:-50], u[50:-50], t[50:-50]).checks
    assert not checks["lagged_input"].passed
    assert checks["lagged_input"].lag_s == pytest.approx(lag_samples * dt)
    assert checks["lagged_input"].value > 0.9


def test_trend_and_rate_are_seen_by_their_own_tests():
    t, u = smooth_input(1000, seed=5)
    noise = np.random.default_rng(6).normal(0.0, 1e-6, t.size)
    trend = residual_tests(noise + 2e-9 * t, u, t).checks
    rate = residual_tests(noise - 2e-4 * np.gradient(u, t), u, t).checks
    assert not trend["time"].passed and trend["time"].value > 0
    assert not rate["input_rate"].passed and rate["input_rate"].value < 0
    assert trend["time"].ratio > trend["input_rate"].ratio
    assert rate["input_rate"].ratio > rate["time"].ratio


def test_residual_tests_refuse_bad_input():
    t, u = smooth_input(100, seed=0)
    with pytest.raises(InputError):
        residual_tests(np.zeros(99), u, t)
    with pytest.raises(InputError):
        residual_tests(np.full(100, np.nan), u, t)
    with pytest.raises(InputError):
        residual_tests(np.zeros(100), u, t[::-1])


# ---- the effect models ----------------------------------------------------------------------------


def test_lagged_input_solves_the_first_order_lag():
    tau, omega = 20.0, 2.0 * np.pi / 250.0
    t = np.linspace(0.0, 600.0, 1201)
    u = np.sin(omega * t)
    phase = omega * tau
    exact = (np.sin(omega * t) - phase * np.cos(omega * t) + phase * np.exp(-t / tau)) / (1.0 + phase**2)
    assert np.max(np.abs(lagged_input(t, u, tau) - exact)) < 1e-4


def test_delayed_input_is_exact_on_a_ramp_and_starts_idle():
    """The current is switched on one sample period (0.5 s) before the first sample, held at u[0]."""
    t = np.arange(0.0, 50.0, 0.5)
    u = 0.2 * t + 1.0
    shifted = delayed_input(t, u, 3.3)
    late, held, idle = t >= 3.3, (t >= 2.8) & (t < 3.3), t < 2.8
    assert np.allclose(shifted[late], 0.2 * (t[late] - 3.3) + 1.0)
    assert np.all(shifted[held] == u[0])
    assert np.all(shifted[idle] == 0.0)
    assert np.allclose(delayed_input(t, u, 1e-9), u, rtol=0, atol=1e-9)  # no delay, no start-up effect


def test_lagged_input_starts_from_an_idle_stage():
    t = np.arange(0.0, 100.0, 0.5)
    step = lagged_input(t, np.full(t.size, 2.0), 10.0)
    assert np.allclose(step, 2.0 * (1.0 - np.exp(-(t + 0.5) / 10.0)))
    assert np.allclose(lagged_input(t, np.sin(t / 10.0) + 1.0, 1e-6), np.sin(t / 10.0) + 1.0, atol=1e-6)


def test_rate_model_without_rate_gain_is_the_gpi():
    t = np.arange(0.0, 500.0, 1.0)
    u = 4.0 * np.sin(2.0 * np.pi * t / 250.0)
    plain = forward(u, TRUE_PARAMETERS, TRUE_OPERATORS)
    theta = TRUE_PARAMETERS.as_array()
    assert np.allclose(rate_forward(u, input_rate(t, u), theta, TRUE_OPERATORS, 0.0)[0], plain, rtol=0, atol=1e-12)
    wider = rate_forward(u, input_rate(t, u), theta, TRUE_OPERATORS, 5.0)[0]
    rising = np.gradient(u) > 0
    assert np.mean(wider[rising] - plain[rising]) < 0 < np.mean(wider[~rising] - plain[~rising])


@pytest.mark.parametrize("effect", ["none", "thermal_lag", "delay", "rate"])
def test_effect_models_reproduce_the_independent_plant_simulation(effect):
    """With the true parameters, the effect models (sampled at 1 Hz) match the plant simulated 10x finer
    by test/synthetic.py to well under the noise: the test data are fair to the identification."""
    case = make_case(effect, seed=0)
    value = next(iter(case.truth.values()), 0.0)
    for record in (case.identification, case.validation):
        t, u = record.t, record.u
        drive = {"thermal_lag": lagged_input(t, u, value) if effect == "thermal_lag" else u,
                 "delay": delayed_input(t, u, value)}.get(effect, u)
        model = (rate_model_output(t, u, TRUE_PARAMETERS, TRUE_OPERATORS, value) if effect == "rate"
                 else forward(drive, TRUE_PARAMETERS, TRUE_OPERATORS))
        assert np.sqrt(np.mean((model - record.clean) ** 2)) < 0.5 * record.noise_sigma_m


def test_a_candidate_that_cannot_be_fitted_is_reported_not_fatal(monkeypatch):
    import sma_stage.identify.diagnosis as diagnosis_module

    real_fit_effect = diagnosis_module.fit_effect

    def failing_rate(name, *args, **kwargs):
        if name == "rate":
            raise InputError("rate: the GPI cannot be fitted")
        return real_fit_effect(name, *args, **kwargs)

    monkeypatch.setattr(diagnosis_module, "fit_effect", failing_rate)
    case = make_case("drift", seed=SEED, duration_s=300.0)
    ident, valid = case.identification, case.validation
    result = diagnose((ident.t, ident.u, ident.y), (valid.t, valid.u, valid.y))
    assert result.effect == "drift"
    assert "rate" not in {c.effect for c in result.candidates}
    reported = [entry for entry in result.to_dict()["candidates"] if entry["effect"] == "rate"]
    assert reported == [{"effect": "rate", "fitted": False, "accepted": False,
                         "reason": "not fitted: rate: the GPI cannot be fitted"}]


def test_a_numerical_failure_inside_a_candidate_is_reported_not_fatal(monkeypatch):
    from sma_stage.identify.effects import drift as drift_module

    def overflowing(*args, **kwargs):
        raise ValueError("min() arg is an empty sequence")

    monkeypatch.setattr(drift_module.DriftEffect, "fit", overflowing)
    case = make_case("none", seed=SEED, duration_s=300.0)
    ident, valid = case.identification, case.validation
    result = diagnose((ident.t, ident.u, ident.y), (valid.t, valid.u, valid.y), max_rounds=1)
    assert result.failures["drift"] == "drift: min() arg is an empty sequence"
    assert {c.effect for c in result.candidates} | set(result.failures) == set(EFFECT_NAMES)
    assert "drift" not in {c.effect for c in result.candidates}


def test_a_recording_whose_creep_fit_fails_is_diagnosed_with_every_candidate():
    """The end-to-end test's recording (1 Hz, starting mid-excitation) on which the creep term of the drift
    candidate could be fitted neither warm nor cold: diagnose raised ValueError from min() of no fits."""
    series = read_csv(Path(__file__).parent / "data" / "refit_drift_unfittable.csv", min_samples=60)
    ident, _ = series.split(0.75)
    base = fit_gpi(ident.input, ident.output, operators=5)
    result = diagnose(ident, series, base=base, operators=5, max_rounds=1, scored_from=len(ident))
    fitted = {candidate.effect for candidate in result.candidates}
    assert fitted | set(result.failures) == set(EFFECT_NAMES)
    drift = next(candidate for candidate in result.candidates if candidate.effect == "drift")
    assert set(drift.parameters) == {"drift_m_per_s"}, "the linear drift kept where the creep cannot be fitted"


def test_residual_tests_serialise_to_json():
    t, u = smooth_input(300, seed=8)
    tests = residual_tests(np.random.default_rng(9).normal(0.0, 1e-6, t.size) + 1e-9 * t, u, t)
    document = json.loads(json.dumps(tests.to_dict()))
    assert set(document) == set(TEST_NAMES)
    assert all(isinstance(entry["passed"], bool) for entry in document.values())
    assert document["lagged_input"]["threshold"] > document["input"]["threshold"]


def test_scored_from_counts_the_validation_errors_from_that_sample():
    case, _ = diagnosed("none")
    ident, valid = case.identification, case.validation
    result = diagnose((ident.t, ident.u, ident.y), (valid.t, valid.u, valid.y), scored_from=600, max_rounds=1)
    predicted = predict(result.base, valid.u)
    assert result.before == error_metrics(valid.y[600:], predicted[600:])
    assert np.array_equal(result.validation_predicted_before, predicted), "the model ran over the whole record"
    with pytest.raises(InputError) as excinfo:
        diagnose((ident.t, ident.u, ident.y), (valid.t, valid.u, valid.y), scored_from=valid.t.size - 2)
    assert "scored_from" in str(excinfo.value)


def test_a_rate_search_step_that_overflows_the_shape_costs_the_whole_output_without_a_warning():
    """gpi_tool diagnose printed numpy's "invalid value encountered in matmul" when the rate search stepped to
    densities that overflow; such a step now predicts nothing (a10 = 0), a finite cost the search moves away from."""
    import warnings

    from sma_stage.identify.effects.rate import _rate_projection

    u = np.linspace(-5.0, 5.0, 101)
    y = np.tanh(u[1:])
    values = np.array([1.0, 1.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.1, 1.0, -800.0])  # exp(800 r) overflows
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        a10, cost, residual = _rate_projection(values, 1.0, u, np.gradient(u), y, 10, "multiplicative")
    assert a10 == 0.0 and cost == pytest.approx(float(y @ y)) and np.all(np.isfinite(residual))
