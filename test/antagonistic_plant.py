"""A second physical SMA stage, written for the tests from another formulation than the package's simulator
(sma_stage/plant/physics.py: Brinson-type phase kinetics with cosine laws, wires cut into nodes). It imports
nothing from sma_stage; `main` alone, which prints the table of docs/families.md, calls the package.

Two NiTi wires work against each other through a lever; a relay sends the current to wire A (u > 0) or wire B
(u < 0). Per wire, per sub-step:
- temperature, one lump: m c dT/dt = u^2 R(xi) - h (T - T_ambient), the resistance rising with the martensite
  fraction xi (solved exactly over the sub-step for the frozen power);
- transformation: a Preisach continuum of temperature hysterons (a triangular grid of relays with switch-up
  temperatures alpha >= switch-down temperatures beta, Gaussian weights around the austenite and martensite
  transformation ranges); each relay sees T - sigma / C_CLAUSIUS, so the stress the wire carries raises its
  transformation temperatures (Clausius-Clapeyron) - stress and position tie the two wires together. The
  relays switch at the stresses the last sub-step left, unless the stresses their switching leaves would switch
  them back (both wires hot at a hand-over: each pulls the other into stress-induced martensite); then they
  switch where the stress they leave agrees with them (AntagonisticStage._equilibrium);
- detwinning: the martensite that forms carries the recoverable strain only once the stress has detwinned
  it, D(sigma) rising between SIGMA_DETWIN_START and SIGMA_DETWIN_FINISH; detwinned martensite stays
  detwinned when the stress falls, and the austenite that forms takes from both kinds in proportion;
- mechanics: sigma = E(xi) (epsilon - EPSILON_L * xi_detwinned), tension only (a slack wire carries
  nothing), E from the austenite and martensite moduli in series; the two wires and a flexure balance
  at the wire-end displacement w (solved per sub-step by bisection, the force being monotone in w);
- the sensor: position = LEVER * w, with Gaussian noise NOISE_PCT % of the recorded span.

`python test/antagonistic_plant.py [--variants nominal,thin_wires,...]` prints `gpi_tool diagnose`'s family table
for the paper's identification and validation signals (1000 s each at 0.2 s); `--alternatives` the two-wire
model's alternatives (shapes, excitation).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SAMPLE_PERIOD_S = 0.2
SUBSTEPS = 5
NOISE_PCT = 0.2
HISTORY_S = 200.0  # at zero current before the record: the wires settle from the initial state
GRID = 60  # hysterons per side of the Preisach triangle
CONSISTENT_SHARE = 0.05  # a sub-step whose own stresses would switch back more martensite than this is solved again
CONSISTENT_K = 1.0  # (not checked where what the relays see moved less than this over the sub-step)
EQUILIBRIUM_TOLERANCE_K = 0.05  # the relays' thresholds lie 0.7 K apart
EQUILIBRIUM_SWEEPS = 8
EQUILIBRIUM_STEP_K = 1.0  # the first step of the bracket's search


@dataclass(frozen=True)
class Stage:
    """The stage's physical constants (SI)."""

    wire_diameter_m: float = 0.6e-3
    wire_length_m: float = 0.10
    density_kg_m3: float = 6450.0
    specific_heat_j_kg_k: float = 837.0
    convection_w_m2_k: float = 150.0  # forced air
    resistivity_austenite_ohm_m: float = 0.82e-6
    resistivity_martensite_ohm_m: float = 1.00e-6
    ambient_k: float = 295.0
    austenite_start_k: float = 333.0  # the relays' switch-up temperatures spread around this ..
    austenite_finish_k: float = 358.0  # .. to this, at zero stress
    martensite_start_k: float = 318.0  # switch-down temperatures from this ..
    martensite_finish_k: float = 293.0  # .. to this
    clausius_pa_per_k: float = 7.0e6
    modulus_austenite_pa: float = 70e9
    modulus_martensite_pa: float = 28e9
    recoverable_strain: float = 0.04
    detwin_start_pa: float = 50e6
    detwin_finish_pa: float = 200e6
    prestrain: float = 0.043  # each wire stretched by this at w = 0: both stay taut
    flexure_n_per_m: float = 30.0e3  # at the wire end
    lever: float = 0.12  # stage position per wire-end displacement (a reducing lever)


VARIANTS = {
    "nominal": Stage(),
    "thin_wires": Stage(wire_diameter_m=0.5e-3, convection_w_m2_k=170.0),
    "hot_alloy": Stage(austenite_start_k=345.0, austenite_finish_k=372.0, martensite_start_k=330.0,
                       martensite_finish_k=303.0),
    "stiff_flexure": Stage(flexure_n_per_m=120.0e3, prestrain=0.045),
    # pre-strained hard, with a strong stress shift: held currents below about 4.2 A do not move it, so the
    # paper's decaying sine (5 A falling to 3.6 A) stops moving it after its first cycles
    "prestrained": Stage(prestrain=0.06, clausius_pa_per_k=3.0e6),
}


class Wire:
    """One wire's temperature, relays and detwinned fraction."""

    def __init__(self, stage: Stage) -> None:
        self.stage = stage
        up, down = np.meshgrid(np.linspace(stage.austenite_start_k - 8.0, stage.austenite_finish_k + 8.0, GRID),
                               np.linspace(stage.martensite_finish_k - 8.0, stage.martensite_start_k + 8.0, GRID),
                               indexing="ij")
        keep = up > down
        self.alpha, self.beta = up[keep], down[keep]
        centre_up = 0.5 * (stage.austenite_start_k + stage.austenite_finish_k)
        centre_down = 0.5 * (stage.martensite_start_k + stage.martensite_finish_k)
        spread_up = (stage.austenite_finish_k - stage.austenite_start_k) / 3.0
        spread_down = (stage.martensite_start_k - stage.martensite_finish_k) / 3.0
        weights = np.exp(-0.5 * (((self.alpha - centre_up) / spread_up) ** 2
                                 + ((self.beta - centre_down) / spread_down) ** 2))
        self.weights = weights / weights.sum()
        self.austenite = np.zeros(self.alpha.size, dtype=bool)  # all martensite at the start, cold
        self._martensite = 1.0
        self.temperature_k = stage.ambient_k
        self.detwinned = 1.0  # the prestrain detwinned the martensite when the stage was assembled
        area = np.pi * stage.wire_diameter_m ** 2 / 4.0
        self.area_m2 = area
        self.heat_capacity_j_k = stage.density_kg_m3 * stage.specific_heat_j_kg_k * area * stage.wire_length_m
        self.loss_w_k = stage.convection_w_m2_k * np.pi * stage.wire_diameter_m * stage.wire_length_m

    @property
    def martensite(self) -> float:
        """Martensite fraction xi."""
        return self._martensite

    def resistance_ohm(self) -> float:
        stage, xi = self.stage, self.martensite
        resistivity = stage.resistivity_austenite_ohm_m + xi * (stage.resistivity_martensite_ohm_m
                                                               - stage.resistivity_austenite_ohm_m)
        return resistivity * stage.wire_length_m / self.area_m2

    def heat(self, current_a: float, dt_s: float) -> None:
        """Advance the temperature over dt_s with the Joule power frozen over the step (exact for a linear loss)."""
        power = current_a ** 2 * self.resistance_ohm()
        target = self.stage.ambient_k + power / self.loss_w_k
        decay = np.exp(-dt_s * self.loss_w_k / self.heat_capacity_j_k)
        self.temperature_k = target + (self.temperature_k - target) * decay

    def seen_k(self, stress_pa: float) -> float:
        """The temperature the relays see under stress_pa (Clausius-Clapeyron)."""
        return self.temperature_k - stress_pa / self.stage.clausius_pa_per_k

    def memory(self) -> tuple[np.ndarray, float, float]:
        """The relays, martensite fraction and detwinned fraction: what a transformation starts from."""
        return self.austenite, self._martensite, self.detwinned

    def transform(self, stress_pa: float) -> None:
        """Switch the relays at the stress-shifted temperature; austenite that forms takes from both martensites."""
        self.transform_from(self.memory(), self.seen_k(stress_pa))

    def switched(self, austenite: np.ndarray, seen_k: float) -> np.ndarray:
        """The relays (True: austenite) switched from `austenite` at the seen temperature seen_k [K]."""
        return np.where(seen_k >= self.alpha, True, np.where(seen_k <= self.beta, False, austenite))

    def martensite_of(self, austenite: np.ndarray) -> float:
        """The martensite fraction of a state of the relays."""
        return 1.0 - float(self.weights[austenite].sum())

    def transform_from(self, memory: tuple[np.ndarray, float, float], seen_k: float) -> None:
        """The relays switched from `memory` at the seen temperature seen_k."""
        austenite, before, detwinned = memory
        self.austenite = self.switched(austenite, seen_k)
        self._martensite = after = self.martensite_of(self.austenite)
        self.detwinned = detwinned * after / before if after < before and before > 0.0 else detwinned

    def detwin(self, stress_pa: float) -> None:
        """Stress above the detwinning start detwins martensite; detwinned martensite stays so."""
        stage = self.stage
        share = np.clip((stress_pa - stage.detwin_start_pa) / (stage.detwin_finish_pa - stage.detwin_start_pa),
                        0.0, 1.0)
        share = share * share * (3.0 - 2.0 * share)
        xi = self.martensite
        self.detwinned = min(xi, max(self.detwinned, xi * share)) if xi > 0.0 else 0.0

    def modulus_pa(self) -> float:
        """Young's modulus, austenite and martensite in series."""
        stage, xi = self.stage, self.martensite
        return 1.0 / ((1.0 - xi) / stage.modulus_austenite_pa + xi / stage.modulus_martensite_pa)

    def stress_pa(self, strain: float) -> float:
        """Tension for a total strain (zero when slack)."""
        return max(self.modulus_pa() * (strain - self.stage.recoverable_strain * self.detwinned), 0.0)


class AntagonisticStage:
    """The two wires, the flexure and the lever."""

    def __init__(self, stage: Stage) -> None:
        self.stage = stage
        self.wires = (Wire(stage), Wire(stage))
        self.displacement_m = 0.0
        self.stresses = (0.0, 0.0)
        self.balance()

    def strains(self, w: float) -> tuple[float, float]:
        stage = self.stage
        return stage.prestrain - w / stage.wire_length_m, stage.prestrain + w / stage.wire_length_m

    def balance(self) -> None:
        """The wire-end displacement where the wires and the flexure balance. The net force is piecewise linear and
        falling in w (each wire elastic while taut, slack beyond its break point): it is solved exactly on the
        piece where it changes sign."""
        stage, (wire_a, wire_b) = self.stage, self.wires
        length, prestrain = stage.wire_length_m, stage.prestrain
        stiff_a = wire_a.area_m2 * wire_a.modulus_pa() / length  # N/m while taut
        stiff_b = wire_b.area_m2 * wire_b.modulus_pa() / length
        slack_a = length * (prestrain - stage.recoverable_strain * wire_a.detwinned)  # A slack for w >= this
        slack_b = length * (stage.recoverable_strain * wire_b.detwinned - prestrain)  # B slack for w <= this

        def force(w: float) -> float:
            return stiff_a * max(slack_a - w, 0.0) - stiff_b * max(w - slack_b, 0.0) - stage.flexure_n_per_m * w

        points = sorted((slack_a, slack_b, 0.0))
        low, high = points[0] - length, points[-1] + length
        for point in points:
            if force(point) > 0.0:
                low = point
            else:
                high = point
                break
        force_low, force_high = force(low), force(high)
        self.displacement_m = low + (high - low) * force_low / (force_low - force_high)
        strain_a, strain_b = self.strains(self.displacement_m)
        self.stresses = (wire_a.stress_pa(strain_a), wire_b.stress_pa(strain_b))

    def step(self, current_a: float, dt_s: float) -> None:
        """One sub-step: heat the wire the relay selects (both cool), transform at the stresses the last sub-step
        left, balance, detwin, balance. Where the stresses this leaves would switch the relays back by more than
        CONSISTENT_SHARE (two hot wires at once pull each other into stress-induced martensite), the sub-step is
        taken again at the stresses it leaves itself (_equilibrium): else the relays flip every sub-step."""
        heated = (max(current_a, 0.0), max(-current_a, 0.0))
        memories = [wire.memory() for wire in self.wires]
        for wire, current in zip(self.wires, heated, strict=True):
            wire.heat(current, dt_s)
        used = [wire.seen_k(stress) for wire, stress in zip(self.wires, self.stresses, strict=True)]
        if not self._consistent(memories, used, self._transformed(memories, used)):
            self._equilibrium(memories, used)

    def _transformed(self, memories: list, seen_k: list[float]) -> list[float]:
        """Transform each wire from its memory at seen_k, balance, detwin, balance; what each wire then sees."""
        for wire, memory, seen in zip(self.wires, memories, seen_k, strict=True):
            wire.transform_from(memory, seen)
        self.balance()
        for wire, stress in zip(self.wires, self.stresses, strict=True):
            wire.detwin(stress)
        self.balance()
        return [wire.seen_k(stress) for wire, stress in zip(self.wires, self.stresses, strict=True)]

    def _consistent(self, memories: list, used: list[float], left: list[float]) -> bool:
        """Whether transforming at the seen temperatures the sub-step left instead of those it used changes no
        martensite fraction by more than CONSISTENT_SHARE (none when they differ by less than CONSISTENT_K)."""
        for wire, memory, before, after in zip(self.wires, memories, used, left, strict=True):
            if abs(after - before) < CONSISTENT_K:
                continue
            if abs(wire.martensite_of(wire.switched(memory[0], after)) - wire.martensite) > CONSISTENT_SHARE:
                return False
        return True

    def _equilibrium(self, memories: list, seen: list[float]) -> None:
        """The sub-step's transformation where each wire's relays switch at the temperature they see under the
        stress that switching leaves (stress-induced transformation): per wire in turn, from `seen` (what the
        relays saw at the sub-step's start), the seen temperature s with s = seen(s) (seen falls as s rises: more
        austenite, more tension), bracketed in growing steps from where it was and then bisected."""
        for _ in range(EQUILIBRIUM_SWEEPS):
            moved = 0.0
            for number in range(2):
                started = seen[number]

                def too_high(value: float, number: int = number) -> bool:
                    seen[number] = value
                    return self._transformed(memories, seen)[number] < value

                step, low, high = EQUILIBRIUM_STEP_K, started, started
                if too_high(started):
                    while too_high(low):
                        high, low, step = low, low - step, step * 4.0
                else:
                    while not too_high(high):
                        low, high, step = high, high + step, step * 4.0
                while high - low > EQUILIBRIUM_TOLERANCE_K:
                    middle = 0.5 * (low + high)
                    if too_high(middle):
                        high = middle
                    else:
                        low = middle
                seen[number] = low
                moved = max(moved, abs(low - started))
            if moved <= EQUILIBRIUM_TOLERANCE_K:
                break
        self._transformed(memories, seen)

    @property
    def position_m(self) -> float:
        return self.stage.lever * self.displacement_m


def simulate(current: np.ndarray, stage: Stage = Stage(), seed: int = 0,
             history: np.ndarray | None = None) -> np.ndarray:
    """Positions [m] at each sample of current [A] (held over SAMPLE_PERIOD_S), after HISTORY_S at zero current
    (or the history given), with noise NOISE_PCT % of the recorded span."""
    plant = AntagonisticStage(stage)
    dt = SAMPLE_PERIOD_S / SUBSTEPS
    before = np.zeros(int(HISTORY_S / SAMPLE_PERIOD_S)) if history is None else history
    for value in before:
        for _ in range(SUBSTEPS):
            plant.step(float(value), dt)
    positions = np.empty(current.size)
    for k, value in enumerate(current):
        positions[k] = plant.position_m
        for _ in range(SUBSTEPS):
            plant.step(float(value), dt)
    span = float(np.ptp(positions))
    return positions + np.random.default_rng(seed).normal(0.0, NOISE_PCT / 100.0 * span, positions.size)


def paper_identification(t: np.ndarray) -> np.ndarray:
    """The paper's decaying sine, 5 A falling to 3.6 A over 1000 s, period 250 s (written out here)."""
    return (5.0 - 1.4 * np.clip(t / 1000.0, 0.0, 1.0)) * np.sin(2.0 * np.pi * t / 250.0)


def paper_validation(t: np.ndarray) -> np.ndarray:
    """The paper's validation input 2.5 cos(0.01 pi t) + 2.5 cos(0.02 t) [A]."""
    return 2.5 * np.cos(0.01 * np.pi * t) + 2.5 * np.cos(0.02 * t)


def random_levels(t: np.ndarray, seed: int = 0, hold_s: float = 60.0) -> np.ndarray:
    """Held random levels [A]: a current drawn uniformly from -5 to 5 A, held hold_s each (steps)."""
    levels = np.random.default_rng(100 + seed).uniform(-5.0, 5.0, int(np.max(t) // hold_s) + 1)
    return levels[(np.asarray(t) // hold_s).astype(int)]


def sine_sweep(t: np.ndarray, duration_s: float = 1000.0) -> np.ndarray:
    """A sine sweep [A]: 4.5 A, its period falling from 200 s to 20 s (exponentially) over duration_s."""
    start_hz, end_hz = 1.0 / 200.0, 1.0 / 20.0
    rate = np.log(end_hz / start_hz) / duration_s
    phase = 2.0 * np.pi * start_hz * (np.exp(rate * np.asarray(t)) - 1.0) / rate
    return 4.5 * np.sin(phase)


VALIDATION_SHAPES = {"paper": paper_validation, "random_levels": random_levels, "sine_sweep": sine_sweep}


def records(stage: Stage, seed: int = 0, duration_s: float = 1000.0) -> dict[str, tuple[np.ndarray, ...]]:
    """(t, input, output) of the identification and the validation records, each from its own settled stage."""
    t = np.arange(0.0, duration_s, SAMPLE_PERIOD_S)
    found = {}
    for number, (name, signal) in enumerate((("identification", paper_identification),
                                             ("validation", paper_validation))):
        u = signal(t)
        found[name] = (t, u, simulate(u, stage, seed + number))
    return found


def _gpi_alone(report: dict) -> dict:
    """The report's one model as a families row, when the GPI family alone was fitted (no families table then)."""
    diagnosis = report.get("diagnosis") or {}
    effects = " + ".join(diagnosis.get("effects") or []) or "no effect"
    validation = (diagnosis.get("after") or {}).get("validation") or report["validation"]
    operators = (diagnosis.get("operators") or {}).get("chosen", "?")
    return {"model": f"GPI, {operators} operators, {effects}", "identification": None, "validation": validation,
            "chosen": True}


def main() -> None:
    import argparse
    import sys
    import tempfile
    import time
    from pathlib import Path

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--families", default="gpi,gpi_free,two_wire,bouc_wen", help="gpi_tool diagnose --families")
    parser.add_argument("--alternatives", action="store_true",
                        help="the two-wire model's alternatives instead: shared or per-wire shapes, identified on "
                             "the paper's or the designed excitation")
    parser.add_argument("--seeds", default=None,
                        help="with --alternatives: these noise and start seeds (comma-separated) in place of --seed, "
                             "and a summary over them")
    parser.add_argument("--shapes", default="shared,per_wire", help="with --alternatives: the shapes compared")
    parser.add_argument("--told-apart", action="store_true",
                        help="with --alternatives: the starts told apart on the paper's validation record, as the "
                             "diagnosis does (else the best fit of the identification record)")
    parser.add_argument("--output-operators", type=int, default=None,
                        help="with --alternatives: the output layer's play operators (1: no output hysteresis)")
    args = parser.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    unknown = [name for name in args.variants.split(",") if name not in VARIANTS]
    if unknown:
        parser.error(f"unknown variant {unknown[0]!r} (known: {', '.join(VARIANTS)})")
    if args.alternatives:
        from sma_stage.errors import InputError
        from sma_stage.identify.two_wire import SHAPES

        try:
            seeds = [int(seed) for seed in args.seeds.split(",")] if args.seeds else [args.seed]
        except ValueError:
            parser.error(f"--seeds must be comma-separated integers, got {args.seeds!r}")
        if args.output_operators is not None and not 1 <= args.output_operators <= 50:
            parser.error(f"--output-operators must be from 1 to 50, got {args.output_operators}")
        shapes = args.shapes.split(",")
        if not set(shapes) <= set(SHAPES):
            parser.error(f"--shapes must be among {', '.join(SHAPES)}, got {args.shapes!r}")
        try:
            alternatives(args.variants.split(","), seeds, shapes, args.told_apart, args.output_operators)
        except InputError as error:
            parser.error(str(error))
        return
    from sma_stage.cli import main as gpi_tool
    from sma_stage.identify.metrics import error_metrics
    from sma_stage.model.kinds import load_any_model_file

    print("| variant | span [mm] | model | identification RMS % | validation RMS % | validation max % | | third record "
          "RMS / max % |")
    print("|---|---|---|---|---|---|---|---|")
    for name in args.variants.split(","):
        made = records(VARIANTS[name], args.seed)
        t_third, u_third, y_third = third_record(VARIANTS[name], args.seed)
        with tempfile.TemporaryDirectory() as folder:
            paths = {}
            for kind, (t, u, y) in made.items():
                paths[kind] = Path(folder) / f"{kind}.csv"
                np.savetxt(paths[kind], np.c_[t, u, y], delimiter=",", header="t,input,output", comments="")
            started = time.perf_counter()
            import contextlib
            import io
            import json

            out = io.StringIO()
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
                gpi_tool(["diagnose", str(paths["identification"]), "--validate", str(paths["validation"]),
                          "--rounds", str(args.rounds), "--workers", "2", "--out", str(Path(folder) / "out"),
                          "--families", args.families, "--json"])
            report = json.loads(out.getvalue())
            seconds = time.perf_counter() - started
            chosen = load_any_model_file(Path(folder) / "out" / "model.yaml").without_state()
            third = error_metrics(y_third, chosen.predict(t_third, u_third))
        span = 1e3 * float(np.ptp(made["identification"][2]))
        for row in report.get("families") or [_gpi_alone(report)]:
            valid = row["validation"]
            if valid is None:
                print(f"| {name} | {span:.3f} | {row['model']}: not fitted ({row['not_fitted']}) | | | | |", flush=True)
                continue
            third_cell = f"{third.rms_pct:.2f} / {third.max_pct:.1f}" if row["chosen"] else ""
            identification = f"{row['identification']['rms_pct']:.2f}" if row["identification"] else "-"
            print(f"| {name} | {span:.3f} | {row['model']} | {identification} | "
                  f"{valid['rms_pct']:.2f} | {valid['max_pct']:.1f} | {'chosen' if row['chosen'] else ''} | "
                  f"{third_cell} |", flush=True)
        print(f"| {name} | | (diagnose, families {args.families}) | | | | {seconds:.0f} s | |", flush=True)


def third_record(stage: Stage, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A record no identification choice sees: the designed excitation (another draw) on the stage, 1000 s at
    0.2 s (t [s], current [A], position [m]); `--alternatives`' second validation record."""
    from sma_stage.signals import designed_identification_signal

    t = np.arange(0.0, 1000.0, SAMPLE_PERIOD_S)
    current = designed_identification_signal(t, seed=7)
    return t, current, simulate(current, stage, seed + 9)


def alternative_records(stage: Stage, seed: int) -> tuple[dict[str, tuple[np.ndarray, ...]], tuple[tuple, tuple]]:
    """`--alternatives`' records of one stage and seed: the two identification records by name (the paper's, the
    designed excitation) and the two validation records (the paper's, a second designed draw)."""
    from sma_stage.signals import designed_identification_signal

    made = records(stage, seed)
    t = made["identification"][0]
    designed = designed_identification_signal(t)
    identified_on = {"paper": made["identification"], "designed": (t, designed, simulate(designed, stage, seed + 5))}
    return identified_on, (made["validation"], third_record(stage, seed))


def alternatives(variants: list[str], seeds: list[int], shapes_compared: list[str], told_apart: bool = False,
                 output_operators: int | None = None) -> None:
    """The two-wire model identified with shared or per-wire transformation shapes, on the paper's identification
    signal or the designed excitation, validated on the paper's validation signal and on a second designed record
    (another draw); a table row each, then the mean and worst over the variants and seeds."""
    from sma_stage.identify.metrics import error_metrics
    from sma_stage.identify.two_wire import OUTPUT_OPERATORS, HeldOut, fit_two_wire

    output_operators = OUTPUT_OPERATORS if output_operators is None else output_operators
    print("| variant | seed | identified on | shapes | parameters | BIC | identification RMS % | paper validation "
          "RMS / max % | designed validation RMS / max % | seconds |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    summary: dict[tuple[str, str], list[tuple[float, float, float]]] = {}
    for seed, name in ((seed, name) for seed in seeds for name in variants):
        identified_on, validations = alternative_records(VARIANTS[name], seed)
        held_out = HeldOut(*validations[0]) if told_apart else None
        for (record, (t, u, y)), shapes in ((item, shapes) for item in identified_on.items()
                                            for shapes in shapes_compared):
            found = fit_two_wire(t, u, y, output_operators=output_operators, seed=seed, shapes=shapes,
                                 held_out=held_out)
            model = found.model.without_state()
            paper, second = (error_metrics(y_v, model.predict(t_v, u_v)) for t_v, u_v, y_v in validations)
            summary.setdefault((record, shapes), []).append((paper.rms_pct, paper.max_pct, second.rms_pct))
            print(f"| {name} | {seed} | {record} | {shapes} | {found.parameter_count} | {found.bic:.0f} | "
                  f"{found.errors.rms_pct:.2f} | {paper.rms_pct:.2f} / {paper.max_pct:.1f} | "
                  f"{second.rms_pct:.2f} / {second.max_pct:.1f} | {found.seconds:.0f} |", flush=True)
    print("\n| identified on | shapes | records | paper validation RMS %: mean, worst | over 2 % | max over 10 % | "
          "designed validation RMS %: mean, worst |")
    print("|---|---|---|---|---|---|---|")
    for (record, shapes), rows in summary.items():
        rms, largest, second_rms = (np.array(column) for column in zip(*rows, strict=True))
        print(f"| {record} | {shapes} | {rms.size} | {rms.mean():.2f}, {rms.max():.2f} | {np.sum(rms > 2.0)} | "
              f"{np.sum(largest > 10.0)} | {second_rms.mean():.2f}, {second_rms.max():.2f} |")


if __name__ == "__main__":
    main()
