"""For each effect the diagnosis can name: does the model `gpi_tool diagnose --out` writes track better
than the plain GPI, once the compensator runs it?

Per effect, test/synthetic.py (a GPI plant written independently of the package, simulated 10x finer
than it is sampled, 2 um noise) makes the identification record (the paper's decaying sine, 1000 s at
1 Hz) and the validation record (the paper's two cosines). `gpi_tool diagnose IDENT --validate VALID
--families gpi --out DIR` identifies (the GPI's diagnosis, whose effects are measured here); sma_stage.control.Compensator loads DIR/model.yaml (the identified model, with the
state the identification record left) and, for comparison, the plain GPI of DIR/report.json (run over the
identification record for its state too). Each then commands the same plant, continuing from the end of
the identification record, feedforward every second for 1000 s: a setpoint at the bottom of 80 % of the
stroke for 60 s, at the signal's first value for 60 s, then the paper's validation signal scaled to it.
Error: the plant's noise-free position at the end of each command's second against that command's
setpoint, over the signal, in % of the stroke.

    .venv/bin/python bench/bench_effect_tracking.py [--effects none,thermal_lag,...] [--seed 0]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from record_results import recorded

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))
import synthetic  # noqa: E402  -- the test-only plant, independent of the package's effect code

from sma_stage.cli import main as gpi_tool  # noqa: E402
from sma_stage.control import Compensator  # noqa: E402
from sma_stage.io import make_series  # noqa: E402
from sma_stage.io.csv_io import write_csv  # noqa: E402
from sma_stage.model import GPIParameters, IdentifiedModel, load_model_file  # noqa: E402
from sma_stage.signals import paper_identification_signal, paper_validation_signal  # noqa: E402

STEP_S = synthetic.SAMPLE_PERIOD_S
TRACK_S = 1000.0
SETTLE_S = 60.0
STROKE_FRACTION = 0.8
MAX_CURRENT_A = 5.0
EFFECTS = ("none", "thermal_lag", "delay", "rate", "drift")


def diagnose_with_gpi_tool(case: synthetic.Case, folder: Path) -> tuple[IdentifiedModel, IdentifiedModel, dict]:
    """(the identified model gpi_tool wrote, the plain GPI of its report, the report)."""
    paths = []
    for name, data in (("ident", case.identification), ("valid", case.validation)):
        path = folder / f"{name}.csv"
        write_csv(path, make_series(data.t, data.u, data.y, name))
        paths.append(str(path))
    out = folder / "diagnosis"
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        status = gpi_tool(["diagnose", paths[0], "--validate", paths[1], "--families", "gpi", "--out", str(out),
                           "--json"])
    if status != 0:
        raise SystemExit(f"gpi_tool diagnose failed with status {status}")
    report = json.loads((out / "report.json").read_text())
    plain = IdentifiedModel(GPIParameters.from_dict(report["gpi_fit"]["parameters"]), report["gpi_fit"]["operators"])
    ident = case.identification
    _, state = plain.run(ident.t, ident.u)
    return load_model_file(out / "model.yaml"), IdentifiedModel(plain.parameters, plain.operators, (), state), report


def setpoints(stroke: tuple[float, float], steps: int) -> np.ndarray:
    """Setpoint [m] of each command: SETTLE_S at the bottom, SETTLE_S at the signal's start, the signal."""
    low, high = stroke
    middle, half_span = 0.5 * (low + high), 0.5 * STROKE_FRACTION * (high - low)
    t = STEP_S * np.arange(steps)
    shape = paper_validation_signal(np.maximum(t - 2.0 * SETTLE_S, 0.0)) / 5.0
    return np.where(t < SETTLE_S, middle - half_span, middle + half_span * shape)


def track(case: synthetic.Case, model: IdentifiedModel, wanted: np.ndarray) -> tuple[float, float]:
    """(RMS, max) error [% of stroke] of the plant commanded feedforward by the compensator with model."""
    compensator = Compensator(model, MAX_CURRENT_A)
    currents = np.array([compensator.command(target, None, STEP_S if k else 0.0) for k, target in enumerate(wanted)])
    ident_end = float(case.identification.t[-1])
    fine_step = STEP_S / synthetic.OVERSAMPLING
    fine_t = np.arange(-STEP_S, ident_end + currents.size * STEP_S + 1e-9, fine_step)
    command_index = np.clip(np.ceil((fine_t - ident_end) / STEP_S - 1e-9).astype(int) - 1, 0, currents.size - 1)
    fine_u = np.where(fine_t <= ident_end, paper_identification_signal(np.maximum(fine_t, 0.0)),
                      currents[command_index])
    position = synthetic.plant_output(fine_t, fine_u, case.effect, case.truth)
    if case.effect == "drift":
        position = position + case.truth["drift_m_per_s"] * fine_t
    ends = ident_end + STEP_S * np.arange(1, currents.size + 1)
    reached = np.interp(ends, fine_t, position)
    on_signal = STEP_S * np.arange(currents.size) >= 2.0 * SETTLE_S
    span = np.ptp(case.identification.clean)
    error = 100.0 * (reached - wanted)[on_signal] / span
    return float(np.sqrt(np.mean(error**2))), float(np.max(np.abs(error)))


def main() -> int:
    """Print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--effects", default=",".join(EFFECTS), help="comma-separated effects of the plant")
    parser.add_argument("--seed", type=int, default=0, help="noise seed of test/synthetic.py")
    args = parser.parse_args()
    print("| plant's effect | named by gpi_tool diagnose | plain GPI RMS (max) % | identified model RMS (max) % "
          "| identified / plain | seconds |")
    print("|---|---|---|---|---|---|")
    for effect in args.effects.split(","):
        started = time.perf_counter()
        case = synthetic.make_case(effect, seed=args.seed)
        with tempfile.TemporaryDirectory() as folder:
            identified, plain, report = diagnose_with_gpi_tool(case, Path(folder))
        stroke = (float(case.identification.clean.min()), float(case.identification.clean.max()))
        wanted = setpoints(stroke, int(round(TRACK_S / STEP_S)))
        plain_rms, plain_max = track(case, plain, wanted)
        rms, peak = track(case, identified, wanted)
        named = " + ".join(report["diagnosis"]["effects"]) or "none"
        print(f"| {effect} | {named} | {plain_rms:.3f} ({plain_max:.2f}) | {rms:.3f} ({peak:.2f}) "
              f"| {rms / plain_rms:.2f} | {time.perf_counter() - started:.0f} |", flush=True)
    return 0


if __name__ == "__main__":
    with recorded(__file__):
        raise SystemExit(main())
