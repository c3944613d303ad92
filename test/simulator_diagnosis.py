"""Test-only data: records of the stage simulator (sma_stage.plant, a physical model with no GPI inside)
with an effect switched on, and a table of what `diagnose` names on them (docs/identification_results.md).

    PYTHONPATH=. python test/simulator_diagnosis.py --order paper --effects none,sensor_delay_s=8
    PYTHONPATH=. python test/simulator_diagnosis.py --effects sensor_delay_s=3 --delay-profile 0,3,6
"""

from __future__ import annotations

import numpy as np

from sma_stage.plant import Effects, simulate
from sma_stage.signals import paper_identification_signal, paper_validation_signal

STEP_S = 0.1  # the simulator's step
RECORD_EVERY = 10  # recorded at 1 Hz
DURATION_S = 1000.0
ORDERS = {"paper": (paper_identification_signal, paper_validation_signal),
          "swapped": (paper_validation_signal, paper_identification_signal)}


def simulator_record(signal, effects: Effects, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t [s], current [A], measured position [m]) of a run from an idle stage."""
    t = np.arange(1, round(DURATION_S / STEP_S) + 1) * STEP_S
    run = simulate(signal(t - STEP_S), STEP_S, effects=effects, seed=seed)
    keep = slice(RECORD_EVERY - 1, None, RECORD_EVERY)
    return run.t_s[keep], run.current_a[keep], run.measured_position_m[keep]


def records(effects: Effects, order: str) -> tuple[tuple, tuple]:
    """Identification (seed 1) and validation (seed 2) records; order "paper" identifies on the decaying
    sine and validates on the two cosines, "swapped" the other way round."""
    first, second = ORDERS[order]
    return simulator_record(first, effects, seed=1), simulator_record(second, effects, seed=2)


def parse_effects(text: str) -> Effects:
    """`none` or name=value pairs joined by `;` (Effects fields)."""
    if text == "none":
        return Effects()
    return Effects(**{name: float(value) for name, value in (pair.split("=") for pair in text.split(";"))})


def delay_profile(effects: Effects, order: str, delays: list[float]) -> None:
    """Print, for each dead time d [s] put in front of the wires, wire_thermal fitted on the identification
    record from rest (its GPI at the plain fit's count) and the validation RMS of the whole model: how
    much a delay on top of the wires helps on each record, whatever the greedy rounds find."""
    from sma_stage.identify.chain import Chain, Validation
    from sma_stage.identify.effects import fit_effect, no_effect
    from sma_stage.identify.effects.base import finish_fit
    from sma_stage.identify.effects.delay import EFFECT as DELAY
    from sma_stage.identify.fit import fit_gpi

    (t, u, y), valid = records(effects, order)
    validation, base = Validation(*valid), fit_gpi(u, y)
    print("| delay d s | wires tau_a, tau_b s | identification RMS % | validation RMS % |")
    print("|---|---|---|---|")
    for delay in delays:
        delayed = DELAY.transform(t, u, delay, "rest") if delay > 0.0 else u
        start = fit_gpi(delayed, y, operators=base.operators, initial=base.parameters)
        wires = fit_effect("wire_thermal", t, delayed, y, start, starts=("rest",))
        stages = [no_effect(t, u, y, base)]
        if delay > 0.0:
            stages.append(finish_fit("delay", {"delay_s": delay}, start.parameters, start.operators, y, start.predicted,
                                     start.parameter_count + 1, 0.0))
        chain = Chain((*stages, wires), base)
        errors = validation.errors(validation.predict(chain.model, chain.start).predicted)
        print(f"| {delay:g} | {wires.parameters['tau_a_s']:.2f}, {wires.parameters['tau_b_s']:.2f} "
              f"| {wires.identification.rms_pct:.3f} | {errors.rms_pct:.3f} |", flush=True)


def main(argv: list[str] | None = None) -> None:
    """Print a Markdown table of `diagnose` on simulator records with each effect switched on."""
    import argparse
    import time

    from sma_stage.identify.diagnosis import diagnose

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("--order", choices=sorted(ORDERS), default="paper")
    parser.add_argument("--workers", type=int, default=1, help="diagnose's worker processes (the same result)")
    parser.add_argument("--effects", default="none,sensor_delay_s=3,sensor_delay_s=8",
                        help="comma-separated: none or name=value[;name=value] (sma_stage.plant.Effects fields)")
    parser.add_argument("--delay-profile", default="",
                        help="comma-separated dead times [s]: print delay_profile for each --effects entry instead")
    args = parser.parse_args(argv)
    if args.delay_profile:
        for text in args.effects.split(","):
            print(f"\n{text}, {args.order} order:\n")
            delay_profile(parse_effects(text), args.order, [float(d) for d in args.delay_profile.split(",")])
        return
    print("| switched on | named (in order) | parameters | validation RMS before -> after | CPU s |")
    print("|---|---|---|---|---|")
    for text in args.effects.split(","):
        started = time.process_time()
        result = diagnose(*records(parse_effects(text), args.order), workers=args.workers)
        parameters = ", ".join(f"{name} = {value:.4g}" for name, value in result.parameters.items())
        print(f"| {text} | {', '.join(result.effects) or 'none'} | {parameters} | {result.before.rms_pct:.2f} % -> "
              f"{result.after.rms_pct:.2f} % | {time.process_time() - started:.0f} |", flush=True)


if __name__ == "__main__":
    main()
