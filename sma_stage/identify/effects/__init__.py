"""Candidate effects the plain GPI lacks, each a model with the GPI inside, fitted from the base fit: one
module per effect, each defining EFFECT (a base.Candidate), found here by their modules, so adding an
effect is adding a module (and its forward model, the kind in sma_stage.model.effects, which the
compensator steps too).

Every effect has `fit(t, u, y, base)` (at the base fit's operator count) and `recount(fit, t, u, y)`
(the operator count chosen again). Time t is in s (or samples for quasi-static data), u in A, y in the
output unit (m).
"""

from __future__ import annotations

import importlib
import pkgutil
import time

import numpy as np

from sma_stage.errors import InputError
from sma_stage.identify.effects.base import (
    FITTED_STARTS,
    Candidate,
    EffectFit,
    NotFitted,
    Progress,
    attempt,
    check_record,
    finish_fit,
    lowest_cost,
)
from sma_stage.identify.fit import FitResult
from sma_stage.model.effects import EFFECT_KINDS

__all__ = ["EFFECTS", "EFFECT_NAMES", "FITTED_STARTS", "EffectFit", "NotFitted", "attempt", "check_record", "fit_effect",
           "lowest_cost", "no_effect", "recount_effect"]


def _discover() -> dict[str, Candidate]:
    """Each effect module's EFFECT, in the order of EFFECT_KINDS; ImportError if a kind has no module."""
    found = {}
    for module in pkgutil.iter_modules(__path__):
        if module.name != "base":
            effect = getattr(importlib.import_module(f"{__name__}.{module.name}"), "EFFECT", None)
            if isinstance(effect, Candidate):
                found[effect.name] = effect
    missing = [kind for kind in EFFECT_KINDS if kind not in found]
    if missing:
        raise ImportError(f"no identification module defines the effect {missing[0]!r}")
    return {kind: found[kind] for kind in EFFECT_KINDS}


EFFECTS: dict[str, Candidate] = _discover()
EFFECT_NAMES: tuple[str, ...] = tuple(EFFECTS)


def fit_effect(name: str, t: np.ndarray, u: np.ndarray, y: np.ndarray, base: FitResult,
               progress: Progress = None, starts: tuple[str, ...] = FITTED_STARTS) -> EffectFit:
    """Fit the candidate effect `name` on (t [s], u [A], y) from the base GPI fit (its operator count), the
    record starting as the best of `starts` (rest, held)."""
    if name not in EFFECTS:
        raise InputError(f"unknown effect {name!r}; known: {', '.join(EFFECT_NAMES)}")
    t, u, y = check_record(t, u, y)
    return EFFECTS[name].fit(t, u, y, base, progress, starts)


def recount_effect(fit: EffectFit, t: np.ndarray, u: np.ndarray, y: np.ndarray,
                   progress: Progress = None) -> EffectFit:
    """The fitted effect with its operator count chosen again (fit_gpi's rule); fit itself if unchanged."""
    t, u, y = check_record(t, u, y)
    return EFFECTS[fit.effect].recount(fit, t, u, y, progress)


def refit_effect(fit: EffectFit, t: np.ndarray, u: np.ndarray, y: np.ndarray, base: FitResult,
                 progress: Progress = None) -> EffectFit:
    """The fitted effect fitted again on (t, u, y) from base, near where it was (Candidate.refit)."""
    t, u, y = check_record(t, u, y)
    return EFFECTS[fit.effect].refit(fit, t, u, y, base, progress)


def no_effect(t: np.ndarray, u: np.ndarray, y: np.ndarray, base: FitResult) -> EffectFit:
    """The plain GPI in the same form as the candidates (no extra parameter)."""
    t, u, y = check_record(t, u, y)
    return finish_fit("none", {}, base.parameters, base.operators, y, base.predicted, base.parameter_count,
                   time.perf_counter())

