"""How a record starts, estimated from its data (sma_stage.identify.start)."""

from dataclasses import replace
from pathlib import Path

import numpy as np

from sma_stage.identify.start import estimate_start
from sma_stage.model import Effect, load_model_file
from sma_stage.model.identified import Start

LAGGED = replace(load_model_file(Path(__file__).resolve().parents[1] / "config" / "model_default.yaml"), effects=(Effect("thermal_lag", {"tau_s": 2.0}),),
                 state=None)


def test_a_free_start_whose_turning_point_the_first_sample_does_not_wipe_out_is_found():
    """Turning point 5 A above the lag's 3.45 A: below the lag's value the SSR is flat in the turning point,
    where a single polish from the best grid point stopped (0.25 % of the span off the truth)."""
    t = np.arange(1200) * 0.1
    u = 2.5 * np.cos(2 * np.pi * t / 23.0) + 2.5 * np.cos(2 * np.pi * t / 8.3)
    clean = LAGGED.predict_from(t, u, Start("free", (5.0, 3.45)))
    span = float(np.ptp(clean))
    measured = clean + np.random.default_rng(0).normal(0.0, 0.002 * span, t.size)
    found = estimate_start(LAGGED, t, u, measured)
    assert found.start.kind == "free"
    assert np.sqrt(np.mean((found.predicted - clean) ** 2)) < 0.0005 * span
    assert abs(found.start.values[0] - 5.0) < 0.2 and abs(found.start.values[1] - 3.45) < 0.1
