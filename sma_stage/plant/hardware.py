"""The one interface the stage node drives, whatever runs the stage: the simulator or real instruments.

Named like ros2_control's hardware interfaces: the command interfaces are the two wires' currents
(`wire_a/current`, `wire_b/current` [A], at most one of them non-zero: the relay routes the current to one
wire), the state interfaces add the stage position (`stage/position` [m]) and velocity (`stage/velocity`
[m/s]). A cycle is ros2_control's: `read(period_s)` (the state at the end of the period and the current
applied over it), then `write(commands)` (the current for the next period).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass

from sma_stage.plant.config import Effects, StageConfig
from sma_stage.plant.simulator import StageSimulator

WIRE_A_CURRENT = "wire_a/current"
WIRE_B_CURRENT = "wire_b/current"
STAGE_POSITION = "stage/position"
STAGE_VELOCITY = "stage/velocity"
COMMAND_INTERFACES = (WIRE_A_CURRENT, WIRE_B_CURRENT)
STATE_INTERFACES = (WIRE_A_CURRENT, WIRE_B_CURRENT, STAGE_POSITION, STAGE_VELOCITY)


class HardwareError(RuntimeError):
    """An instrument fault (lost connection, timeout, garbage reply, error in its queue, protection trip),
    as one line naming the instrument."""

    def __init__(self, message: str) -> None:
        super().__init__(" ".join(str(message).split()))


def wire_commands(current_a: float) -> dict[str, float]:
    """The command interfaces for a signed stage current [A]: u > 0 heats wire A, u < 0 heats wire B."""
    return {WIRE_A_CURRENT: max(current_a, 0.0), WIRE_B_CURRENT: max(-current_a, 0.0)}


def signed_current(values: Mapping[str, float]) -> float:
    """The signed stage current [A] of a commands or states mapping (wire A positive, wire B negative)."""
    return float(values[WIRE_A_CURRENT]) - float(values[WIRE_B_CURRENT])


@dataclass(frozen=True)
class Reading:
    """The state interfaces after a cycle, and the stage's time [s] (simulated time for the simulator, the
    host's steady clock since connect otherwise); read_ns: the host's clock (time.time_ns, the ROS clock of a
    node without simulated time) [ns] at which the instruments were read, None for the simulator."""

    time_s: float
    states: Mapping[str, float]
    read_ns: int | None = None

    @property
    def position_m(self) -> float:
        """The measured stage position [m]."""
        return float(self.states[STAGE_POSITION])

    @property
    def current_a(self) -> float:
        """The signed current [A] applied to the stage (read back where the hardware can)."""
        return signed_current(self.states)


class StageHardware(ABC):
    """What runs the stage. connect() leaves the output off; write/read one cycle; stop() zeroes the
    current, switches the output off and opens the relay, confirmed; close() ends the connection."""

    kind = "hardware"

    @abstractmethod
    def connect(self) -> dict[str, str]:
        """Open and set up the hardware with the output off; the identity of each part (name -> identity)."""

    @abstractmethod
    def enable(self) -> None:
        """Allow current to flow (the output on at zero current)."""

    @abstractmethod
    def write(self, commands: Mapping[str, float]) -> None:
        """Apply the command interfaces [A] (limits and switching rules applied by the hardware layer)."""

    @abstractmethod
    def read(self, period_s: float) -> Reading:
        """The state after a cycle of period_s [s] (the simulator advances by it; instruments ignore it)."""

    @abstractmethod
    def stop(self) -> None:
        """Zero current, output off, relay open, each confirmed; HardwareError when one is not."""

    @abstractmethod
    def close(self) -> None:
        """End the connection (best effort, never raises)."""

    def status(self) -> dict[str, object]:
        """Key values for /diagnostics (identity, errors, relay, trips)."""
        return {}


class SimulatedHardware(StageHardware):
    """The embedded physics simulator behind the hardware interface (simulated time, nothing to connect)."""

    kind = "sim"

    def __init__(self, config: StageConfig, effects: Effects, seed: int) -> None:
        self._args = (config, effects, seed)
        self.simulator: StageSimulator | None = None
        self._current_a = 0.0
        self._enabled = False

    def connect(self) -> dict[str, str]:
        self.simulator = StageSimulator(*self._args)
        self._current_a, self._enabled = 0.0, False
        return {"stage": "sma_stage simulator"}

    def enable(self) -> None:
        self._enabled = True

    def write(self, commands: Mapping[str, float]) -> None:
        self._current_a = signed_current(commands) if self._enabled else 0.0

    def read(self, period_s: float) -> Reading:
        state = self.simulator.step(self._current_a, period_s) if period_s > 0.0 else self.simulator.state
        return Reading(state.time_s, {**wire_commands(state.current_a), STAGE_POSITION: state.measured_position_m,
                                      STAGE_VELOCITY: state.velocity_m_s})

    def stop(self) -> None:
        self._current_a, self._enabled = 0.0, False

    def close(self) -> None:
        self._enabled = False

    def status(self) -> dict[str, object]:
        if self.simulator is None:
            return {}
        state = self.simulator.state
        return {
            "wire_a_temperature_k": state.wire_temperatures_k[0],
            "wire_b_temperature_k": state.wire_temperatures_k[1],
            "wire_a_martensite_fraction": state.martensite_fractions[0],
            "wire_b_martensite_fraction": state.martensite_fractions[1],
            "simulated_time_s": state.time_s,
        }
