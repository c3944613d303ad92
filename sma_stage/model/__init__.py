"""The GPI hysteresis model (no ROS): parameters, forward model, exact and analytic inverses."""

from sma_stage.model.effects import Effect, EffectState
from sma_stage.model.forward import GPIForwardStream, forward, forward_with_states
from sma_stage.model.identified import IdentifiedModel, ModelState, load_model_file
from sma_stage.model.inverse import (
    GPIInverseStream,
    InverseResult,
    default_input_range,
    inverse,
)
from sma_stage.model.parameters import (
    DEFAULT_OPERATORS,
    PARAMETER_NAMES,
    GPIParameters,
)

__all__ = [
    "DEFAULT_OPERATORS",
    "Effect",
    "EffectState",
    "PARAMETER_NAMES",
    "GPIForwardStream",
    "GPIInverseStream",
    "GPIParameters",
    "InverseResult",
    "IdentifiedModel",
    "ModelState",
    "default_input_range",
    "forward",
    "forward_with_states",
    "inverse",
    "load_model_file",
]
