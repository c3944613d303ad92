"""Shared test set-up: isolate ROS 2 traffic per pytest process before anything imports rclpy."""

import os


def _isolate_ros() -> None:
    os.environ["ROS_DOMAIN_ID"] = str(1 + os.getpid() % 101)
    os.environ["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    # Deprecated in Jazzy; when set it overrides the discovery range and logs a warning in every node.
    os.environ.pop("ROS_LOCALHOST_ONLY", None)
    os.environ.pop("ROS_STATIC_PEERS", None)
    os.environ.setdefault("MPLBACKEND", "Agg")


_isolate_ros()
