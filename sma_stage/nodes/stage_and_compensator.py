"""Entry point `stage_and_compensator`: one stage's stage and compensator nodes in one process and one executor.

The two nodes are the same as `stage_node` and `compensator_node` (parameters, topics, services, lifecycle),
each reading its own section (`stage:`, `compensator:`) of the parameter files given; `-r __ns:=/stage_3`
puts both under one namespace. One process instead of two halves the interpreters, DDS participants and
executor threads a stage costs: with many stages on one machine (bench/bench_stages.py) that is what keeps
their cycles on time.
"""

from __future__ import annotations

from sma_stage.nodes._common import exit_with, run_nodes
from sma_stage.nodes.compensator_node import CompensatorNode
from sma_stage.nodes.stage_node import StageNode


def main(args: list[str] | None = None) -> None:
    """Entry point `stage_and_compensator`."""
    exit_with(run_nodes([StageNode, CompensatorNode], args))


if __name__ == "__main__":
    main()
