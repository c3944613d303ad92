"""gpi_tool plot: the views of a recording (CSV or rosbag2) as PNG, for users without Foxglove or PlotJuggler:
the hysteresis loop, the time series and, with a model, its prediction over the measurement and the residual."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from sma_stage.commands.identify import read_data
from sma_stage.identify.metrics import error_metrics
from sma_stage.io.run_folder import RunFolder
from sma_stage.io.series import Series
from sma_stage.model.kinds import load_any_model_file
from sma_stage.plots import Panel, save_panels

MICROMETRES_PER_M = 1e6


def display_scale(unit: str) -> tuple[float, str]:
    """(factor, unit shown): positions in m are drawn in um."""
    return (MICROMETRES_PER_M, "um") if unit == "m" else (1.0, unit)


def recording_panels(series: Series, unit: str, predicted: np.ndarray | None) -> dict[str, list[Panel]]:
    """The figures' panels by file name: loop.png, time_series.png and, with a prediction, residual.png."""
    scale, shown = display_scale(unit)
    t_label = "sample" if series.time_is_index else "t [s]"
    measured = [("measured", series.output * scale)]
    model = [("model, from rest", predicted * scale)] if predicted is not None else []
    figures = {
        "loop.png": [Panel("hysteresis loop: output against input", series.input, measured + model,
                           "input [A]", f"output [{shown}]")],
        "time_series.png": [Panel("input", series.t, [("input", series.input)], t_label, "input [A]"),
                            Panel("output", series.t, measured + model, t_label, f"output [{shown}]")],
    }
    if predicted is not None:
        residual = [("measured - model", (series.output - predicted) * scale)]
        figures["residual.png"] = [Panel("residual over time", series.t, residual, t_label, f"residual [{shown}]"),
                                   Panel("residual against input", series.input, residual, "input [A]",
                                         f"residual [{shown}]")]
    return figures


def run_plot(args: argparse.Namespace) -> dict:
    """Read the recording (and the model), write the PNGs into --out as one set (a failed run leaves --out as
    it was); what was written."""
    with RunFolder(args.out) as run:
        series = read_data(args.data, args)
        model = load_any_model_file(args.model) if args.model is not None else None
        predicted = model.predict(series.t, series.input) if model is not None else None
        figures = recording_panels(series, args.unit, predicted)
        for name, panels in figures.items():
            save_panels(run.staging / name, panels, columns=len(panels))
    files = [str(Path(args.out) / name) for name in figures]
    report: dict = {"data": str(args.data), "samples": len(series), "files": files}
    if predicted is not None:
        report["model"] = str(args.model)
        report["residual"] = error_metrics(series.output, predicted).to_dict()
    return report
