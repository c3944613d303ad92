"""PNG figures a person reads at a glance: hysteresis loops, time series, correlations with bands."""

from __future__ import annotations

import io
import os
from collections.abc import Sequence
from dataclasses import dataclass, field

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from sma_stage.io.atomic import atomic_write_bytes  # noqa: E402


@dataclass
class Panel:
    """One subplot: x data and named y curves, with axis labels."""

    title: str
    x: np.ndarray
    curves: list[tuple[str, np.ndarray]] = field(default_factory=list)
    xlabel: str = ""
    ylabel: str = ""
    band: float | None = None


MAX_DRAWN_POINTS = 20_000  # a curve is thinned to about this many points: no more can be told apart on a PNG


def drawn_indices(values: np.ndarray, max_points: int = MAX_DRAWN_POINTS) -> np.ndarray:
    """Indices of the samples to draw: all of them up to max_points; else, in each of max_points / 2 consecutive
    buckets, the lowest and the highest sample in their order (peaks stay, the curve's envelope with them)."""
    values = np.asarray(values)
    if values.size <= max_points:
        return np.arange(values.size)
    buckets = max_points // 2
    edges = np.linspace(0, values.size, buckets + 1).astype(np.int64)
    width = int(np.max(np.diff(edges)))
    padded = np.full(buckets * width, np.nan)
    rows = np.repeat(np.arange(buckets), np.diff(edges))
    columns = np.arange(values.size) - np.repeat(edges[:-1], np.diff(edges))
    padded[rows * width + columns] = values
    grid = padded.reshape(buckets, width)  # a bucket shorter than width is padded with NaN, which nanarg* skip
    low = np.nanargmin(grid, axis=1) + edges[:-1]
    high = np.nanargmax(grid, axis=1) + edges[:-1]
    return np.unique(np.concatenate([low, high, [0, values.size - 1]]))


def save_panels(path: str | os.PathLike, panels: Sequence[Panel], columns: int = 2, kind: str = "line") -> None:
    """Write the panels as one PNG (atomically); kind 'line' for curves, 'stem' for correlations."""
    rows = int(np.ceil(len(panels) / columns))
    figure, axes = plt.subplots(rows, columns, figsize=(6.0 * columns, 3.8 * rows), squeeze=False)
    for axis, panel in zip(axes.flat, panels, strict=False):
        for label, values in panel.curves:
            if kind == "stem":
                axis.stem(panel.x, values, label=label, basefmt=" ")
            else:
                shown = drawn_indices(values)
                axis.plot(np.asarray(panel.x)[shown], np.asarray(values)[shown], label=label, linewidth=1.0)
        if panel.band is not None:
            axis.axhspan(-panel.band, panel.band, color="tab:gray", alpha=0.25, label="95 % band")
        axis.set_title(panel.title, fontsize=10)
        axis.set_xlabel(panel.xlabel)
        axis.set_ylabel(panel.ylabel)
        axis.grid(True, alpha=0.3)
        axis.legend(fontsize=8, loc="upper left")
    for axis in list(axes.flat)[len(panels):]:
        axis.set_visible(False)
    figure.tight_layout()
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=110)
    plt.close(figure)
    atomic_write_bytes(path, buffer.getvalue())
