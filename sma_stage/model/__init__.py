"""The GPI hysteresis model (no ROS): parameters, forward model, exact and analytic inverses."""

from sma_stage.model.forward import GPIForwardStream, forward, forward_with_states
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
    ModelFile,
    load_model_file,
)

__all__ = [
    "DEFAULT_OPERATORS",
    "PARAMETER_NAMES",
    "GPIForwardStream",
    "GPIInverseStream",
    "GPIParameters",
    "InverseResult",
    "ModelFile",
    "default_input_range",
    "forward",
    "forward_with_states",
    "inverse",
    "load_model_file",
]
