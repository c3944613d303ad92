"""The two-wire model family: forward from rest and from a carried state, the stream, the exact inverse one
sample at a time, the model file, and identification on the second physical stage (test/antagonistic_plant.py),
which the model's code did not make."""

import copy

import numpy as np
import pytest
from antagonistic_plant import VARIANTS, records, third_record
from threadpoolctl import threadpool_limits

from sma_stage.errors import InputError
from sma_stage.identify.fit import fit_gpi, predict
from sma_stage.identify.metrics import error_metrics
from sma_stage.identify.two_wire import HeldOut, TwoWireFitting, fit_two_wire
from sma_stage.identify.workers import Workers
from sma_stage.model.two_wire import KEEP_TOLERANCE, TwoWireModel, TwoWireParameters

SPAN_M = 6e-4


def example_model(wire_operators: int = 3, output_operators: int = 3, **changes: float) -> TwoWireModel:
    """A model with the magnitudes identification finds on the antagonistic stage (output in m); `changes` replace
    some of its scalar parameters."""
    values = {"tau_a_s": 4.0, "tau_b_s": 3.5, "heating_reference_a": 5.0, "coupling_a": 3800.0,
              "coupling_b": 4000.0, "centre_a": 1.6, "centre_b": 1.7, "width_a": 1.2, "width_b": 1.1,
              "hysteresis_a": 0.6, "hysteresis_b": 0.9, "stroke_a": 4e-4, "stroke_b": 3.5e-4, "offset": 1e-5,
              "output_threshold": 8e-5, "resistance_drop": 0.3, "tension_coupling": 0.4, **changes}
    return TwoWireModel(TwoWireParameters(values, tuple(np.linspace(0.1, 0.5, wire_operators)),
                                          tuple(np.linspace(0.4, 0.2, wire_operators)),
                                          tuple(np.linspace(0.7, 0.1, output_operators))))


def excitation(samples: int = 1500, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Uneven sample times [s] and a current [A] of both signs, up to 5 A."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.1, 0.3, samples))
    return t, 5.0 * np.sin(2 * np.pi * t / 90.0) * (0.4 + 0.6 * rng.random(samples) ** 0.3)


def test_the_output_rises_with_the_current_at_every_step():
    """The exact inverse rests on it: held over a step, more current (less on wire b, more on wire a) never
    lowers the output."""
    model, (_, u) = example_model(), excitation(300)
    stream = model.stream()
    for current in u:
        state = stream._state.copy()
        ends = []
        for trial in np.linspace(-5.0, 5.0, 41):
            stream._state[:] = state
            ends.append(stream.step(trial, 0.2))
        assert np.all(np.diff(ends) >= -1e-18)
        stream._state[:] = state
        stream.step(current, 0.2)


def test_a_record_continued_from_its_carried_state_matches_the_whole():
    model, (t, u) = example_model(), excitation()
    whole = model.predict(t, u)
    first, state = model.run(t[:700], u[:700])
    second = model.predict(t[700:], u[700:], state)
    np.testing.assert_allclose(np.r_[first, second], whole, rtol=0, atol=1e-15)
    assert np.ptp(whole) > 0.5 * SPAN_M


def test_the_stream_follows_the_record():
    model, (t, u) = example_model(), excitation(400)
    stream = model.stream()
    outputs = [stream.output] + [stream.step(current, step) for current, step in zip(u[:-1], np.diff(t), strict=True)]
    np.testing.assert_allclose(outputs, model.predict(t, u), rtol=0, atol=1e-15)


@pytest.mark.parametrize(("hold_s", "tolerance_pct"), [(1.6, 5.0), (20.0, 1.0), (120.0, 1.0)])
def test_a_long_hold_is_what_the_same_hold_sampled_gives(hold_s, tolerance_pct):
    """The inverse holds a current over the lead's horizon (1.6 s at lead 3, 30 time constants with none) and the
    reach is a 30-time-constant hold: in one step the position's pull and the heating's fall stay where the hold
    began (9 % and 32 % of the span off here); the hold in sub-steps stays near the same hold in 0.2 s steps."""
    model = example_model(4, 5)
    span = model.stream().step(5.0, 200.0) - model.stream().step(-5.0, 200.0)
    for current in np.linspace(-5.0, 5.0, 21):
        sampled = model.stream()
        for _ in range(int(round(hold_s / 0.2))):
            end = sampled.step(current, 0.2)
        assert abs(model.stream().step(current, hold_s) - end) <= tolerance_pct / 100 * span


def test_a_hold_of_no_finite_length_ends():
    """The sub-steps count down a finite hold; an infinite one is one step (settled), and so is a NaN one (its
    temperature NaN), where counting down would never end."""
    assert np.isfinite(example_model().stream().step(3.0, float("inf")))
    stream = example_model().stream()
    stream.step(3.0, float("nan"))
    assert np.isnan(stream.temperatures[0])


def test_a_slow_wire_holds_in_at_most_so_many_sub_steps():
    """A wire of 500 s (the fit's bound) settles over 1500 s, taken in 30 sub-steps of 50 s (not 1500 of 1 s, a
    cost per inverse trial): the hold still ends within 1 % of the span of where 1 s steps take it."""
    model = example_model(tau_a_s=500.0, tau_b_s=450.0)
    span = model.stream().step(5.0, 2e4) - model.stream().step(-5.0, 2e4)
    sampled = model.stream()
    for _ in range(3000):
        end = sampled.step(4.0, 1.0)
    assert abs(model.stream().step(4.0, 3000.0) - end) <= 0.01 * span


def keep_band(model: TwoWireModel) -> float:
    """How near a target [m] the last command may leave the output (KEEP_TOLERANCE of the strokes and offset)."""
    values = model.parameters.values
    return KEEP_TOLERANCE * (abs(values["stroke_a"]) + abs(values["stroke_b"]) + abs(values["offset"]))


def test_the_exact_inverse_round_trips_reachable_targets():
    """Targets the model reached under some current: the inverse, one sample at a time, reaches each within the band
    its last command may stay in (KEEP_TOLERANCE of the strokes, 0.02 % of this record's span), but with a command at
    the current limit (the band's lag can leave a steep target beyond it)."""
    model, (t, u) = example_model(), excitation(800)
    targets = model.predict(t, u)
    stream = model.stream(max_current_a=5.0)
    reached, commands = [stream.output], [0.0]
    for target, step in zip(targets[1:], np.diff(t), strict=True):
        commands.append(stream.command_for(target, step))
        reached.append(stream.output)
    at_the_limit = np.abs(commands) == 5.0
    misses = np.abs(np.array(reached) - targets)[~at_the_limit]
    assert np.max(misses) <= 1.000001 * keep_band(model)


def test_an_unreachable_target_gets_the_current_limit():
    stream = example_model().stream(max_current_a=5.0)
    assert stream.command_for(1.0, 0.2) == 5.0
    assert stream.command_for(-1.0, 0.2) == -5.0


def test_the_inverse_from_the_last_command_answers_as_the_search_over_the_whole_range():
    """current_for seeks its bracket from its last answer first; the answer is the one found from the range's ends (a
    fresh stream: no last answer) for the near edge of the band the last answer may stay in (the target moved
    KEEP_TOLERANCE of the strokes towards where the last answer leaves the output), near the last one, far from it
    and beyond reach either way."""
    model, (t, u) = example_model(), excitation(800)
    outputs, state = model.run(t[:400], u[:400])
    low, high = float(np.min(outputs)), float(np.max(outputs))
    stream = model.stream(state, max_current_a=5.0)
    last = stream.current_for(0.5 * (low + high), 0.2)
    for target in (0.5 * (low + high) + 1e-3 * (high - low), low + 0.1 * (high - low), high - 0.05 * (high - low),
                   high + 10.0 * (high - low), 0.5 * (low + high), low - 10.0 * (high - low)):
        left_at = model.stream(state, max_current_a=5.0).step(last, 0.2)
        fresh = model.stream(state, max_current_a=5.0)
        expected = fresh.current_for(target + np.sign(left_at - target) * keep_band(model), 0.2)
        last = stream.current_for(target, 0.2)
        assert last == pytest.approx(expected, abs=1e-9)
        assert stream.last_clipped == fresh.last_clipped
    assert stream.last_clipped == -1  # the last target is beyond reach below


def test_the_inverse_keeps_its_last_current_for_a_target_a_hair_off_where_the_output_is_flat():
    """Wire a heated, then cooled back to 1 A through its hysteresis: held 1 s, 0.5 A more moves the output 10 nm. A
    target 30 nm above, within the band of KEEP_TOLERANCE of the strokes (76 nm), keeps the last current, where the
    exact answer was 2.05 A (1.07 A for 1 nm); 300 nm above, the answer brings the output to the band's near edge."""
    model = example_model(width_a=0.48, width_b=0.48, hysteresis_a=0.9, hysteresis_b=0.9)
    stream = model.stream(max_current_a=5.0)
    stream.step(5.0, 60.0)
    output = stream.step(1.0, 120.0)
    assert copy.deepcopy(stream).step(1.5, 1.0) - output < 2e-8  # flat above 1 A
    holding = stream.current_for(output, 1.0)
    assert holding == pytest.approx(1.0, abs=1e-6)
    for off_m in (1e-9, -1e-9, 3e-8, -3e-8):
        assert stream.current_for(output + off_m, 1.0) == holding
    stream.current_for(output, 1.0)
    current = stream.current_for(output + 3e-7, 1.0)
    reached = copy.deepcopy(stream).step(current, 1.0)
    assert reached == pytest.approx(output + 3e-7 - keep_band(model), abs=1e-12)


def test_the_model_file_round_trips(tmp_path):
    model, (t, u) = example_model(4, 5), excitation()
    _, state = model.run(t, u)
    carried = TwoWireModel(model.parameters, "m", state, {"note": "test"})
    carried.save(tmp_path / "two_wire.yaml")
    from sma_stage.model.kinds import load_any_model_file

    loaded = load_any_model_file(tmp_path / "two_wire.yaml")
    assert isinstance(loaded, TwoWireModel) and loaded.metadata == {"note": "test"}
    np.testing.assert_allclose(loaded.parameters.as_array(), model.parameters.as_array(), rtol=1e-12, atol=0)
    t_next, u_next = t[-1] + np.cumsum(np.full(200, 0.2)), 3.0 * np.cos(np.arange(200) / 20.0)
    np.testing.assert_allclose(loaded.predict(t_next, u_next, loaded.state),
                               carried.predict(t_next, u_next, carried.state), rtol=0, atol=1e-12 * SPAN_M)


@pytest.mark.parametrize(("change", "message"), [
    (lambda d: d["parameters"].update(weights_a=[0.1, -0.2, 0.3]), "weights_a must be >= 0"),
    (lambda d: d["parameters"].pop("tau_a_s"), "missing: tau_a_s"),
    (lambda d: d["parameters"].update(tau_b_s=0.0), "tau_b_s must be > 0"),
    (lambda d: d["parameters"].update(width_a=float("nan")), "width_a must be a finite number"),
    (lambda d: d["parameters"].update(stroke_a=-1e-4), "stroke_a must be >= 0"),
    (lambda d: d["parameters"].update(resistance_drop=1.0), "resistance_drop must be < 1"),
    (lambda d: d["parameters"].update(compact_onset=0.5), "compact_onset must be 0 \\(tanh\\) or 1"),
    (lambda d: d.update(extra=1), "unknown key 'extra'"),
    (lambda d: d.update(state={"time_s": 0.0, "current_a": 0.0, "values": [0.0]}), "state holds 1 values"),
])
def test_a_bad_model_file_is_refused_in_one_line(tmp_path, change, message):
    import yaml

    from sma_stage.model.kinds import load_any_model_file

    document = example_model().to_dict()
    change(document)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(document))
    with pytest.raises(InputError, match=message) as raised:
        load_any_model_file(path)
    assert "\n" not in str(raised.value)


@pytest.mark.parametrize("name", ["resistance_drop", "tension_coupling", "compact_onset"])
def test_a_model_file_written_before_a_parameter_existed_reads_as_one_without_it(tmp_path, name):
    """Model files of the two-wire family from before `resistance_drop` (the heating independent of the
    transformation), `tension_coupling` (each wire blind to the other's transformation) or `compact_onset` (the
    tanh transformation curve) existed load with the parameter 0 and predict as they did."""
    import yaml

    from sma_stage.model.kinds import load_any_model_file

    document = example_model(compact_onset=1.0).to_dict()
    document["parameters"].pop(name)
    (tmp_path / "older.yaml").write_text(yaml.safe_dump(document))
    loaded = load_any_model_file(tmp_path / "older.yaml")
    assert loaded.parameters.values[name] == 0.0
    values = {**example_model(compact_onset=1.0).parameters.values, name: 0.0}
    assert loaded.parameters.values == values
    t, u = excitation(400)
    with_it = example_model(compact_onset=1.0).predict(t, u)
    without = loaded.predict(t, u)
    assert np.max(np.abs(with_it - without)) > 0.005 * np.ptp(with_it), "the parameter changes the output"


def test_a_compact_onset_leaves_a_wire_heated_below_its_transformation_where_it_was():
    """With compact_onset 1 a wire heated to a temperature seen more than 1.5 widths below its centre does not
    move the stage at all, as a wire below its transformation start does not; tanh's tail moves it a little.
    The stage held 60 s at 0 A, then 60 s at a current heating wire a to 2 widths below its centre."""
    centre, width = 1.6, 0.2
    current = float(np.sqrt((centre - 2.0 * width) * 5.0))  # theta = u^2 / heating_reference, 5 A
    t = np.arange(0.0, 120.0, 0.2)
    u = np.where(t < 60.0, 0.0, current)
    moved = {}
    for compact in (0.0, 1.0):
        model = example_model(centre_a=centre, width_a=width, width_b=width, coupling_a=0.0, coupling_b=0.0,
                              tension_coupling=0.0, compact_onset=compact)
        y = model.predict(t, u)
        moved[compact] = abs(y[-1] - y[np.searchsorted(t, 59.0)])
    assert moved[1.0] == 0.0
    assert moved[0.0] > 1e-3 * 4e-4, "tanh's tail moves the stage a little"


def test_the_gpi_model_file_still_reads_as_a_gpi(tmp_path):
    from sma_stage.model.identified import IdentifiedModel, load_model_file
    from sma_stage.model.kinds import load_any_model_file
    from sma_stage.model.parameters import GPIParameters

    gpi = IdentifiedModel(GPIParameters(*np.linspace(0.1, 1.1, 11)), 5)
    gpi.save(tmp_path / "gpi.yaml")
    assert load_any_model_file(tmp_path / "gpi.yaml") == gpi
    example_model().save(tmp_path / "two_wire.yaml")
    with pytest.raises(InputError, match="model kind 'two_wire' is not supported"):
        load_model_file(tmp_path / "two_wire.yaml")


@pytest.mark.parametrize(("script", "arguments", "message"), [
    ("test/antagonistic_plant.py", ["--variants", "nope"], "unknown variant 'nope'"),
    ("test/antagonistic_plant.py", ["--alternatives", "--seeds", "0,x"], "--seeds must be comma-separated integers"),
    ("test/antagonistic_plant.py", ["--alternatives", "--shapes", "odd"], "--shapes must be among"),
    ("test/antagonistic_plant.py", ["--alternatives", "--output-operators", "0"],
     "--output-operators must be from 1 to 50"),
    ("bench/bench_sample_period.py", ["--variants", "nope"], "unknown variant 'nope'"),
    ("bench/bench_sample_period.py", ["--seed", "-1"], "--seed must be 0 or more"),
    ("bench/bench_probe_bands.py", ["--plants", "simulator"], "unknown plant 'simulator'"),
    ("bench/bench_exact_model.py", ["--plants", "nope"], "unknown plant 'nope'"),
    ("bench/bench_exact_model.py", ["--shapes", "sine 50 s,odd"], "unknown shape 'odd'"),
    ("bench/bench_exact_model.py", ["--seed", "-1"], "--seed must be 0 or more"),
    ("bench/bench_exact_model.py", ["--workers", "0"], "--workers must be from 1 to 16"),
    ("bench/bench_candidate_laws.py", ["--only", "no such law"], "no candidate law's name holds 'no such law'"),
    ("bench/bench_reachable.py", ["--periods", "50,x"], "--periods must be comma-separated numbers"),
    ("bench/bench_reachable.py", ["--periods", "nan"], "--periods must each be from 5 to 1000 s"),
    ("bench/bench_reachable.py", ["--horizon", "0.5"], "--horizon must be from 1 to 20 s, got 0.5"),
    ("bench/bench_reachable.py", ["--seconds", "nan"], "--seconds must be from 10 to 1000, got nan"),
    ("bench/bench_reachable.py", ["--learnt", "-1"], "--learnt must be from 0 to 50 periods, got -1"),
    ("bench/bench_rounding.py", ["--variants", "nope"], "unknown variant 'nope'"),
    ("bench/bench_rounding.py", ["--copies", "0"], "--copies must be from 1 to 50, got 0"),
    ("bench/bench_rounding.py", ["--eps", "nan"], "--eps must be above 0 and at most 1e-3, got nan"),
    ("bench/bench_rounding.py", ["--record", "designed", "--design-seed", "-1"], "--design-seed must be 0 or more"),
])
def test_the_second_stage_scripts_refuse_bad_arguments_in_one_line(script, arguments, message):
    """The second stage's script and the benchmarks on its plants end in one line, their results files untouched."""
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    results = repo / "bench" / "results" / f"{Path(script).stem.removeprefix('bench_')}.md"
    before = results.read_bytes() if results.exists() else None
    run = subprocess.run([sys.executable, str(repo / script), *arguments], capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and run.stdout == ""
    assert message in run.stderr.strip().splitlines()[-1] and "Traceback" not in run.stderr
    assert (results.read_bytes() if results.exists() else None) == before


@pytest.mark.parametrize(("shapes", "tension", "compact"), [("shared", False, False), ("per_wire", False, False),
                                                           ("shared", True, False), ("per_wire", True, False),
                                                           ("shared", True, True), ("per_wire", False, True)])
def test_the_fit_jacobian_is_the_derivative_of_the_residuals(shapes, tension, compact):
    """The sensitivities carried through the recursion (run_with_sensitivities) against central differences,
    at starts with weak coupling (strong coupling makes the output's sample-to-sample loop amplify rounding,
    and differences then disagree with each other as much as with the derivative). The worst column measured
    5e-5 (a weight whose output play barely moves); a wrong term errs by its whole size."""
    from sma_stage.identify.two_wire import _Problem

    t, u = excitation(600)
    y = example_model().predict(t, u)
    problem = _Problem(t, u, y, 4, 5, shapes, tension, compact)
    assert problem.tie.shape[1] == _Problem(t, u, y, 4, 5, shapes).tie.shape[1] + tension
    assert problem.parameters(problem.random_start(np.random.default_rng(0))).values["compact_onset"] == compact
    rng = np.random.default_rng(2)
    for _ in range(3):
        x = problem.random_start(rng)
        x[np.isin(problem.tie.argmax(axis=0), (2, 3))] *= 0.1  # coupling_a, coupling_b
        jacobian = problem.jacobian(x)
        for column in range(x.size):
            step = 1e-6 * abs(x[column])
            above, below = x.copy(), x.copy()
            above[column] += step
            below[column] -= step
            differences = (problem.residuals(above) - problem.residuals(below)) / (2.0 * step)
            error = np.linalg.norm(jacobian[:, column] - differences)
            assert error <= 2e-4 * np.linalg.norm(differences), (column, error)


def test_a_run_stops_where_its_error_stalls_and_keeps_the_point_it_reached(monkeypatch):
    """A run whose RMS error falls by less than STALL_FRACTION over STALL_ITERATIONS iterations ends there
    (status -2), with the point reached and its cost; with no stall fraction it runs to its tolerance."""
    import sma_stage.identify.two_wire as two_wire

    t, u = excitation(600)
    problem = two_wire._Problem(t, u, example_model().predict(t, u), 4, 5, "shared")
    start = problem.random_start(np.random.default_rng(3))
    free = problem.solve(start, 60, two_wire.SEARCH_TOLERANCE)
    monkeypatch.setattr(two_wire, "STALL_ITERATIONS", 2)
    monkeypatch.setattr(two_wire, "STALL_FRACTION", 1.0)  # any run that has not reached zero error stalls
    stalled = problem.solve(start, 60, two_wire.SEARCH_TOLERANCE)
    assert free.status > 0 and free.nfev > 3
    assert stalled.status == -2 and stalled.nfev <= 4
    assert stalled.cost == pytest.approx(0.5 * np.sum(problem.residuals(stalled.x) ** 2), rel=1e-12)
    assert stalled.cost < 0.5 * np.sum(problem.residuals(start) ** 2)


def test_a_start_whose_run_meets_values_that_are_not_finite_is_passed_over(monkeypatch):
    """scipy refuses a Jacobian that overflowed (ValueError), or a run ends where the error is not finite: that
    run is dropped and the fit made from the others;
    when every run fails the fit is refused in one line (the family's row says why) instead of raising scipy's
    error through the identification."""
    import sma_stage.identify.two_wire as two_wire

    t, u = excitation(600)
    y = example_model().predict(t, u)
    solve, runs = two_wire._Problem.solve, []

    def every_other_fails(problem, start, evaluations, tolerance=1e-8):
        runs.append(evaluations)
        if len(runs) % 4 == 1:
            raise ValueError("array must not contain infs or NaNs")
        found = solve(problem, start, evaluations, tolerance)
        if len(runs) % 4 == 3:  # or ends at a point whose error is not finite
            found.cost, found.x = np.nan, np.full_like(found.x, np.nan)
        return found

    monkeypatch.setattr(two_wire._Problem, "solve", every_other_fails)
    found = fit_two_wire(t, u, y, starts=4)
    assert len(runs) == 4 + 2  # four starts searched, two of them failing; the two leaders' polishes, one failing
    assert found.evaluations > 0 and np.all(np.isfinite(found.model.predict(t, u)))
    assert np.isfinite(found.errors.rms_pct) and np.isfinite(found.bic)
    monkeypatch.setattr(two_wire._Problem, "solve", lambda *args: (_ for _ in ()).throw(ValueError("inf")))
    with pytest.raises(InputError, match="the two-wire fit failed: every start's search met values that are not"):
        fit_two_wire(t, u, y, starts=4)


@pytest.mark.parametrize("kept", [True, False])
def test_the_tension_coupling_is_kept_only_when_the_held_out_record_passes_it(monkeypatch, kept):
    """With a held-out record the fit is made with the tension coupling free as well, and the diagnosis's rule
    (judge) decides on that record which stands, saying why; without one the coupling is not fitted."""
    import sma_stage.identify.two_wire as two_wire

    t, u = excitation(600)
    y = example_model().predict(t, u)
    t_held, u_held = excitation(400, seed=5)
    held_out = HeldOut(t_held, u_held, example_model().predict(t_held, u_held))
    verdicts = []

    def rule(delta_bic, validation, before):
        verdicts.append((delta_bic, validation, before))
        return kept, "the rule's reason"

    monkeypatch.setattr(two_wire, "judge", rule)
    found = fit_two_wire(t, u, y, starts=2, held_out=held_out)
    coupling = found.model.parameters.values["tension_coupling"]
    assert len(verdicts) == 1
    _, coupled, without = verdicts[0]
    assert held_out.rms_pct(found.model.without_state()) == pytest.approx((coupled if kept else without).rms_pct)
    assert found.tension == f"tension coupling {'kept' if kept else 'left at 0'}: the rule's reason"
    assert (coupling > 0.0) if kept else (coupling == 0.0)
    assert found.parameter_count == two_wire._Problem(t, u, y, 4, 5, "shared").tie.shape[1] + kept
    plain = fit_two_wire(t, u, y, starts=2)
    assert plain.tension == "" and plain.model.parameters.values["tension_coupling"] == 0.0 and len(verdicts) == 1


def test_the_tension_coupling_is_judged_on_the_held_out_record_predicted_worst(monkeypatch):
    """With further held-out records (HeldOut.others, each from rest) the coupling is judged, as the diagnosis
    judges an effect, on the record each fit predicts worst: here a record whose output is 1.3 times the stage's,
    which no fit predicts within the first record's error."""
    import sma_stage.identify.two_wire as two_wire

    t, u = excitation(600)
    y = example_model().predict(t, u)
    t_held, u_held = excitation(400, seed=5)
    first = (t_held, u_held, example_model().predict(t_held, u_held))
    t_other, u_other = excitation(300, seed=6)
    other = (t_other, u_other, 1.3 * example_model().predict(t_other, u_other))
    verdicts = []

    def rule(delta_bic, validation, before):
        verdicts.append((validation, before))
        return True, "the rule's reason"

    monkeypatch.setattr(two_wire, "judge", rule)
    found = fit_two_wire(t, u, y, starts=2, held_out=HeldOut(*first, others=(other,)))
    (coupled, _), = verdicts
    model = found.model.without_state()
    on_other = error_metrics(other[2], model.predict(other[0], other[1]))
    assert coupled.rms_pct == pytest.approx(on_other.rms_pct) and coupled.max_pct == pytest.approx(on_other.max_pct)
    assert coupled.rms_pct > 2.0 * HeldOut(*first).rms_pct(model)


def test_identification_judges_the_two_wire_fit_on_every_validation_record(monkeypatch):
    """identify_recording's further validation records reach the two-wire fit's held-out records (after the
    first), thinned as the others are."""
    from sma_stage.identify import pipeline
    from sma_stage.io import make_series

    given = []

    def captured(family, ident, output_unit, pool, held_out=None):
        given.append((family, held_out))
        return pipeline.Pending(lambda: (_ for _ in ()).throw(InputError("not fitted here")))

    monkeypatch.setattr(pipeline, "start_held_current_fit", captured)
    t, u = excitation(500)
    records = [make_series(t, u, example_model().predict(t, u), name) for name in ("identification", "validation")]
    t_more, u_more = excitation(300, seed=7)
    more = make_series(t_more, u_more, example_model().predict(t_more, u_more), "more")
    pipeline.identify_recording(records[0], records[1], diagnose_rounds=0, families=("gpi", "two_wire"),
                                more_validation=[more])
    (family, held_out), = given
    assert family == "two_wire" and len(held_out.others) == 1
    np.testing.assert_array_equal(held_out.others[0][0], more.t)
    np.testing.assert_array_equal(held_out.others[0][2], more.output)


def test_a_fit_whose_every_run_with_the_tension_coupling_fails_keeps_the_fit_without_it(monkeypatch):
    """Runs with the coupling free that all meet values that are not finite leave it at 0 and say so; the fit
    without it stands (a family's row is not lost to them)."""
    import sma_stage.identify.two_wire as two_wire

    t, u = excitation(600)
    y = example_model().predict(t, u)
    t_held, u_held = excitation(400, seed=5)
    held_out = HeldOut(t_held, u_held, example_model().predict(t_held, u_held))
    solve = two_wire._Problem.solve

    def coupled_fails(problem, start, evaluations, tolerance=1e-8):
        if problem.tension:
            raise ValueError("array must not contain infs or NaNs")
        return solve(problem, start, evaluations, tolerance)

    monkeypatch.setattr(two_wire._Problem, "solve", coupled_fails)
    found = fit_two_wire(t, u, y, starts=2, held_out=held_out)
    assert found.tension == "tension coupling left at 0: every fit with it met values that are not finite"
    assert found.model.parameters.values["tension_coupling"] == 0.0 and np.isfinite(found.errors.rms_pct)


def test_an_unknown_onset_is_refused_in_one_line():
    t, u = excitation(300)
    with pytest.raises(InputError, match="onset must be one of tanh, compact, got 'sharp'") as raised:
        fit_two_wire(t, u, example_model().predict(t, u), onset="sharp")
    assert "\n" not in str(raised.value)


def test_a_record_heating_one_wire_only_is_refused():
    t = np.arange(0.0, 200.0, 0.2)
    u = 4.0 * np.abs(np.sin(t / 20.0))
    y = 1e-4 * np.tanh(u - 2.0) + 1e-6 * np.sin(t)
    with pytest.raises(InputError, match="needs both wires heated: wire b"):
        fit_two_wire(t, u, y)


@pytest.fixture(scope="module")
def nominal_stage():
    """The paper's identification and validation records of the second physical stage (nominal variant)."""
    return records(VARIANTS["nominal"])


@pytest.fixture(scope="module")
def nominal_fit(nominal_stage):
    """The two-wire model identified on the nominal stage's paper identification record, its starts told apart
    on the validation record (as the diagnosis does), in this process with BLAS on two threads, as a process
    that never limited them has it (the worker processes run it on one: with the fit's jobs run so in this
    process too, the models differed)."""
    with threadpool_limits(2, user_api="blas"):
        return fit_two_wire(*nominal_stage["identification"], held_out=HeldOut(*nominal_stage["validation"]))


def test_the_two_wire_model_identified_on_the_second_stage_validates(nominal_stage, nominal_fit):
    """Identified on the paper's identification signal, validated on the paper's validation signal (each from a
    settled stage): the issue's targets, 2 % RMS and 10 % max (measured: 1.04 % and 3.6 %); the
    plain GPI on the same records is several times worse."""
    t, u, y = nominal_stage["identification"]
    t_valid, u_valid, y_valid = nominal_stage["validation"]
    found = nominal_fit
    validation = error_metrics(y_valid, found.model.without_state().predict(t_valid, u_valid))
    assert found.errors.rms_pct <= 1.5
    assert validation.rms_pct <= 2.0 and validation.max_pct <= 10.0, validation
    plain = fit_gpi(u, y, operators=5)
    plain_validation = error_metrics(y_valid, predict(plain, u_valid))
    assert plain_validation.rms_pct >= 2.0 * validation.rms_pct, (plain_validation, validation)


def test_a_fit_whose_starts_run_in_worker_processes_is_the_fit_made_in_this_process(nominal_stage, nominal_fit):
    """The pool's processes search the starts and polish the leaders (beside a diagnosis): the same model."""
    with Workers(2) as pool:
        fitting = TwoWireFitting(*nominal_stage["identification"], pool=pool,
                                 held_out=HeldOut(*nominal_stage["validation"]))
        found = fitting.result()
    assert found.model == nominal_fit.model and found.evaluations == nominal_fit.evaluations


def test_the_start_chosen_on_held_out_data_also_predicts_a_record_no_choice_saw_better(nominal_stage, nominal_fit):
    """On the nominal stage the paper's identification record fits several starts about as well (within
    START_FIT_MARGIN) that validate differently: told apart on the validation record, the fit also predicts a
    third record (the designed excitation, another draw) better than the best fit of the identification record
    alone (measured: validation 3.01 -> 1.04 %, third record 2.26 -> 1.04 %); the fit told apart also keeps the
    tension coupling there (validation 1.16 -> 1.04 %), which a fit with no held-out record does not fit."""
    stage, made, told_apart = VARIANTS["nominal"], nominal_stage, nominal_fit
    with threadpool_limits(2, user_api="blas"):
        fitted_alone = fit_two_wire(*made["identification"])
    t_third, u_third, y_third = third_record(stage)
    third = {name: error_metrics(y_third, fit.model.without_state().predict(t_third, u_third)).rms_pct
             for name, fit in (("alone", fitted_alone), ("told apart", told_apart))}
    validation = {name: error_metrics(made["validation"][2],
                                      fit.model.without_state().predict(*made["validation"][:2])).rms_pct
                  for name, fit in (("alone", fitted_alone), ("told apart", told_apart))}
    assert told_apart.admitted > 1 and fitted_alone.admitted == 0
    assert told_apart.tension.startswith("tension coupling kept") and fitted_alone.tension == ""
    assert told_apart.model.parameters.values["tension_coupling"] > 0.0
    assert fitted_alone.model.parameters.values["tension_coupling"] == 0.0
    assert validation["told apart"] <= 2.0 < validation["alone"], validation
    assert third["told apart"] <= 0.85 * third["alone"], third


def test_the_family_with_the_lowest_held_out_error_is_chosen_and_bic_parts_near_ties():
    from sma_stage.identify.families import FamilyRow, choose
    from sma_stage.identify.metrics import ErrorMetrics

    def row(family: str, rms: float, bic: float, not_fitted: str = "") -> FamilyRow:
        return FamilyRow(family, family, 10, ErrorMetrics(rms, 3 * rms, 100), ErrorMetrics(rms, 3 * rms, 100), bic,
                         not_fitted)

    assert choose([row("gpi", 2.9, -100.0), row("two_wire", 2.0, -50.0)]) == 1
    assert choose([row("gpi", 2.04, -100.0), row("two_wire", 2.0, -50.0)]) == 0  # within 5 %: the lower BIC
    assert choose([row("gpi", 2.9, -100.0), row("two_wire", 2.0, -50.0, "not fitted")]) == 0
    assert choose([]) is None


def test_an_unknown_family_is_refused_in_one_line():
    from sma_stage.identify.families import check_families

    assert check_families(["two_wire", "gpi"]) == ("gpi", "two_wire")
    assert check_families(["two_wire_compact", "two_wire"]) == ("two_wire", "two_wire_compact")
    with pytest.raises(InputError, match="unknown model family 'preisach'"):
        check_families(["gpi", "preisach"])
    with pytest.raises(InputError, match="no model family given"):
        check_families([" "])


def test_the_pipeline_compares_the_families_and_keeps_the_gpi_beside_a_chosen_two_wire(nominal_stage):
    """identify_recording with both families on the second stage: the two-wire model is deployed, its row
    marked chosen, the report says how the compensator runs it, and the GPI family's model is kept beside it."""
    from sma_stage.identify.pipeline import identify_recording
    from sma_stage.io.series import make_series
    from sma_stage.model.identified import IdentifiedModel

    ident, valid = (make_series(*nominal_stage[name], source=name) for name in ("identification", "validation"))
    found = identify_recording(ident, valid, families=("gpi", "two_wire"))
    rows = {row["family"]: row for row in found.report["families"]}
    assert rows["two_wire"]["chosen"] and not rows["gpi"]["chosen"]
    assert rows["two_wire"]["validation"]["rms_pct"] < rows["gpi"]["validation"]["rms_pct"]
    assert isinstance(found.model, TwoWireModel) and found.model.state is not None
    assert isinstance(found.gpi_model, IdentifiedModel) and found.gpi_model.state is not None
    assert found.report["model"]["kind"] == "two_wire"
    assert list(found.report["compensation"]) == ["two_wire"]
    from sma_stage.identify.report import markdown_summary

    summary = markdown_summary(found.report, "diagnosis")
    assert "Model written (model.yaml): **two-wire" in summary and "| two_wire |" in summary


def test_the_compact_onset_is_a_family_of_its_own_and_chosen_where_it_predicts_better():
    """`two_wire_compact` beside `two_wire` on the thin-wire stage (paper's records), whose wires stay still below
    their transformation start: the compact onset's model validates better (measured 0.60 % against 1.01 % RMS),
    is chosen, says so, and carries compact_onset 1 into the model deployed."""
    from sma_stage.identify.pipeline import identify_recording
    from sma_stage.io.series import make_series

    stage = records(VARIANTS["thin_wires"])
    ident, valid = (make_series(*stage[name], source=name) for name in ("identification", "validation"))
    found = identify_recording(ident, valid, families=("two_wire_compact", "two_wire"), workers=2)
    rows = {row["family"]: row for row in found.report["families"]}
    assert list(rows) == ["two_wire", "two_wire_compact"]
    assert rows["two_wire_compact"]["validation"]["rms_pct"] < 0.8 * rows["two_wire"]["validation"]["rms_pct"]
    assert rows["two_wire_compact"]["chosen"] and "compact onset" in rows["two_wire_compact"]["model"]
    assert "compact onset" not in rows["two_wire"]["model"]
    assert found.model.parameters.values["compact_onset"] == 1.0


def test_the_two_wire_inverse_tracks_the_second_stage_in_feedforward(nominal_stage, nominal_fit):
    """The exact inverse one sample at a time drives the physical stage (no measurement fed back) along a sine
    over 70 % of the identified span: at most 2 % RMS and 6 % max of that span after the first cycle (measured
    1.32 % and 4.00 %; a 10-operator plain GPI through the package's compensator: 6.17 % and 16.1 %)."""
    from antagonistic_plant import HISTORY_S, SAMPLE_PERIOD_S, SUBSTEPS, AntagonisticStage

    plant = AntagonisticStage(VARIANTS["nominal"])
    for _ in range(int(HISTORY_S / SAMPLE_PERIOD_S) * SUBSTEPS):
        plant.step(0.0, SAMPLE_PERIOD_S / SUBSTEPS)
    y = nominal_stage["identification"][2]
    span, centre = float(np.ptp(y)), 0.5 * float(y.max() + y.min())
    t = np.arange(0.0, 600.0, SAMPLE_PERIOD_S)
    target = centre + 0.35 * span * np.sin(2 * np.pi * t / 120.0) * np.minimum(t / 60.0, 1.0)
    stream = nominal_fit.model.without_state().stream(max_current_a=5.0)
    errors = []
    for k in range(t.size - 1):
        errors.append(plant.position_m - target[k])
        current = stream.command_for(target[k + 1], SAMPLE_PERIOD_S)
        for _ in range(SUBSTEPS):
            plant.step(current, SAMPLE_PERIOD_S / SUBSTEPS)
    tracked = np.array(errors)[t[:-1] > 120.0]
    assert 100 * np.sqrt(np.mean(tracked**2)) / span <= 2.0
    assert 100 * np.max(np.abs(tracked)) / span <= 6.0


def test_the_compensator_runs_a_two_wire_model_through_its_exact_inverse():
    """With no lead limit and no rate limit, the package's compensator sends the currents that bring the model
    to each target at the end of its hold, within the band its last command may stay in (KEEP_TOLERANCE of the
    strokes, 0.02 % of the span): the two-wire model goes through the same control core as the GPI."""
    from sma_stage.control.compensator import Compensator

    model, (t, u) = example_model(), excitation(600)
    targets = model.predict(t, u)
    core = Compensator(model, 5.0, lead_limit=1e9, feedforward_lead_limit=1e9, feedforward_step_lead_limit=1e9,
                       max_rate_a_per_s=0.0)
    commands = []
    for k in range(t.size - 1):
        dt = t[k] - t[k - 1] if k else 0.0
        commands.append(core.command(targets[k + 1], dt_s=dt, hold_s=t[k + 1] - t[k]))
    reached = model.predict(t, np.r_[commands, 0.0])
    assert np.max(np.abs(reached - targets)) <= 1.000001 * keep_band(model)
    assert core.tau_s == 4.0 and "two-wire" in core.drive.describe()


def test_the_compensator_saturates_towards_an_unreachable_target_and_refuses_the_analytic_inverse():
    from sma_stage.control.compensator import Compensator

    core = Compensator(example_model(), 5.0, max_rate_a_per_s=0.0)
    low, high = core.drive.reach
    assert core.command(high + 0.1 * (high - low), dt_s=0.2) == 5.0 and core.saturated == 1
    assert core.drive.out_of_reach == 1
    assert core.command(low - 0.1 * (high - low), dt_s=0.2) == -5.0 and core.saturated == -1
    with pytest.raises(InputError, match="exact inverse only"):
        Compensator(example_model(), 5.0, method="analytic")


def test_a_hand_over_with_both_wires_hot_moves_the_second_stage_through_without_flipping_its_wires():
    """Full current switched from wire b (held 60 s) to wire a: for a few seconds both wires are hot, and each
    pulls the other into stress-induced martensite. The plant's relays switch where the stress they leave agrees
    with them, so the stage moves over to wire a's side with no wire's martensite jumping by a quarter in a
    sub-step and the stress within what a transformation plateau carries (before: the relays of both wires flipped
    all the way every sub-step, 84 MPa <-> 3.01 GPa, holding the stage at 0 for 2 s)."""
    from antagonistic_plant import SAMPLE_PERIOD_S, SUBSTEPS, AntagonisticStage

    plant = AntagonisticStage(VARIANTS["nominal"])
    dt = SAMPLE_PERIOD_S / SUBSTEPS
    for current, seconds in ((0.0, 200.0), (-4.57, 60.0)):
        for _ in range(round(seconds / dt)):
            plant.step(current, dt)
    start = plant.position_m
    fractions, stresses, positions = [], [], []
    for _ in range(round(15.0 / dt)):
        plant.step(4.74, dt)
        fractions.append([wire.martensite for wire in plant.wires])
        stresses.append(max(plant.stresses))
        positions.append(plant.position_m)
    assert np.max(np.abs(np.diff(fractions, axis=0))) < 0.25
    assert max(stresses) < 1.5e9
    assert start < 0.0 < -0.9 * start < positions[-1]
