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


def save_panels(path: str | os.PathLike, panels: Sequence[Panel], columns: int = 2, kind: str = "line") -> None:
    """Write the panels as one PNG (atomically); kind 'line' for curves, 'stem' for correlations."""
    rows = int(np.ceil(len(panels) / columns))
    figure, axes = plt.subplots(rows, columns, figsize=(6.0 * columns, 3.8 * rows), squeeze=False)
    for axis, panel in zip(axes.flat, panels, strict=False):
        for label, values in panel.curves:
            if kind == "stem":
                axis.stem(panel.x, values, label=label, basefmt=" ")
            else:
                axis.plot(panel.x, values, label=label, linewidth=1.0)
        if panel.band is not None:
            axis.axhspan(-panel.band, panel.band, color="tab:gray", alpha=0.25, label="95 % band")
        axis.set_title(panel.title, fontsize=10)
        axis.set_xlabel(panel.xlabel)
        axis.set_ylabel(panel.ylabel)
        axis.grid(True, alpha=0.3)
        axis.legend(fontsize=8)
    for axis in list(axes.flat)[len(panels):]:
        axis.set_visible(False)
    figure.tight_layout()
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=110)
    plt.close(figure)
    atomic_write_bytes(path, buffer.getvalue())
