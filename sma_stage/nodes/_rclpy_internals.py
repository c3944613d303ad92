"""The two things the nodes take from rclpy's internals, in one place; test/test_rclpy_internals.py pins what
they rely on, so that an rclpy upgrade that moves them fails a test, not a user."""

from __future__ import annotations

from rclpy._rclpy_pybind11 import RCLError  # raised by rcl, e.g. on a wait set whose context shut down
from rclpy.node import Node
from rclpy.parameter import Parameter

__all__ = ["RCLError", "parameter_overrides"]


def parameter_overrides(node: Node) -> dict[str, Parameter]:
    """The node's parameter overrides (from `parameter_overrides=` and params files) by name, before any is
    declared: the dict rclpy declares from, so a value replaced in it is the one declare_parameter takes.
    rclpy has no public way to read them before declaring."""
    return node._parameter_overrides
