"""Test-only data: a GPI plant with one effect injected, written independently of sma_stage.identify.effects.

The plant is simulated on a time grid OVERSAMPLING times finer than the recorded one (as a
continuous plant would run) and then sampled; Gaussian noise of known sigma [m] is added to the
recorded output. Each record starts from an idle stage (operators at zero) whose current is switched
on one sample period before the first recorded sample.
Nothing here is shared with the identification, which is never told the effect.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import signal as sps

from sma_stage.model import GPIParameters
from sma_stage.signals import paper_identification_signal, paper_validation_signal

TRUE_PARAMETERS = GPIParameters(
    a1=0.70e-3, a2=0.55, a3=0.15, a4=0.54e-3,
    a5=0.68e-3, a6=0.65, a7=-0.2, a8=0.78e-3,
    a9=60e-6, a10=0.22, a11=2.5e3,
)
TRUE_OPERATORS = 10
SAMPLE_PERIOD_S = 1.0
DURATION_S = 1000.0
OVERSAMPLING = 10
NOISE_SIGMA_M = 2e-6

DEFAULT_EFFECTS: dict[str, dict[str, float]] = {
    "none": {},
    "thermal_lag": {"tau_s": 20.0},
    "delay": {"delay_s": 4.5},
    "rate": {"rate_gain_s_per_A": 5.0},
    "drift": {"drift_m_per_s": 5e-8},
}


@dataclass(frozen=True)
class Record:
    """One recorded experiment: time [s], current [A], noisy position [m], noise-free position [m]."""

    t: np.ndarray
    u: np.ndarray
    y: np.ndarray
    clean: np.ndarray
    noise_sigma_m: float

    @property
    def noise_floor_pct(self) -> float:
        """The noise sigma in % of the recorded output's span: the best RMS error any model can reach."""
        return 100.0 * self.noise_sigma_m / float(np.ptp(self.y))


@dataclass(frozen=True)
class Case:
    """Identification and validation records of one plant, and the injected effect (the truth)."""

    effect: str
    truth: dict[str, float]
    identification: Record
    validation: Record
    extra: dict = field(default_factory=dict)


def play_outputs(v: np.ndarray, thresholds: np.ndarray, params: GPIParameters = TRUE_PARAMETERS) -> np.ndarray:
    """y_k = sum_i p_i z_ik with z_ik = max(gl(v_k) - r_ik, min(gr(v_k) + r_ik, z_i,k-1)), z starting at 0.

    thresholds is (samples, operators) [m]; the weights p_i use the nominal thresholds a9 i.
    """
    low = params.envelope_left(v)
    high = params.envelope_right(v)
    weights = params.densities(thresholds.shape[1])
    z = np.zeros(thresholds.shape[1])
    out = np.empty(v.size)
    for k in range(v.size):
        z = np.maximum(low[k] - thresholds[k], np.minimum(high[k] + thresholds[k], z))
        out[k] = weights @ z
    return out


def first_order_lag(t: np.ndarray, u: np.ndarray, tau_s: float) -> np.ndarray:
    """v' = (u - v)/tau (scipy's lsim on the fine grid), from v = 0: the stage was idle, the current
    steps to u[0] at t[0]."""
    _, filtered, _ = sps.lsim(([1.0], [tau_s, 1.0]), u, t - t[0], X0=[0.0])
    return filtered


def plant_output(t: np.ndarray, u: np.ndarray, effect: str, values: dict[str, float]) -> np.ndarray:
    """The noise-free position [m] of the plant with the effect (drift is added by `record`), on the fine
    grid t; the stage is idle before t[0]. Several effects joined by "+" act in the order written."""
    nominal = TRUE_PARAMETERS.thresholds(TRUE_OPERATORS)
    thresholds = np.broadcast_to(nominal, (t.size, TRUE_OPERATORS))
    drive = u
    for name in effect.split("+"):
        if name == "thermal_lag":
            drive = first_order_lag(t, drive, values["tau_s"])
        elif name == "delay":
            drive = np.interp(t - values["delay_s"], t, drive, left=0.0)
        elif name == "rate":
            rate = np.abs(np.gradient(drive, t))
            thresholds = nominal[None, :] * (1.0 + values["rate_gain_s_per_A"] * rate[:, None])
        elif name not in ("none", "drift"):
            raise ValueError(f"unknown effect {name!r}")
    return play_outputs(drive, np.ascontiguousarray(thresholds))


def record(input_signal, effect: str, values: dict[str, float], rng: np.random.Generator,
           noise_sigma_m: float, sample_period_s: float, duration_s: float) -> Record:
    """Simulate finely from an idle stage whose current is switched on one sample period before the
    first recorded sample (held at its first value until then, as a zero-order-hold source delivers
    it), sample every sample_period_s from t = 0, add noise."""
    fine_t = np.arange(-sample_period_s, duration_s + 1e-9, sample_period_s / OVERSAMPLING)
    fine_u = input_signal(np.maximum(fine_t, 0.0))
    fine_y = plant_output(fine_t, fine_u, effect, values)
    pick = slice(OVERSAMPLING, None, OVERSAMPLING)
    t, clean = fine_t[pick].copy(), fine_y[pick].copy()
    if "drift" in effect.split("+"):
        clean += values.get("drift_m_per_s", 0.0) * t
        clean += values.get("creep_m", 0.0) * (1.0 - np.exp(-t / values.get("creep_tau_s", 1.0)))
    noisy = clean + rng.normal(0.0, noise_sigma_m, clean.size)
    return Record(t, fine_u[pick].copy(), noisy, clean, noise_sigma_m)


def make_case(effect: str, seed: int = 0, noise_sigma_m: float = NOISE_SIGMA_M,
              sample_period_s: float = SAMPLE_PERIOD_S, duration_s: float = DURATION_S,
              **values: float) -> Case:
    """Identification (paper's decaying sine) and validation (paper's two cosines) records with the effect."""
    truth = dict(values) or {key: value for name in effect.split("+") for key, value in DEFAULT_EFFECTS[name].items()}
    rng = np.random.default_rng(seed)
    ident = record(paper_identification_signal, effect, truth, rng, noise_sigma_m, sample_period_s, duration_s)
    valid = record(paper_validation_signal, effect, truth, rng, noise_sigma_m, sample_period_s, duration_s)
    return Case(effect, truth, ident, valid)


def main(argv: list[str] | None = None) -> None:
    """Print a Markdown table of `diagnose` on every case and seed (the numbers in docs/identification_results.md)."""
    import argparse
    import time

    from sma_stage.identify.diagnosis import diagnose

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("--seeds", default="0,1,2,3,4", help="comma-separated noise seeds")
    parser.add_argument("--effects", default=",".join(DEFAULT_EFFECTS), help="comma-separated injected effects")
    args = parser.parse_args(argv)
    print("| seed | injected | named | validation RMS before % | after % | noise floor % | after / floor "
          "| parameters | operators | CPU s |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for seed in (int(s) for s in args.seeds.split(",")):
        for effect in args.effects.split(","):
            case = make_case(effect, seed=seed)
            ident, valid = case.identification, case.validation
            started = time.process_time()
            result = diagnose((ident.t, ident.u, ident.y), (valid.t, valid.u, valid.y))
            floor = valid.noise_floor_pct
            parameters = ", ".join(f"{name} = {value:.4g}" for name, value in result.parameters.items())
            named = " + ".join(result.effects) or "none"
            print(f"| {seed} | {effect} | {named} | {result.before.rms_pct:.3f} | {result.after.rms_pct:.3f} "
                  f"| {floor:.3f} | {result.after.rms_pct / floor:.2f} | {parameters} "
                  f"| {result.base.operators} -> {result.chosen.operators} "
                  f"| {time.process_time() - started:.1f} |", flush=True)


if __name__ == "__main__":
    main()
