"""The models that went in force, newest last, and the guard on an automatic swap (no ROS).

A model is the same as another when its file says the same without the carried state (a model pushed again with
a fresh state is the same model). A swap is guarded: a candidate fitted on a recent record replaces the model in
force only when it predicts that record's held-out tail better, both run from rest over the whole record.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from sma_stage.errors import InputError
from sma_stage.identify.metrics import ErrorMetrics, error_metrics
from sma_stage.io.series import Series
from sma_stage.model.kinds import AnyModel


def started_from(model: AnyModel, t_s: np.ndarray, current_a: np.ndarray) -> AnyModel:
    """The model carrying the state a record of the applied current (t [s], u [A]) leaves it in, run from rest
    (no state without a record)."""
    plain = model.without_state()
    if len(t_s) == 0:
        return plain
    return replace(plain, state=plain.run(t_s, current_a)[1])


def model_key(model: AnyModel) -> str:
    """What makes two models the same: their file's text without the carried state."""
    return model.without_state().to_yaml_text()


@dataclass
class HistoryEntry:
    """A model that went in force: where it came from, why, when [s, the node's clock] and how well it predicted
    its held-out data when identified (% of the span; None: not known)."""

    model: AnyModel
    source: str
    reason: str
    since_s: float
    held_out_rms_pct: float | None = None

    def to_dict(self) -> dict[str, object]:
        """The report's form (without the model itself)."""
        return {"source": self.source, "reason": self.reason, "since_s": self.since_s,
                "held_out_rms_pct": self.held_out_rms_pct, "kind": getattr(self.model, "kind", "gpi")}


class ModelHistory:
    """The last `keep` models in force, newest last."""

    def __init__(self, keep: int) -> None:
        if keep < 2:
            raise InputError(f"the model history must keep at least 2 models (one to roll back to), got {keep}")
        self.keep = keep
        self.entries: list[HistoryEntry] = []

    def note(self, model: AnyModel, source: str, reason: str, now_s: float, held_out_rms_pct: float | None = None
             ) -> HistoryEntry | None:
        """A model went in force: the entry it now has (a model seen before moves to the end, with this time and
        reason), or None when it is the model in force already."""
        key = model_key(model)
        if self.entries and model_key(self.entries[-1].model) == key:
            return None
        earlier = next((entry for entry in self.entries if model_key(entry.model) == key), None)
        if earlier is not None:
            self.entries.remove(earlier)
            earlier.source, earlier.reason, earlier.since_s = source, reason, now_s
            held_out_rms_pct = earlier.held_out_rms_pct if held_out_rms_pct is None else held_out_rms_pct
            earlier.held_out_rms_pct = held_out_rms_pct
            entry = earlier
        else:
            entry = HistoryEntry(model.without_state(), source, reason, now_s, held_out_rms_pct)
        self.entries.append(entry)
        del self.entries[:-self.keep]
        return entry

    @property
    def current(self) -> HistoryEntry | None:
        return self.entries[-1] if self.entries else None

    @property
    def previous(self) -> HistoryEntry | None:
        """The model before the one in force (None: there is none)."""
        return self.entries[-2] if len(self.entries) >= 2 else None

    def to_report(self) -> list[dict[str, object]]:
        """Every entry's report form, oldest first."""
        return [entry.to_dict() for entry in self.entries]


@dataclass(frozen=True)
class SwapDecision:
    """Whether a candidate replaces the model in force, its and the model in force's errors on the held-out tail,
    and why, in one line."""

    swap: bool
    candidate: ErrorMetrics
    in_force: ErrorMetrics
    reason: str


def judge_swap(candidate: AnyModel, in_force: AnyModel, record: Series, scored_from: int) -> SwapDecision:
    """Compare two models on record's samples from scored_from on, each run from rest over the whole record."""
    measured = record.output[scored_from:]
    errors = [error_metrics(measured, model.without_state().predict(record.t, record.input)[scored_from:])
              for model in (candidate, in_force)]
    better = errors[0].rms_pct < errors[1].rms_pct
    held_out_s = float(record.t[-1] - record.t[scored_from])
    verdict = "swapped in" if better else "kept the model in force"
    reason = (f"{verdict}: on the last {held_out_s:.0f} s the candidate predicts at {errors[0].rms_pct:.3g} % RMS, "
              f"the model in force at {errors[1].rms_pct:.3g} %")
    return SwapDecision(better, errors[0], errors[1], reason)
