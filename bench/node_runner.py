"""Runs a node for bench_nodes.py under a chosen executor through sma_stage.nodes._common.run_node:
`events` is rclpy's EventsExecutor (C++, experimental in Jazzy), what the installed executables use;
`single` the SingleThreadedExecutor, for comparison. `echo` copies each setpoint to
current_cmd unchanged, so the latency table can tell transport and rclpy from the model's work.

Run: python bench/node_runner.py {stage,compensator,echo} {single,events} [--ros-args ...]
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence

from rclpy.node import Node
from std_msgs.msg import Float64

from sma_stage.errors import InputError
from sma_stage.nodes._common import COMMAND_QOS, run_node


class EchoNode(Node):
    """setpoint in, the same value out on current_cmd, with the compensator's QoS."""

    def __init__(self, **node_options: object) -> None:
        super().__init__("echo", **node_options)
        self.publisher = self.create_publisher(Float64, "current_cmd", COMMAND_QOS)
        self.create_subscription(Float64, "setpoint", self.on_setpoint, COMMAND_QOS)
        self.get_logger().info("echo ready")

    def on_setpoint(self, message: Float64) -> None:
        """Republish the value."""
        self.publisher.publish(Float64(data=message.data))


def node_class(name: str) -> Callable[..., Node]:
    """The node class for a name: stage, compensator or echo."""
    if name == "stage":
        from sma_stage.nodes.stage_node import StageNode

        return StageNode
    if name == "compensator":
        from sma_stage.nodes.compensator_node import CompensatorNode

        return CompensatorNode
    if name == "echo":
        return EchoNode
    raise InputError(f"unknown node {name!r} (stage, compensator, echo)")


def main(argv: Sequence[str]) -> int:
    """node_runner.py NODE EXECUTOR [--ros-args ...]."""
    if len(argv) < 2 or argv[1] not in ("single", "events"):
        print("usage: node_runner.py {stage,compensator,echo} {single,events} [--ros-args ...]", file=sys.stderr)
        return 2
    return run_node(node_class(argv[0]), ["node_runner", *argv[2:]], executor_kind=argv[1])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
