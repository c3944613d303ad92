"""Runs a node for bench_nodes.py under a chosen executor: `single` is what the installed executables use
(sma_stage.nodes._common.run_node, SingleThreadedExecutor), `events` is rclpy's EventsExecutor (C++,
experimental in Jazzy), the candidate fix the benchmark compares. `echo` copies each setpoint to
current_cmd unchanged, so the latency table can tell transport and rclpy from the model's work.

Run: python bench/node_runner.py {stage,compensator,echo} {single,events} [--ros-args ...]
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from std_msgs.msg import Float64

from sma_stage.errors import InputError
from sma_stage.nodes._common import COMMAND_QOS, run_node

SPIN_SLICE_S = 1.0


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


def run_with_events_executor(make_node: Callable[..., Node], args: Sequence[str] | None = None) -> int:
    """run_node's life cycle with rclpy.experimental.EventsExecutor: spin until Ctrl-C/SIGTERM."""
    from rclpy.experimental import EventsExecutor
    from rclpy.task import Future

    rclpy.init(args=args)
    node = executor = None
    try:
        executor = EventsExecutor()
        node = make_node()
        executor.add_node(node)
        never = Future()
        while rclpy.ok():  # EventsExecutor.spin() busy-waits in rclpy 7.1.5; this call does not
            executor.spin_until_future_complete(never, timeout_sec=SPIN_SLICE_S)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if executor is not None:
            executor.shutdown(timeout_sec=1.0)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


def main(argv: Sequence[str]) -> int:
    """node_runner.py NODE EXECUTOR [--ros-args ...]."""
    if len(argv) < 2 or argv[1] not in ("single", "events"):
        print("usage: node_runner.py {stage,compensator,echo} {single,events} [--ros-args ...]", file=sys.stderr)
        return 2
    make_node, ros_args = node_class(argv[0]), ["node_runner", *argv[2:]]
    if argv[1] == "single":
        return run_node(make_node, ros_args)
    return run_with_events_executor(make_node, ros_args)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
