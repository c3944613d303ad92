"""The two-wire model's costs, side by side with the GPI's in one run; prints a table.

    .venv/bin/python bench/bench_two_wire.py [--calls 20000]

Per call as a compensator makes them, one sample at a time: the two-wire exact inverse (`command_for`: regula falsi
over the current, each trial one held step of both wires' plays and the output layer) and the GPI's streaming exact
inverse (20 operators); then the package's whole control core (`Compensator.command`, feedforward at 100 Hz: the
model's states advanced, the inverse, the lead, the rate limit) with each family's model; latency percentiles
(target for the two-wire model: p99 <= 20 us); the forward model over a record (samples per second); and
`fit_two_wire` on the second physical stage's paper identification record.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from record_results import recorded

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "test"))

from sma_stage.control.compensator import Compensator  # noqa: E402
from sma_stage.model import Effect, GPIInverseStream, GPIParameters, IdentifiedModel  # noqa: E402
from sma_stage.model.two_wire import TwoWireModel, TwoWireParameters  # noqa: E402

STAGE_GPI = GPIParameters(a1=0.5e-3, a2=0.6, a3=0.1, a4=0.0, a5=0.5e-3, a6=0.6, a7=-0.2, a8=0.05e-3,
                          a9=0.05e-3, a10=0.2, a11=5e3)
TWO_WIRE = TwoWireModel(TwoWireParameters(
    {"tau_a_s": 3.5, "tau_b_s": 3.6, "heating_reference_a": 4.9, "coupling_a": 2500.0, "coupling_b": 4300.0,
     "centre_a": 1.9, "centre_b": 1.5, "width_a": 1.36, "width_b": 1.05, "hysteresis_a": 1.26, "hysteresis_b": 0.96,
     "stroke_a": 4.2e-4, "stroke_b": 3.1e-4, "offset": -1.6e-5, "output_threshold": 1.4e-4, "resistance_drop": 0.4},
    (0.26, 1.13, 0.0, 0.14), (0.21, 1.39, 0.0, 0.1), (0.3, 0.37, 0.34, 0.63, 0.18)))


def latencies(call, targets: np.ndarray) -> np.ndarray:
    """Seconds per call over targets (after a warm-up)."""
    for target in targets[:200]:
        call(target)
    out = np.empty(targets.size)
    for k, target in enumerate(targets):
        started = time.perf_counter()
        call(target)
        out[k] = time.perf_counter() - started
    return out


def row(name: str, seconds: np.ndarray) -> str:
    us = 1e6 * seconds
    return f"| {name} | {np.median(us):.1f} | {np.percentile(us, 99):.1f} | {us.max():.1f} |"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=20000)
    args = parser.parse_args()
    t = np.arange(args.calls) * 0.01
    span = 6e-4
    targets = 0.4 * span * np.sin(2 * np.pi * t / 30.0)
    stream = TWO_WIRE.stream(max_current_a=5.0)
    two_wire = latencies(lambda target: stream.command_for(target, 0.01), targets)
    gpi = GPIInverseStream(STAGE_GPI, 20)
    gpi_targets = 0.5 * (STAGE_GPI.a1 + STAGE_GPI.a5) * 0.8 * np.sin(2 * np.pi * t / 30.0)
    gpi_latency = latencies(gpi.step, gpi_targets)
    print(f"{args.calls} calls each, one sample per call\n")
    print("| inverse | median [us] | p99 [us] | max [us] |\n|---|---|---|---|")
    print(row("two-wire command_for (4+4 operators, 5 output operators)", two_wire))
    print(row("GPI exact inverse step (20 operators)", gpi_latency))
    lagged_gpi = IdentifiedModel(STAGE_GPI, 20, (Effect("thermal_lag", {"tau_s": 3.6}),))
    for name, model, family_targets in (("two-wire model", TWO_WIRE, targets),
                                        ("GPI (20 operators) + thermal_lag", lagged_gpi, gpi_targets)):
        command = Compensator(model, 5.0).command
        print(row(f"Compensator.command, {name}", latencies(lambda target, command=command: command(target, dt_s=0.01),
                                                            family_targets)))
    record_t = np.arange(0.0, 2000.0, 0.01)
    record_u = 5.0 * np.sin(2 * np.pi * record_t / 250.0)
    TWO_WIRE.predict(record_t[:100], record_u[:100])
    started = time.perf_counter()
    TWO_WIRE.predict(record_t, record_u)
    forward_s = time.perf_counter() - started
    print(f"\nforward over {record_t.size:,} samples: {forward_s * 1e3:.1f} ms ({record_t.size / forward_s:,.0f} samples/s)")
    from antagonistic_plant import VARIANTS, records

    from sma_stage.identify.two_wire import fit_two_wire

    t_i, u_i, y_i = records(VARIANTS["nominal"])["identification"]
    found = fit_two_wire(t_i, u_i, y_i)
    print(f"fit_two_wire on the second stage's paper identification record ({t_i.size} samples): "
          f"{found.seconds:.1f} s, {found.evaluations} evaluations, identification RMS {found.errors.rms_pct:.2f} %")


if __name__ == "__main__":
    with recorded(__file__):
        main()
