"""The demonstration runs end to end on the model and its figures make sense."""

from pathlib import Path

import numpy as np
import pytest

from sma_stage.demo import DEFAULT_MODEL_FILE, compensation_demo, main
from sma_stage.io import read_bag
from sma_stage.nodes.end_to_end import identification_loop, save_tracking_plots


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


def test_the_demo_picture_shows_the_identified_loop_from_the_session_bag(tmp_path):
    """The README's picture starts with the excitation as the identification node recorded it (from the first
    current applied) and the model's prediction over it; a bag of 244 samples whose first current is 5.7 mA."""
    bag = Path(__file__).parent / "data" / "excitation_mcap"
    recorded = read_bag(bag, input_topic="current_cmd")  # recorded before the node recorded current_applied
    panels = identification_loop(bag, DEFAULT_MODEL_FILE, duration_s=2.0, input_topic="current_cmd")
    loop, output, residual = panels
    excitation = recorded.t < recorded.t[0] + 2.0
    assert np.array_equal(loop.x, recorded.input[excitation])
    measured, model = (curve for _, curve in loop.curves)
    assert np.allclose(measured, 1e6 * recorded.output[excitation])
    assert np.all(np.isfinite(model)) and np.allclose(residual.curves[0][1], measured - model)
    assert [name for name, _ in output.curves] == ["measured", "model, from rest"]
    save_tracking_plots(tmp_path / "tracking.png", [], panels)
    assert (tmp_path / "tracking.png").stat().st_size > 10_000


def test_the_demo_says_which_family_the_refit_deployed_and_passes_its_families_to_the_node(tmp_path):
    """`--families` reaches the identification node's `families`; with a two-wire model chosen the demo's line
    names it and every family's held-out RMS (it printed the GPI's effects and failed on a two-wire report)."""
    from sma_stage.nodes.end_to_end import EndToEndSettings, describe_diagnosis, node_parameters

    settings = EndToEndSettings(families=("gpi", "two_wire"))
    assert node_parameters(settings, tmp_path)["identification_node"]["families"] == ["gpi", "two_wire"]
    rows = [{"family": "gpi", "model": "GPI, 10 operators, thermal_lag", "validation": {"rms_pct": 1.9},
             "chosen": False},
            {"family": "two_wire", "model": "two-wire, 4 operators per wire", "validation": {"rms_pct": 1.5},
             "chosen": True}]
    diagnosis = {"before": {"validation": {"rms_pct": 8.5}}, "after": {"validation": {"rms_pct": 1.9}},
                 "effects": ["thermal_lag"]}
    line = describe_diagnosis({"diagnosis": diagnosis, "families": rows,
                               "model": {"kind": "two_wire", "parameters": {}}})
    assert "gpi 1.90 %, two_wire 1.50 %" in line and line.endswith("two-wire, 4 operators per wire went to the "
                                                                   "compensator")
    gpi = {"diagnosis": diagnosis, "model": {"effects": []}}
    assert describe_diagnosis(gpi).endswith("the plain GPI went to the compensator")


def test_the_demo_refuses_an_unknown_family_in_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as ended:
        main(["--out", str(tmp_path / "out"), "--no-nodes", "--families", "gpi,preisach"])
    assert ended.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert "unknown model family 'preisach'" in error and not (tmp_path / "out").exists()
