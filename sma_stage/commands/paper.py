"""gpi_tool paper: evaluate the source paper's Table 1 on its identification and validation signals."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sma_stage.io.atomic import atomic_write_text
from sma_stage.model.forward import forward
from sma_stage.model.paper import PAPER_TABLE_1, READINGS, envelope_findings, loop_summary
from sma_stage.plots import Panel, save_panels
from sma_stage.signals import IDENTIFICATION_DURATION_S, paper_identification_signal, paper_validation_signal

SAMPLE_PERIOD_S = 0.5


def paper_signals() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The paper's two inputs [A] against time [s], sampled every SAMPLE_PERIOD_S."""
    t = np.arange(0.0, IDENTIFICATION_DURATION_S + SAMPLE_PERIOD_S, SAMPLE_PERIOD_S)
    return {
        "identification (decaying sine)": (t, paper_identification_signal(t)),
        "validation (two cosines)": (t, paper_validation_signal(t)),
    }


def evaluate_paper(out_dir: Path, operators: int) -> dict:
    """Evaluate every reading of Table 1, write the loop and time-series PNGs and a Markdown summary."""
    findings = envelope_findings(PAPER_TABLE_1, operators)
    readings = {}
    for name, params in READINGS.items():
        loop = loop_summary(params, operators)
        readings[name] = {"parameters": params.to_dict(), "loop_span": loop.span, "loop_width": loop.width,
                          "loop_width_fraction": loop.width_fraction}
    report = {
        "operators": operators,
        "table_1": PAPER_TABLE_1.to_dict(),
        "a10_positive_as_the_text_requires": PAPER_TABLE_1.a10 > 0,
        "smallest_gl_minus_gr": findings.smallest_gap,
        "gl_above_gr_everywhere": findings.smallest_gap > 0,
        "pinned_operators": findings.pinned_operators,
        "density_signs": findings.density_signs,
        "readings": readings,
        "files": [],
    }
    report["files"] = write_figures(out_dir, operators) + [str(out_dir / "paper_summary.md")]
    atomic_write_text(out_dir / "paper_summary.md", summary_markdown(report))
    return report


def write_figures(out_dir: Path, operators: int) -> list[str]:
    """paper_loops.png (output against input) and paper_time_series.png, one panel per signal and reading."""
    loops, series = [], []
    for signal_name, (t, current) in paper_signals().items():
        for reading, params in READINGS.items():
            output = forward(current, params, operators)
            title = f"{reading}: {signal_name}"
            loops.append(Panel(title, current, [("model", output)], "input current [A]", "output [paper unit]"))
            series.append(Panel(title, t, [("model output", output)], "time [s]", "output [paper unit]"))
    paths = [out_dir / "paper_loops.png", out_dir / "paper_time_series.png"]
    save_panels(paths[0], loops, columns=4)
    save_panels(paths[1], series, columns=4)
    return [str(path) for path in paths]


def summary_markdown(report: dict) -> str:
    """A short Markdown account of what Table 1 gives and why."""
    lines = [
        "# The paper's Table 1 under eqs 1-5 as printed",
        "",
        f"Operators: {report['operators']} (the paper does not state n). Input range: -5 A to 5 A.",
        "",
        f"- a10 = {report['table_1']['a10']} < 0, against the text's a10 > 0: the density p(r_i) is "
        f"{report['density_signs']}.",
        f"- gl(v) - gr(v) is at least {report['smallest_gl_minus_gr']:.4g} over the input range: gl > gr "
        "everywhere, against the text's gl <= gr.",
        f"- Operators {report['pinned_operators']} have an empty band (gl - r_i > gr + r_i for every input): "
        "they are pinned to gl - r_i and keep no memory.",
        "",
        "| reading | output span | loop width | width / span |",
        "|---|---|---|---|",
    ]
    for name, values in report["readings"].items():
        lines.append(f"| {name} | {values['loop_span']:.4g} | {values['loop_width']:.3g} | "
                     f"{100 * values['loop_width_fraction']:.3g} % |")
    lines += ["", "Figures: " + ", ".join(Path(path).name for path in report["files"][:2]), ""]
    return "\n".join(lines)
