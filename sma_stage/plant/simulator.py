"""The stage simulator: a per-sample `StageSimulator.step` and a batched `simulate`, same trajectory."""

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from sma_stage.errors import InputError, finite_number
from sma_stage.plant import physics as ph
from sma_stage.plant.config import Effects, StageConfig, pack_parameters

_TIME_TOLERANCE_S = 1e-9
PROGRESS_SAMPLES = 200_000  # simulate() runs in parts of this many samples, reporting progress after each


@dataclass(frozen=True)
class StageState:
    """The stage after a step: time [s], true and measured position [m], velocity [m/s], wires (A, B)."""

    time_s: float
    position_m: float
    velocity_m_s: float
    measured_position_m: float
    wire_temperatures_k: tuple[float, float]
    martensite_fractions: tuple[float, float]
    current_a: float
    wire_stresses_pa: tuple[float, float] = (0.0, 0.0)


@dataclass(frozen=True)
class SimulationResult:
    """Arrays of a run, one row per step; sample k holds the state after the k-th current was applied."""

    t_s: np.ndarray
    current_a: np.ndarray
    position_m: np.ndarray
    measured_position_m: np.ndarray
    velocity_m_s: np.ndarray
    wire_temperatures_k: np.ndarray
    martensite_fractions: np.ndarray


def _check_dt(dt_s: float) -> float:
    try:
        dt = float(dt_s)
    except (TypeError, ValueError):
        raise InputError(f"dt_s must be a number, got {dt_s!r}") from None
    if not (math.isfinite(dt) and dt > 0.0):
        raise InputError(f"dt_s must be finite and positive, got {dt_s!r}")
    return dt


def _check_current(current_a) -> float:
    return finite_number("current_a", current_a)


def _check_currents(current_a) -> np.ndarray:
    try:
        currents = np.asarray(current_a, dtype=float)
    except (TypeError, ValueError):
        raise InputError("current_a must be numbers") from None
    if currents.ndim != 1 or currents.size == 0:
        raise InputError(f"current_a must be a non-empty 1-D sequence, got shape {currents.shape}")
    if not np.all(np.isfinite(currents)):
        raise InputError("current_a contains NaN or infinite values")
    return currents


def _sense(true_positions: np.ndarray, noise: np.ndarray, config: StageConfig) -> np.ndarray:
    """Sensor reading [m]: position plus Gaussian noise, quantised to the sensor resolution."""
    reading = true_positions + config.sensor_noise_m * noise
    if config.sensor_resolution_m > 0.0:
        reading = np.round(reading / config.sensor_resolution_m) * config.sensor_resolution_m
    return reading


class StageSimulator:
    """The antagonistic two-wire NiTi stage, stepped one current sample at a time (SI units)."""

    def __init__(self, config: StageConfig | None = None, effects: Effects | None = None, seed: int = 0):
        self.config = config if config is not None else StageConfig()
        self.effects = effects if effects is not None else Effects()
        if not isinstance(self.config, StageConfig) or not isinstance(self.effects, Effects):
            raise InputError("config must be a StageConfig and effects an Effects")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise InputError(f"seed must be a whole number >= 0, got {seed!r}")
        self.seed = int(seed)
        self._parameters = pack_parameters(self.config, self.effects)
        self._current, self._reading, self._noise = np.zeros(1), np.zeros(1), np.zeros(1)
        self._outputs = _allocate(1)
        self.reset()
        self._load_step_kernel()

    def _load_step_kernel(self) -> None:
        """Compile the step's kernel (or load it from numba's cache) on a scratch copy of the state, so that the
        first step does not wait for the compiler: a node's first control tick, on a cold cache, waited 13 s."""
        ph.run(self._parameters, self._state.copy(), np.zeros(1), 1e-3, *_allocate(1))

    def reset(self) -> StageState:
        """Back to rest at t = 0 (wires at ambient, martensite, pre-strained); noise restarts from the seed."""
        self._state = ph.new_state(self._parameters)
        ph.settle(self._parameters, self._state)
        self._rng = np.random.default_rng(self.seed)
        self._position = ph.stage_position(self._parameters, self._state)
        self._initial_position = self._position
        self._history: deque[tuple[float, float]] = deque()
        self._last = self._snapshot(0.0, self._position, 0.0)
        return self._last

    @property
    def state(self) -> StageState:
        """The most recent state."""
        return self._last

    def step(self, current_a: float, dt_s: float) -> StageState:
        """Apply current_a [A] (clamped to max_current_a) for dt_s [s]; return the state at the end."""
        dt = _check_dt(dt_s)
        self._current[0] = _check_current(current_a)
        position, _, _, times = self._outputs
        ph.run(self._parameters, self._state, self._current, dt, *self._outputs)
        velocity = (position[0] - self._position) / dt
        self._position = position[0]
        self._history.append((times[0], position[0]))
        self._reading[0] = self._delayed_position(times[0])
        self._noise[0] = self._rng.standard_normal()
        measured = _sense(self._reading, self._noise, self.config)[0]
        limit = self.config.max_current_a
        self._last = self._snapshot(min(limit, max(-limit, self._current[0])), measured, velocity)
        return self._last

    def _delayed_position(self, now_s: float) -> float:
        target = now_s - self.effects.sensor_delay_s + _TIME_TOLERANCE_S
        while len(self._history) > 1 and self._history[1][0] <= target:
            self._history.popleft()
        if self._history[0][0] <= target:
            return self._history[0][1]
        return self._initial_position

    def _snapshot(self, current: float, measured: float, velocity: float) -> StageState:
        s, p = self._state, self._parameters
        return StageState(
            time_s=float(s[ph.S_TIME]),
            position_m=float(self._position),
            velocity_m_s=float(velocity),
            measured_position_m=float(measured),
            wire_temperatures_k=(ph.wire_mean(p, s, 0, ph.K_TEMPERATURE), ph.wire_mean(p, s, 1, ph.K_TEMPERATURE)),
            martensite_fractions=(ph.wire_mean(p, s, 0, ph.K_DETWINNED), ph.wire_mean(p, s, 1, ph.K_DETWINNED)),
            current_a=current,
            wire_stresses_pa=(float(s[ph.S_STRESS_A]), float(s[ph.S_STRESS_B])),
        )


def _allocate(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    return np.zeros(n), np.zeros((n, 2)), np.zeros((n, 2)), np.zeros(n)


def simulate(
    current_a,
    dt_s: float,
    config: StageConfig | None = None,
    effects: Effects | None = None,
    seed: int = 0,
    progress: Callable[[int, int], None] | None = None,
) -> SimulationResult:
    """Run the stage from rest on a current sequence [A] sampled every dt_s [s] (zero-order hold); progress,
    when given, is called with (samples done, samples in all) every PROGRESS_SAMPLES samples.

    Gives the same trajectory as calling StageSimulator(config, effects, seed).step(i, dt_s) per sample.
    """
    dt = _check_dt(dt_s)
    currents = _check_currents(current_a)
    sim = StageSimulator(config, effects, seed)
    position, temperatures, fractions, times = _allocate(currents.size)
    for start in range(0, currents.size, PROGRESS_SAMPLES):
        part = slice(start, start + PROGRESS_SAMPLES)
        ph.run(sim._parameters, sim._state, currents[part], dt, position[part], temperatures[part], fractions[part],
               times[part])
        if progress is not None:
            progress(min(start + PROGRESS_SAMPLES, currents.size), currents.size)
    previous = np.concatenate(([sim._initial_position], position[:-1]))
    velocity = (position - previous) / dt
    target = times - sim.effects.sensor_delay_s + _TIME_TOLERANCE_S
    source = np.searchsorted(times, target, side="right") - 1
    delayed = np.where(source >= 0, position[np.maximum(source, 0)], sim._initial_position)
    measured = _sense(delayed, sim._rng.standard_normal(currents.size), sim.config)
    limit = sim.config.max_current_a
    return SimulationResult(
        t_s=times,
        current_a=np.clip(currents, -limit, limit),
        position_m=position,
        measured_position_m=measured,
        velocity_m_s=velocity,
        wire_temperatures_k=temperatures,
        martensite_fractions=fractions,
    )
