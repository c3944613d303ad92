"""How a record starts, estimated from its data (sma_stage.identify.start)."""

from dataclasses import replace
from pathlib import Path

import independent_plant as plant
import numpy as np

from sma_stage.identify.start import estimate_start
from sma_stage.model import Effect, GPIParameters, load_model_file
from sma_stage.model.identified import IdentifiedModel, Start

DEFAULT_MODEL = load_model_file(Path(__file__).resolve().parents[1] / "config" / "model_default.yaml")
LAGGED = replace(DEFAULT_MODEL, effects=(Effect("thermal_lag", {"tau_s": 2.0}),), state=None)


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


def test_the_wires_free_start_after_a_history_reaches_the_noise_floor_with_the_true_model():
    """The independent plant's own hysteresis and wires (seed 1): the validation record follows an arbitrary
    history. Polished from the 3 best candidates the start stopped at 0.252 % of the span (turning point
    -5.8 A), 1.27 noise floors; the true start is at 5.0 A."""
    weights = np.exp(-plant.WEIGHT_DECAY_PER_M * plant.THRESHOLD_STEP_M * np.arange(plant.OPERATORS))
    loading, unloading = plant.LOADING, plant.UNLOADING
    hysteresis = GPIParameters(*loading, *unloading, a9=plant.THRESHOLD_STEP_M, a10=1.0 / weights.sum(),
                               a11=plant.WEIGHT_DECAY_PER_M)
    truth = plant.TRUTH["wire_thermal"]
    wires = Effect("wire_thermal", {"tau_a_s": truth["tau_a_s"], "tau_b_s": truth["tau_b_s"],
                                    "joule_reference_a": truth["reference_a"]})
    model = IdentifiedModel(hysteresis, plant.OPERATORS, (wires,))
    _, valid = plant.make_records("wire_thermal", seed=1)
    found = estimate_start(model, valid.t, valid.u, valid.y)
    rms_pct = 100.0 * np.sqrt(np.mean((found.predicted - valid.y) ** 2)) / np.ptp(valid.y)
    assert found.start.kind == "free"
    assert rms_pct <= 1.02 * valid.noise_floor_pct
