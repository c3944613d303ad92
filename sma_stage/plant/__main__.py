"""Print the simulated stage's stroke, loop width and speed: `python -m sma_stage.plant [--rate HZ]`."""

import argparse
import time

import numpy as np

from sma_stage.plant import StageConfig, simulate
from sma_stage.signals import IDENTIFICATION_DURATION_S, IDENTIFICATION_PERIOD_S, paper_identification_signal


def loop_widths(current: np.ndarray, position: np.ndarray) -> tuple[float, float]:
    """Largest and zero-current gap [m] between the rising and falling branches of one trough-to-trough cycle."""
    peak = int(np.argmax(current))
    rising_i, rising_x = current[: peak + 1], position[: peak + 1]
    falling_i, falling_x = current[peak:][::-1], position[peak:][::-1]
    grid = np.linspace(max(rising_i[0], falling_i[0]), current[peak], 501)
    gap = np.interp(grid, falling_i, falling_x) - np.interp(grid, rising_i, rising_x)
    return float(np.abs(gap).max()), float(np.interp(0.0, grid, gap))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--rate", type=float, default=100.0, help="sample rate [Hz] (default 100)")
    args = parser.parse_args()
    dt = 1.0 / args.rate
    t = np.arange(0.0, IDENTIFICATION_DURATION_S, dt)
    current = paper_identification_signal(t)
    simulate(current[:10], dt)
    start = time.perf_counter()
    result = simulate(current, dt)
    wall = time.perf_counter() - start
    period = IDENTIFICATION_PERIOD_S
    keep = (t >= 0.75 * period) & (t < 1.75 * period)
    stroke = float(np.ptp(result.position_m[keep]))
    widest, at_zero = loop_widths(current[keep], result.position_m[keep])
    config = StageConfig()
    print(f"paper identification signal, {t.size} samples at {args.rate:g} Hz ({t[-1] + dt:g} s simulated)")
    print(f"wall time {wall:.3f} s = {t.size / wall:,.0f} steps/s = {(t[-1] + dt) / wall:,.0f} x real time")
    print(f"position range over the run {result.position_m.min() * 1e6:.1f} .. {result.position_m.max() * 1e6:.1f} um")
    print(f"major loop (0.75-1.75 periods, 5 A): stroke {stroke * 1e6:.1f} um, widest gap {widest * 1e6:.1f} um "
          f"({100 * widest / stroke:.0f} % of stroke), gap at 0 A {at_zero * 1e6:.1f} um "
          f"({100 * at_zero / stroke:.0f} %)")
    print(f"wire temperature peak {result.wire_temperatures_k.max():.1f} K, thermal time constant "
          f"{config.thermal_time_constant_s:.1f} s")


if __name__ == "__main__":
    main()
