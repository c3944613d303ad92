"""Shared test set-up: isolate ROS 2 traffic per pytest process before anything imports rclpy.

Under pytest-xdist (`./run.sh test` runs two workers) each worker takes its own share of the domain ids,
so two workers never pick the same one: the process's ROS_DOMAIN_ID from 1..100, and the ids
`test_nodes.unique_domain` hands out from 120..219.
"""

import os


def worker_share(first: int, size: int) -> tuple[int, int]:
    """(start, length) of this worker's share of the domain ids first .. first + size - 1."""
    count = max(int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")), 1)
    worker = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0")[2:] or 0) % count
    length = size // count
    return first + worker * length, length


def _isolate_ros() -> None:
    start, length = worker_share(1, 100)
    os.environ["ROS_DOMAIN_ID"] = str(start + os.getpid() % length)
    os.environ["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    # Deprecated in Jazzy; when set it overrides the discovery range and logs a warning in every node.
    os.environ.pop("ROS_LOCALHOST_ONLY", None)
    os.environ.pop("ROS_STATIC_PEERS", None)
    os.environ.setdefault("MPLBACKEND", "Agg")


_isolate_ros()


def _hypothesis_profiles() -> None:
    """Property tests draw the same cases every run (derandomize), so that CI passes or fails on the code,
    not on the draw; HYPOTHESIS_PROFILE=explore draws new ones, many more, to look for more failures."""
    from hypothesis import settings

    settings.register_profile("default", derandomize=True)
    settings.register_profile("explore", derandomize=False, max_examples=2000)
    settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))


_hypothesis_profiles()
