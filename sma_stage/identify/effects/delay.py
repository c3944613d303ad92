"""`delay`: the hysteresis sees u(t - d) (dead time d [s], linear interpolation between samples).
"""

from __future__ import annotations

import numpy as np

from sma_stage.identify.effects.base import (
    InputTransformEffect,
)
from sma_stage.model.effects import Effect


def delayed_input(t: np.ndarray, u: np.ndarray, delay_s: float) -> np.ndarray:
    """u(t - d) [A], linear between samples, from an idle stage (zero before the current was switched
    on): the delay effect's input transform."""
    return Effect("delay", {"delay_s": delay_s}).transform(t, u)[0]



EFFECT = InputTransformEffect("delay", "delay_s", lambda delay: Effect("delay", {"delay_s": delay}), relative_cost=5.9)
