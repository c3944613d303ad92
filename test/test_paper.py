"""The paper's Table 1 evaluated as printed, and gpi_tool paper."""

import json

import numpy as np

from sma_stage.cli import main
from sma_stage.model.paper import PAPER_TABLE_1, READINGS, envelope_findings, loop_summary


def test_table_1_breaks_both_conditions_of_the_text():
    findings = envelope_findings(PAPER_TABLE_1, 10)
    assert PAPER_TABLE_1.a10 < 0
    assert findings.density_signs == "all negative"
    assert findings.smallest_gap > 0
    v = np.linspace(-5, 5, 101)
    assert np.all(PAPER_TABLE_1.envelope_left(v) > PAPER_TABLE_1.envelope_right(v))
    assert findings.pinned_operators == [0, 1, 2, 3, 4, 5]


def test_table_1_has_no_loop_under_any_reading():
    for params in READINGS.values():
        loop = loop_summary(params, 10)
        assert loop.span > 0.5
        assert loop.width_fraction < 1e-9


def test_a_parameter_set_with_a_loop_shows_one():
    """The loop measure itself can see a loop (so the zero above is a finding, not a blind spot)."""
    stage = PAPER_TABLE_1.replace(a1=1.0, a2=0.6, a3=0.0, a4=0.0, a5=1.0, a6=0.6, a7=-0.5, a8=0.2, a9=0.1,
                                  a10=0.3, a11=1.0)
    assert loop_summary(stage, 10).width_fraction > 0.05


def test_gpi_tool_paper_writes_plots_and_json(tmp_path, capsys):
    assert main(["paper", "--out", str(tmp_path), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["gl_above_gr_everywhere"] and not report["a10_positive_as_the_text_requires"]
    for name in ("paper_loops.png", "paper_time_series.png", "paper_summary.md"):
        assert (tmp_path / name).stat().st_size > 1000 or name.endswith(".md")
    assert (tmp_path / "paper_loops.png").read_bytes()[:4] == b"\x89PNG"
