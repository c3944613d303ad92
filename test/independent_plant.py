"""Test-only records made without any of sma_stage: a hysteretic stage with one effect, started NOT from rest.

The generator imports nothing from the package (only `main`, which prints the table, calls `diagnose`). The
hysteresis is written out from its definition (play operators
between two tanh envelopes, weights decaying with the threshold); the effects are simulated as a
continuous plant would run them, on a grid FINE times finer than the recorded one:
- `thermal_lag`: the hysteresis sees the wire temperature, tau T' = u - T (classical fourth-order
  Runge-Kutta on the fine grid, the input interpolated linearly within a fine step);
- `delay`: the hysteresis sees u(t - d), the input signal evaluated exactly at t - d;
- `rate_multiplicative` / `rate_additive`: thresholds r_i (1 + c |du/dt|), or r_i + c |du/dt| (every
  operator, the first too), du/dt the signal's exact derivative;
- `drift`: a linear drift and a creep, k t + A (1 - exp(-t / tau_c)), added to the position;
- `wire_thermal`: two antagonistic wires, each heated only by its share of the current (u > 0 heats
  wire a, u < 0 wire b, Joule heating u^2 / u_ref), each cooling with its own time constant; the
  hysteresis sees the difference of the two temperatures.

Every record starts after a history: either held at its first current long enough to settle
(`start="held"`), or after an arbitrary earlier signal (`start="history"`). The plant is simulated from
rest HISTORY_S seconds before the first sample; only t >= 0 is recorded. Noise: NOISE_PCT % of the
recorded span, Gaussian.

`python test/independent_plant.py --seeds 0,1,2` prints the table in docs/identification_results.md.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

SAMPLE_PERIOD_S = 0.1
SAMPLES = 1200
FINE = 20
HISTORY_S = 60.0
NOISE_PCT = 0.2
OPERATORS = 12
THRESHOLD_STEP_M = 35e-6
WEIGHT_DECAY_PER_M = 2.5e3
LOADING = (0.50e-3, 0.45, -0.10, 0.45e-3)  # scale [m], gain [1/A], shift, offset [m]: s tanh(g v + h) + o
UNLOADING = (0.55e-3, 0.50, 0.15, 0.50e-3)
TRUTH: dict[str, dict[str, float]] = {
    "none": {},
    "thermal_lag": {"tau_s": 2.0},
    "delay": {"delay_s": 0.8},
    "rate_multiplicative": {"gain_s_per_A": 0.15},
    "rate_additive": {"gain_m_s_per_A": 12e-6},
    "drift": {"drift_m_per_s": 4e-7, "creep_m": 40e-6, "creep_tau_s": 15.0},
    "wire_thermal": {"tau_a_s": 1.5, "tau_b_s": 4.0, "reference_a": 5.0},
}

Signal = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class Record:
    """Time [s], current [A], noisy position [m], noise-free position [m], the noise sigma [m]."""

    t: np.ndarray
    u: np.ndarray
    y: np.ndarray
    clean: np.ndarray
    noise_sigma_m: float

    @property
    def noise_floor_pct(self) -> float:
        """The noise sigma in % of the recorded span: the RMS error a perfect model leaves."""
        return 100.0 * self.noise_sigma_m / float(np.ptp(self.y))


def identification_signal(t: np.ndarray) -> np.ndarray:
    """Current [A]: a slow sweep with a faster wave on it, so that minor loops of every size occur, over the validation signal's range; 5 A at
    t = 0."""
    return 3.5 * np.cos(2 * np.pi * t / 30.0) + 1.5 * np.cos(2 * np.pi * t / 6.1)


def validation_signal(t: np.ndarray) -> np.ndarray:
    """Current [A]: two cosines, 5 A at t = 0 (as the source paper's validation signal starts)."""
    return 2.5 * np.cos(2 * np.pi * t / 23.0) + 2.5 * np.cos(2 * np.pi * t / 8.3)


def with_history(signal: Signal, start: str, seed: int) -> Signal:
    """The signal for t >= 0; before it, the held first value (`held`) or an arbitrary earlier signal
    that joins it continuously at t = 0 (`history`), both from zero at t = -HISTORY_S."""
    first = float(signal(np.zeros(1))[0])
    rng = np.random.default_rng(1000 + seed)
    periods, phases, amplitudes = rng.uniform(3.0, 25.0, 3), rng.uniform(0, 2 * np.pi, 3), rng.uniform(0.8, 1.6, 3)

    def earlier(t: np.ndarray) -> np.ndarray:
        if start == "held":
            return np.full_like(t, first)
        wave = sum(a * np.sin(2 * np.pi * t / p + f) for a, p, f in zip(amplitudes, periods, phases, strict=True))
        at_zero = sum(a * np.sin(f) for a, f in zip(amplitudes, phases, strict=True))
        return np.clip(first + wave - at_zero, -5.0, 5.0)

    def joined(t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        ramp = np.clip((t + HISTORY_S) / 2.0, 0.0, 1.0)  # switched on from rest over 2 s
        return np.where(t >= 0.0, signal(np.maximum(t, 0.0)), ramp * earlier(np.minimum(t, 0.0)))

    return joined


def derivative(signal: Signal, t: np.ndarray) -> np.ndarray:
    """du/dt [A/s] by a central difference of the continuous signal (step 1e-5 s)."""
    step = 1e-5
    return (signal(t + step) - signal(t - step)) / (2 * step)


def first_order(t: np.ndarray, drive: np.ndarray, tau_s: float) -> np.ndarray:
    """tau x' = drive - x from x = 0, classical Runge-Kutta, the drive linear within each step."""
    x = np.empty_like(drive)
    x[0] = 0.0
    for k in range(1, t.size):
        h = t[k] - t[k - 1]
        d0, d1 = drive[k - 1], drive[k]
        dm = 0.5 * (d0 + d1)
        k1 = (d0 - x[k - 1]) / tau_s
        k2 = (dm - (x[k - 1] + 0.5 * h * k1)) / tau_s
        k3 = (dm - (x[k - 1] + 0.5 * h * k2)) / tau_s
        k4 = (d1 - (x[k - 1] + h * k3)) / tau_s
        x[k] = x[k - 1] + h * (k1 + 2 * k2 + 2 * k3 + k4) / 6.0
    return x


def envelope(values: tuple[float, float, float, float], v: np.ndarray) -> np.ndarray:
    scale, gain, shift, offset = values
    return scale * np.tanh(gain * v + shift) + offset


def hysteresis(v: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    """Weighted sum of play operators between the envelopes, from zero; thresholds (samples, operators) [m]."""
    low, high = envelope(LOADING, v), envelope(UNLOADING, v)
    nominal = THRESHOLD_STEP_M * np.arange(OPERATORS)
    weights = np.exp(-WEIGHT_DECAY_PER_M * nominal)
    weights /= weights.sum()
    z = np.zeros(OPERATORS)
    out = np.empty(v.size)
    for k in range(v.size):
        z = np.maximum(low[k] - thresholds[k], np.minimum(high[k] + thresholds[k], z))
        out[k] = weights @ z
    return out


def position(effect: str, signal: Signal, t: np.ndarray) -> np.ndarray:
    """Noise-free position [m] on the fine grid t (starting at rest at t[0])."""
    values = TRUTH[effect]
    u = signal(t)
    nominal = THRESHOLD_STEP_M * np.arange(OPERATORS)
    thresholds = np.broadcast_to(nominal, (t.size, OPERATORS))
    v = u
    if effect == "thermal_lag":
        v = first_order(t, u, values["tau_s"])
    elif effect == "delay":
        v = signal(t - values["delay_s"])
    elif effect == "rate_multiplicative":
        thresholds = nominal[None, :] * (1.0 + values["gain_s_per_A"] * np.abs(derivative(signal, t))[:, None])
    elif effect == "rate_additive":
        thresholds = nominal[None, :] + values["gain_m_s_per_A"] * np.abs(derivative(signal, t))[:, None]
    elif effect == "wire_thermal":
        reference = values["reference_a"]
        wire_a = first_order(t, np.where(u > 0.0, u * u / reference, 0.0), values["tau_a_s"])
        wire_b = first_order(t, np.where(u < 0.0, u * u / reference, 0.0), values["tau_b_s"])
        v = wire_a - wire_b
    y = hysteresis(v, np.ascontiguousarray(thresholds))
    if effect == "drift":
        elapsed = np.maximum(t, 0.0)
        y = y + values["drift_m_per_s"] * elapsed + values["creep_m"] * -np.expm1(-elapsed / values["creep_tau_s"])
    return y


def record(effect: str, signal: Signal, start: str, seed: int, noise_seed: int) -> Record:
    """One record of SAMPLES samples every SAMPLE_PERIOD_S from t = 0, after its history."""
    step = SAMPLE_PERIOD_S / FINE
    fine_t = np.arange(-round(HISTORY_S / step), SAMPLES * FINE) * step
    fine_y = position(effect, with_history(signal, start, seed), fine_t)
    first = round(HISTORY_S / step)
    pick = slice(first, None, FINE)
    t, clean = fine_t[pick].copy(), fine_y[pick].copy()
    sigma = NOISE_PCT / 100.0 * float(np.ptp(clean))
    noisy = clean + np.random.default_rng(noise_seed).normal(0.0, sigma, clean.size)
    return Record(t, signal(t), noisy, clean, sigma)


def make_records(effect: str, seed: int = 0) -> tuple[Record, Record]:
    """(identification record held at 5 A before it, validation record after an arbitrary history)."""
    if effect not in TRUTH:
        raise ValueError(f"unknown effect {effect!r}")
    return (record(effect, identification_signal, "held", seed, 2 * seed),
            record(effect, validation_signal, "history", seed, 2 * seed + 1))


def main(argv: list[str] | None = None) -> None:
    """Print a Markdown table of `diagnose` on every effect and seed."""
    import argparse
    import time

    from sma_stage.identify.diagnosis import diagnose

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("--seeds", default="0,1,2", help="comma-separated seeds")
    parser.add_argument("--effects", default=",".join(TRUTH), help="comma-separated effects")
    parser.add_argument("--workers", type=int, default=1, help="diagnose's worker processes (the same result)")
    args = parser.parse_args(argv)
    print("| seed | plant | named | starts (ident, valid) | valid. RMS before % | after % | floor % | after / floor "
          "| max after % | parameters | s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for seed in (int(s) for s in args.seeds.split(",")):
        for effect in args.effects.split(","):
            ident, valid = make_records(effect, seed)
            started = time.perf_counter()
            result = diagnose((ident.t, ident.u, ident.y), (valid.t, valid.u, valid.y), workers=args.workers)
            floor = valid.noise_floor_pct
            starts = {record: found.start.kind for record, found in result.starts.items()}
            parameters = ", ".join(f"{name} = {value:.4g}" for name, value in result.parameters.items())
            print(f"| {seed} | {effect} | {' + '.join(result.effects) or 'none'} "
                  f"| {starts.get('identification', 'rest')}, {starts.get('validation', 'rest')} "
                  f"| {result.before.rms_pct:.3f} | {result.after.rms_pct:.3f} | {floor:.3f} "
                  f"| {result.after.rms_pct / floor:.2f} | {result.after.max_pct:.2f} | {parameters} "
                  f"| {time.perf_counter() - started:.1f} |", flush=True)


if __name__ == "__main__":
    main()
