"""The demonstration runs end to end on the model and its figures make sense."""

from sma_stage.demo import DEFAULT_MODEL_FILE, compensation_demo, main


def test_exact_inverse_removes_the_hysteresis_that_a_linear_map_leaves(tmp_path):
    errors = compensation_demo(DEFAULT_MODEL_FILE, tmp_path)
    assert errors["exact inverse"]["max_pct"] < 1e-6
    assert errors["linear map, no compensation"]["rms_pct"] > 5.0
    assert errors["exact inverse"]["rms_pct"] < errors["analytic inverse"]["rms_pct"]
    assert (tmp_path / "compensation.png").read_bytes()[:4] == b"\x89PNG"


def test_demo_main_writes_its_outputs(tmp_path, capsys):
    assert main(["--out", str(tmp_path), "--no-nodes"]) == 0
    assert "exact inverse" in capsys.readouterr().out
    assert (tmp_path / "paper" / "paper_summary.md").exists()
