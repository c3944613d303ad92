"""What sma_stage.nodes._rclpy_internals relies on in rclpy: an upgrade that moves it fails here."""

import os

import pytest

rclpy = pytest.importorskip("rclpy")

from rclpy.context import Context  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from sma_stage.nodes._rclpy_internals import RCLError, parameter_overrides  # noqa: E402


@pytest.fixture
def context():
    context = Context()
    rclpy.init(context=context, domain_id=int(os.environ["ROS_DOMAIN_ID"]))
    yield context
    rclpy.shutdown(context=context)


def test_the_overrides_are_read_before_declaring_and_a_replaced_one_is_declared(context):
    node = Node("overrides", context=context, parameter_overrides=[Parameter("rate_hz", value=50)])
    try:
        overrides = parameter_overrides(node)
        assert overrides["rate_hz"].value == 50 and not node.has_parameter("rate_hz")
        overrides["rate_hz"] = Parameter("rate_hz", value=50.0)
        assert node.declare_parameter("rate_hz", 10.0).value == 50.0
    finally:
        node.destroy_node()


def test_rcl_error_is_what_rcl_raises_on_a_shut_down_context():
    context = Context()
    rclpy.init(context=context, domain_id=int(os.environ["ROS_DOMAIN_ID"]))
    node = Node("closing", context=context)
    rclpy.shutdown(context=context)
    with pytest.raises(RCLError, match="context"):
        node.create_publisher(String, "closing", 10)
    node.destroy_node()
