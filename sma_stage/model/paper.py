"""The source paper's Table 1 and what it gives under eqs 1-5 as printed (no ROS, no plotting)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sma_stage.model.forward import forward
from sma_stage.model.parameters import GPIParameters

PAPER_OUTPUT_UNIT = "unstated (paper)"
PAPER_TABLE_1 = GPIParameters(
    a1=7.61667, a2=1.11619, a3=1.51672, a4=31.42343, a5=0.25761, a6=19.47572, a7=-30.93615,
    a8=0.86628, a9=2.03529, a10=-1.31329, a11=0.42705, output_unit=PAPER_OUTPUT_UNIT,
)
PAPER_INPUT_RANGE_A = (-5.0, 5.0)


def exchanged_envelopes(params: GPIParameters) -> GPIParameters:
    """A reading: a1..a4 and a5..a8 swapped, so that gl <= gr as the paper's text requires."""
    return params.replace(a1=params.a5, a2=params.a6, a3=params.a7, a4=params.a8,
                          a5=params.a1, a6=params.a2, a7=params.a3, a8=params.a4)


def positive_density(params: GPIParameters) -> GPIParameters:
    """A reading: a10 replaced by |a10|, as the paper's text requires a10 > 0."""
    return params.replace(a10=abs(params.a10))


READINGS = {
    "as printed": PAPER_TABLE_1,
    "reading: a10 -> |a10|": positive_density(PAPER_TABLE_1),
    "reading: envelopes exchanged": exchanged_envelopes(PAPER_TABLE_1),
    "reading: envelopes exchanged, a10 -> |a10|": positive_density(exchanged_envelopes(PAPER_TABLE_1)),
}


@dataclass(frozen=True)
class LoopSummary:
    """A parameter set's loop over a full input sweep [output unit]: span, widest vertical gap between
    the rising and falling branches, and that gap as a fraction of the span."""

    span: float
    width: float

    @property
    def width_fraction(self) -> float:
        """Loop width / output span (0 for a memoryless map)."""
        return self.width / self.span if self.span > 0 else 0.0


def loop_summary(params: GPIParameters, operators: int,
                 input_range: tuple[float, float] = PAPER_INPUT_RANGE_A, points: int = 2001) -> LoopSummary:
    """Sweep the input low -> high -> low -> high and compare the last rising and falling branches."""
    low, high = input_range
    rising = np.linspace(low, high, points)
    sweep = np.concatenate([rising, rising[::-1], rising])
    output = forward(sweep, params, operators)
    falling_branch = output[points: 2 * points][::-1]
    rising_branch = output[2 * points:]
    return LoopSummary(span=float(np.ptp(output)), width=float(np.max(np.abs(falling_branch - rising_branch))))


@dataclass(frozen=True)
class EnvelopeFindings:
    """Facts about the envelopes over the input range: min of gl - gr [output unit], and which
    operators have their band [gl - r_i, gr + r_i] empty everywhere (pinned to gl - r_i)."""

    smallest_gap: float
    pinned_operators: list[int]
    density_signs: str


def envelope_findings(params: GPIParameters, operators: int,
                      input_range: tuple[float, float] = PAPER_INPUT_RANGE_A) -> EnvelopeFindings:
    """Where gl > gr + 2 r_i for every input, operator i ignores its memory: z_i = gl - r_i."""
    v = np.linspace(*input_range, 4001)
    gap = params.envelope_left(v) - params.envelope_right(v)
    thresholds = params.thresholds(operators)
    pinned = [i for i, r in enumerate(thresholds) if np.all(gap > 2.0 * r)]
    weights = params.densities(operators)
    signs = "all negative" if np.all(weights < 0) else "all positive" if np.all(weights > 0) else "mixed"
    return EnvelopeFindings(float(gap.min()), pinned, signs)
