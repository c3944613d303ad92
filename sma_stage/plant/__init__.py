"""Physical simulator of the antagonistic two-wire NiTi micro-positioning stage (no ROS, no GPI code).

    from sma_stage.plant import StageConfig, Effects, StageSimulator, simulate
    result = simulate(currents_a, dt_s, config=StageConfig(), effects=Effects(), seed=0)

Equations, defaults and their sources: docs/simulator.md.
"""

from sma_stage.plant.config import Effects, StageConfig
from sma_stage.plant.simulator import SimulationResult, StageSimulator, StageState, simulate

__all__ = ["Effects", "SimulationResult", "StageConfig", "StageSimulator", "StageState", "simulate"]
