"""The demonstration runs end to end on the model and its figures make sense."""

from pathlib import Path

import numpy as np

from sma_stage.demo import (
    DEFAULT_MODEL_FILE,
    compensation_demo,
    identification_loop,
    main,
    save_tracking_plots,
)
from sma_stage.io import read_bag


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
