"""Control (no ROS): the compensator's law, GPI inverse with a thermal-lag lead and a PI loop."""

from sma_stage.control.compensator import Compensator

__all__ = ["Compensator"]
