"""gpi_tool from the outside: exit status, JSON on stdout only, one-line errors, files written."""

import json
import re

import numpy as np
import pytest

from sma_stage.cli import main
from sma_stage.model import forward, load_model_file
from sma_stage.signals import paper_identification_signal, paper_validation_signal

STAGE = load_model_file("config/model_default.yaml")


def write_gpi_csv(path, signal, noise=1e-6, samples=600, seed=0):
    t = np.linspace(0.0, 1000.0, samples)
    u = signal(t)
    y = forward(u, STAGE.parameters, STAGE.operators) + np.random.default_rng(seed).normal(0.0, noise, samples)
    np.savetxt(path, np.c_[t, u, y], delimiter=",", header="t,input,output", comments="")
    return path


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    folder = tmp_path_factory.mktemp("data")
    return (write_gpi_csv(folder / "ident.csv", paper_identification_signal),
            write_gpi_csv(folder / "valid.csv", paper_validation_signal, seed=1))


def test_fit_prints_only_the_json_report_and_writes_the_model(data, tmp_path, capsys):
    ident, valid = data
    assert main(["fit", str(ident), "--validate", str(valid), "--operators", "10", "--out", str(tmp_path),
                 "--json"]) == 0
    captured = capsys.readouterr()
    report = json.loads(captured.out)
    assert set(report) >= {"model", "identification", "validation", "fit_seconds"}
    assert report["gpi_fit"]["operators"] == 10 and len(report["gpi_fit"]["parameters"]) == 11
    assert report["model"]["kind"] == "gpi" and report["model"]["parameters"] == report["gpi_fit"]["parameters"]
    assert report["validation"]["samples"] == 600
    assert report["validation"]["max_pct"] < 4.0
    assert "gpi_tool:" in captured.err
    assert load_model_file(tmp_path / "model.yaml").operators == 10
    assert (tmp_path / "fit.png").exists() and (tmp_path / "report.md").exists()


def bad_csv(tmp_path, text):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    return str(path)


@pytest.mark.parametrize("case", ["missing file", "missing column", "nan", "no excitation", "few samples",
                                  "moved once"])
def test_bad_data_ends_with_status_2_and_one_line(case, tmp_path, capsys):
    rows = "\n".join(f"{k},{np.sin(k / 5)},{np.cos(k / 5)}" for k in range(60))
    path = {
        "missing file": str(tmp_path / "absent.csv"),
        "missing column": bad_csv(tmp_path, "t,current,output\n" + rows),
        "nan": bad_csv(tmp_path, "t,input,output\n" + rows + "\n60,nan,0.1"),
        "no excitation": bad_csv(tmp_path, "t,input,output\n" + "\n".join(f"{k},1.0,{k}" for k in range(60))),
        "few samples": bad_csv(tmp_path, "t,input,output\n0,1,2\n1,2,3"),
        "moved once": bad_csv(tmp_path, "t,input,output\n" + "\n".join(
            f"{k},{4 * np.sin(k / 16)},{min(k / 15, 1.0) * 1e-4 + 1e-8 * np.sin(7 * k)}" for k in range(1000))),
    }[case]
    assert main(["fit", path, "--out", str(tmp_path / "out"), "--json"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert len(captured.err.strip().splitlines()) == 1 and captured.err.startswith("gpi_tool: error:")
    assert case != "moved once" or "no excitation: the output moved over 5 % of its span in only" in captured.err
    assert not (tmp_path / "out").exists()


def test_simulate_writes_a_csv_that_fit_can_read(tmp_path, capsys):
    out = tmp_path / "sim.csv"
    assert main(["simulate", "--input", "validation", "--rate-hz", "1", "--duration", "300", "--out", str(out),
                 "--effect", "sensor_delay_s=2", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["samples"] == 300 and summary["effects"]["sensor_delay_s"] == 2.0
    assert out.read_text().startswith("t,input,output")


@pytest.mark.parametrize("arguments", [["--effect", "bogus=1"], ["--effect", "sensor_delay_s"],
                                       ["--set", "flexure_stiffness_n_m=-1"], ["--rate-hz", "inf"],
                                       ["--rate-hz", "nan"], ["--duration", "inf"], ["--duration", "1e12"],
                                       ["--seed", "-1"]])
def test_simulate_refuses_bad_settings(arguments, tmp_path, capsys):
    assert main(["simulate", "--input", "validation", "--out", str(tmp_path / "s.csv"), *arguments]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and error[0].startswith("gpi_tool: error: "), error
    assert not (tmp_path / "s.csv").exists()


def test_diagnose_fills_every_key_of_the_report(tmp_path, capsys):
    from synthetic import make_case

    case = make_case("delay", seed=3)
    paths = []
    for name, record in (("ident", case.identification), ("valid", case.validation)):
        paths.append(tmp_path / f"{name}.csv")
        np.savetxt(paths[-1], np.c_[record.t, record.u, record.y], delimiter=",", header="t,input,output",
                   comments="")
    assert main(["diagnose", str(paths[0]), "--validate", str(paths[1]), "--out", str(tmp_path / "out"),
                 "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    diagnosis = report["diagnosis"]
    assert diagnosis["effect"] == "delay"
    assert diagnosis["after"]["validation"]["rms_pct"] < diagnosis["before"]["validation"]["rms_pct"] / 5
    assert set(diagnosis) >= {"effect", "evidence", "parameters", "before", "after"}
    assert report["validation"]["rms_pct"] == diagnosis["before"]["validation"]["rms_pct"]
    for name in ("report.json", "report.md", "model.yaml", "diagnosis_loops.png", "diagnosis_correlations.png"):
        assert (tmp_path / "out" / name).exists()


def test_diagnose_reports_every_validation_record_and_chooses_on_the_worst(data, tmp_path, capsys):
    """--validate twice: each family is scored on both records, the report gives the written model's errors on
    each, and the family chosen is the one whose worse record is best (within the parsimony margin, by BIC)."""
    from sma_stage.identify.families import PARSIMONY
    from sma_stage.signals import designed_identification_signal

    ident, valid = data
    second = write_gpi_csv(tmp_path / "levels.csv", lambda t: designed_identification_signal(t, 5.0, 1000.0, 3),
                           seed=2)
    assert main(["diagnose", str(ident), "--validate", str(valid), "--validate", str(second), "--families",
                 "gpi,bouc_wen", "--rounds", "1", "--out", str(tmp_path / "out"), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert [record["source"] for record in report["validation_records"]] == [str(valid), str(second)]
    rows = [row for row in report["families"] if not row["not_fitted"]]
    assert len(rows) == 2 and all(len(row["more_validation"]) == 1 for row in rows)
    for row in rows:
        assert row["worst_validation"]["rms_pct"] == max(row["validation"]["rms_pct"],
                                                         row["more_validation"][0]["rms_pct"])
    best = min(row["worst_validation"]["rms_pct"] for row in rows)
    chosen = [row for row in rows if row["chosen"]]
    assert len(chosen) == 1 and chosen[0]["worst_validation"]["rms_pct"] <= best * (1.0 + PARSIMONY)
    assert report["model"]["kind"] == ("gpi" if chosen[0]["family"] == "gpi" else "bouc_wen")
    assert "worst validation record" in (tmp_path / "out" / "report.md").read_text()


def test_diagnose_needs_validation_data(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_status:
        main(["diagnose", str(tmp_path / "ident.csv")])
    assert exit_status.value.code == 2
    assert "--validate" in capsys.readouterr().err


@pytest.mark.parametrize(("arguments", "message"), [
    (["--holdout", "1.5"], "between 0 and 1"),
    (["--holdout", "nan"], "between 0 and 1"),
    (["--holdout", "0.25", "--validate", "v.csv"], "not allowed with"),
    (["--holdout", "0.25", "--rounds", "9"], "from 1 to 4"),
    (["--holdout", "0.25", "--workers", "0"], "from 1 to 64"),
    (["--holdout", "0.25", "--workers", "two"], "from 1 to 64"),
])
def test_diagnose_refuses_a_bad_holdout_round_or_worker_count(arguments, message, tmp_path, capsys):
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exit_status:
        main(["diagnose", str(tmp_path / "ident.csv"), "--out", str(out), *arguments])
    assert exit_status.value.code == 2
    assert message in capsys.readouterr().err and not out.exists()


def test_json_output_is_strict_json_even_with_non_finite_numbers(data, tmp_path, capsys, monkeypatch):
    """A standard error or validation error of inf once printed as `Infinity`, which strict JSON parsers refuse."""
    import sma_stage.commands.identify as identify_command

    monkeypatch.setattr(identify_command, "run_fit", lambda args: {"a9": float("inf"), "rms": np.float64("nan")})
    assert main(["fit", str(data[0]), "--json"]) == 0

    def refuse(constant):
        raise ValueError(f"not strict JSON: {constant}")

    assert json.loads(capsys.readouterr().out, parse_constant=refuse) == {"a9": None, "rms": None}


def test_argument_errors_are_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as stopped:
        main(["simulate", "--input", "validation", "--rate-hz", "abc", "--out", str(tmp_path / "s.csv")])
    assert stopped.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert error == ["gpi_tool simulate: error: argument --rate-hz: invalid float value: 'abc' "
                     "(see gpi_tool simulate --help)"]


@pytest.mark.parametrize("scale", [1e-30, 1e-8, 1e8, 1e90])
def test_the_fit_does_not_depend_on_the_output_unit(data, tmp_path, capsys, scale):
    """The same record in another unit fits the same (the fit works on the output scaled to unit span):
    an output of 1e-12 m span once fitted at 36 % RMS and one of 1e200 raised LinAlgError."""
    records = np.loadtxt(data[0], delimiter=",", skiprows=1)
    records[:, 2] *= scale
    scaled = tmp_path / "scaled.csv"
    np.savetxt(scaled, records, delimiter=",", header="t,input,output", comments="", fmt="%.17g")
    assert main(["fit", str(data[0]), "--operators", "5", "--json"]) == 0
    reference = json.loads(capsys.readouterr().out)
    assert main(["fit", str(scaled), "--operators", "5", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["identification"]["rms_pct"] == pytest.approx(reference["identification"]["rms_pct"], rel=1e-3)


@pytest.mark.parametrize(("column", "factor", "message"), [
    ("output", 1e-300, "the output's largest magnitude is .* outside 1e-100 to 1e\\+100"),
    ("output", 1e300, "the output's largest magnitude is .* outside 1e-100 to 1e\\+100"),
    ("input", 1e200, "the input's largest magnitude is .* give the current in A"),
    ("t", 1e9, "t spans .* s .*: is it in ms, us or ns\\? give it in seconds"),
    ("t", 1e-300, "t steps by .* s \\(median\\): is it in seconds\\?")])
def test_magnitudes_no_record_can_have_are_refused_with_one_line(data, tmp_path, capsys, column, factor, message):
    records = np.loadtxt(data[0], delimiter=",", skiprows=1)
    records[:, ("t", "input", "output").index(column)] *= factor
    scaled = tmp_path / "scaled.csv"
    np.savetxt(scaled, records, delimiter=",", header="t,input,output", comments="", fmt="%.17g")
    assert main(["fit", str(scaled), "--json", "--out", str(tmp_path / "out")]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and not (tmp_path / "out").exists()
    (line,) = captured.err.strip().splitlines()
    assert re.search(message, line), line


def run_files(folder):
    return {path.name: path.read_bytes() for path in folder.iterdir() if not path.name.startswith(".")}


def test_out_that_is_a_file_is_refused_before_the_work(data, tmp_path, capsys, monkeypatch):
    import sma_stage.commands.identify as identify_command

    monkeypatch.setattr(identify_command, "identify_recording", lambda *args, **kwargs: pytest.fail("fitted"))
    taken = tmp_path / "taken"
    taken.write_text("mine")
    assert main(["fit", str(data[0]), "--out", str(taken)]) == 2
    assert capsys.readouterr().err.strip() == f"gpi_tool: error: --out {taken} is a file, not a folder"
    assert taken.read_text() == "mine"


@pytest.mark.parametrize("failure", [OSError(28, "No space left on device"), KeyboardInterrupt()])
def test_a_run_that_fails_after_the_model_leaves_the_folder_as_it_was(data, tmp_path, capsys, monkeypatch, failure):
    """model.yaml is written before the figures: a figure that cannot be written, or Ctrl-C there, once left
    a new model beside the old report and figures."""
    import sma_stage.commands.identify as identify_command

    out = tmp_path / "out"
    assert main(["fit", str(data[0]), "--operators", "5", "--out", str(out)]) == 0
    before = run_files(out)

    def fail(*args, **kwargs):
        raise failure

    monkeypatch.setattr(identify_command, "write_fit_figures", fail)
    assert main(["fit", str(data[1]), "--operators", "5", "--out", str(out)]) in (2, 130)
    assert run_files(out) == before
    assert [path.name for path in tmp_path.iterdir()] == ["out"], "no staging folder left"


def test_a_run_replaces_the_whole_set_of_an_earlier_run(data, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["diagnose", str(data[0]), "--validate", str(data[1]), "--operators", "5", "--rounds", "1",
                 "--out", str(out)]) == 0
    diagnosed = set(run_files(out))
    (out / "notes.txt").write_text("the user's own file")
    assert main(["fit", str(data[0]), "--operators", "5", "--out", str(out)]) == 0
    fitted = set(run_files(out))
    assert fitted == {"model.yaml", "report.json", "report.md", "fit.png", "notes.txt"}
    assert diagnosed - fitted, "the diagnose run's own files are gone"


def test_a_failed_run_creates_no_folder_and_names_the_file_it_could_not_write(data, tmp_path, capsys, monkeypatch):
    """A failed run used to leave the missing parents of --out behind, and a full disk's error named the hidden
    staging path."""
    import errno

    from sma_stage.model.identified import IdentifiedModel

    def disk_full(self, path):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(IdentifiedModel, "save", disk_full)
    out = tmp_path / "deep" / "a" / "b"
    assert main(["fit", str(data[0]), "--operators", "5", "--out", str(out)]) == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert error == f"gpi_tool: error: No space left on device: {out / 'model.yaml'}", error
    assert list(tmp_path.iterdir()) == [], "no folder created, no staging folder left"


def test_a_dangling_symlink_as_out_is_refused_before_the_work(data, tmp_path, capsys, monkeypatch):
    import sma_stage.commands.identify as identify_command

    (tmp_path / "out").symlink_to(tmp_path / "nowhere")
    monkeypatch.setattr(identify_command, "identify_recording", lambda *a, **k: pytest.fail("the fit ran"))
    assert main(["fit", str(data[0]), "--out", str(tmp_path / "out")]) == 2
    assert "symbolic link to nothing" in capsys.readouterr().err


def test_a_staging_folder_left_by_a_killed_run_is_removed_by_the_next(data, tmp_path, capsys):
    import subprocess
    import sys

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    left = tmp_path / f".out.{int(dead.stdout)}.abc123.staging"
    left.mkdir()
    (left / "model.yaml").write_text("half")
    assert main(["fit", str(data[0]), "--operators", "5", "--out", str(tmp_path / "out")]) == 0
    assert sorted(path.name for path in tmp_path.iterdir()) == ["out"]


def test_holdout_leaving_too_few_samples_is_refused_by_its_value(data, capsys):
    assert main(["fit", str(data[0]), "--holdout", "1e-300"]) == 2
    assert "holdout fraction 1e-300 leaves 0 of 600 samples" in capsys.readouterr().err


@pytest.mark.parametrize("interrupt, line, status", [("terminated", "gpi_tool: terminated", 143),
                                                     ("interrupted", "gpi_tool: interrupted", 130)])
def test_an_interrupt_prints_one_line_whatever_its_half_built_objects_raise(interrupt, line, status, monkeypatch,
                                                                            capsys):
    """A SIGTERM landing while numba loaded a kernel left llvmlite objects whose finalizers raised as they were
    collected: "Exception ignored in ObjectRef.__del__" and a traceback after the one line."""
    import argparse
    import gc
    import sys

    from sma_stage import cli

    raised = []
    monkeypatch.setattr(sys, "unraisablehook", raised.append)

    class HalfBuilt:
        def __del__(self):
            raise AttributeError("'ValueRef' object has no attribute '_as_parameter_'")

    def handler(args):
        half_built = HalfBuilt()  # noqa: F841 -- freed with this frame, once the interrupt is handled
        raise cli.Terminated if interrupt == "terminated" else KeyboardInterrupt

    assert cli._run(argparse.Namespace(handler=handler)) == status
    gc.collect()
    assert raised == [] and capsys.readouterr().err.strip() == line


def test_sigterm_ends_a_diagnosis_and_its_workers_as_ctrl_c_does(data, tmp_path):
    """SIGTERM used to end the main process at once and leave the forkserver, the resource tracker and both
    workers running, and a staging folder beside --out."""
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "out"
    process = subprocess.Popen([sys.executable, "-m", "sma_stage.cli", "diagnose", str(data[0]), "--validate",
                                str(data[1]), "--workers", "2", "--out", str(out)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.monotonic() + 60.0
    while time.monotonic() < deadline and len(descendants(process.pid)) < 2:
        time.sleep(0.1)
    assert len(descendants(process.pid)) >= 2, "the workers started (gpi_tool forks them)"
    process.send_signal(signal.SIGTERM)
    assert_terminated_cleanly(process, 30.0, tmp_path)


def test_sigterm_while_the_workers_fork_ends_the_diagnosis(data, tmp_path):
    """A SIGTERM handled in an after-fork callback (logging has one) was dropped by Python ("Exception ignored")
    and the diagnosis ran on to status 0; here a callback sends it at every fork of the workers."""
    import subprocess
    import sys

    out = tmp_path / "out"
    script = ("import os, signal, sys\n"
              "from sma_stage.cli import main\n"
              "def signal_here():\n"
              "    os.kill(os.getpid(), signal.SIGTERM)\n"
              "    sum(range(1000))\n"
              "os.register_at_fork(after_in_parent=signal_here)\n"
              f"sys.exit(main(['diagnose', {str(data[0])!r}, '--validate', {str(data[1])!r}, '--workers', '2', "
              f"'--out', {str(out)!r}]))\n")
    process = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, start_new_session=True)
    error = assert_terminated_cleanly(process, 60.0, tmp_path)
    assert "Exception ignored" not in error


def assert_terminated_cleanly(process, timeout_s: float, tmp_path) -> str:
    """Wait for a gpi_tool run started in its own session; assert it ended by SIGTERM (143, its one line) and left
    no process (killed here if it did) and nothing in tmp_path; its stderr."""
    import os
    import signal
    import time

    _, error = process.communicate(timeout=timeout_s)
    time.sleep(1.0)
    survivors = [pid for pid in session_members(process.pid) if pid != process.pid]
    for pid in survivors:
        os.kill(pid, signal.SIGKILL)
    assert process.returncode == 143 and error.strip().endswith("gpi_tool: terminated"), error
    assert not survivors, "no process of the run left"
    assert sorted(path.name for path in tmp_path.iterdir()) == [], "no folder and no staging folder left"
    return error


def descendants(pid: int) -> list[int]:
    """The processes below pid (Linux /proc)."""
    from pathlib import Path

    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    found, pending = [], [pid]
    while pending:
        for child in children.get(pending.pop(), []):
            found.append(child)
            pending.append(child)
    return found


def session_members(session: int) -> list[int]:
    """The live processes of a session (those re-parented to PID 1 included)."""
    from pathlib import Path

    members = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[3]) == session and fields[0] != "Z":
            members.append(int(stat.parent.name))
    return members


def test_a_record_too_large_for_the_free_memory_is_refused_before_it_is_read(data, tmp_path, capsys, monkeypatch):
    """A 10-million-row CSV under a 2 GB limit used to end in a MemoryError traceback."""
    import sma_stage.commands.identify as identify_command

    monkeypatch.setattr(identify_command, "available_memory_bytes", lambda: 100 << 20)
    monkeypatch.setattr(identify_command, "load_series", lambda *a, **k: pytest.fail("the record was read"))
    assert main(["fit", str(data[0]), "--out", str(tmp_path / "out")]) == 2
    error = capsys.readouterr().err.strip()
    assert re.fullmatch(r"gpi_tool: error: the records hold about \d+ rows: the fit needs about [0-9.]+ GiB and "
                        r"0\.1 GiB are free .*", error), error
    assert not (tmp_path / "out").exists()


def test_plot_draws_a_bag_and_a_model_and_refuses_a_bad_model_in_one_line(tmp_path, capsys):
    """gpi_tool plot on a bag the identification node recorded, with a model: the loop, the time series and the
    residual as PNG, the residual's size in the JSON; a bad model file ends with one line and no folder."""
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    out = tmp_path / "plots"
    assert main(["plot", str(repo / "test" / "data" / "excitation_mcap"), "--input-topic", "current_cmd",
                 "--model", str(repo / "config" / "model_default.yaml"), "--out", str(out), "--json"]) == 0
    captured = capsys.readouterr()
    report = json.loads(captured.out)
    assert captured.err == "", "no warning from matplotlib or anything else"
    assert sorted(path.name for path in out.glob("*.png")) == ["loop.png", "residual.png", "time_series.png"]
    assert all(path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for path in out.glob("*.png"))
    assert report["samples"] > 200 and 0.0 < report["residual"]["rms_pct"] < 100.0
    bad = tmp_path / "bad.yaml"
    bad.write_text("kind: gpi\noperators: 10\nparameters: {a1: 1.0}\n")
    assert main(["plot", str(repo / "test" / "data" / "excitation_mcap"), "--input-topic", "current_cmd",
                 "--model", str(bad), "--out", str(tmp_path / "none")]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and str(bad) in error[0] and not (tmp_path / "none").exists()
