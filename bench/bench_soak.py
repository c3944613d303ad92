"""Soak: the three nodes together for a long run with recording on, counting messages and watching memory.

The identification node starts first and records (record_bag) before the stage exists; the stage then runs at
--rate-hz on wall time (time_scale 1), the compensator at 100 Hz in feedback, and ~/excite drives the stage for
the whole run. At the end the stage is stopped first (it logs how many steps it published: one joint_states
and one current_applied each), then the identification node, which finishes the bag. Lost messages: the
steps published against the messages of each topic in the bag. Memory: the resident set of each node
process every 10 s, from /proc.

Run: .venv/bin/python bench/bench_soak.py [--minutes 10] [--rate-hz 500]   (kept out of the test run)
"""

from __future__ import annotations

import argparse
import os
import re
import tempfile
import time
from pathlib import Path

from record_results import recorded

from sma_stage.nodes.launch import CONFIG_DIR, NodeProcesses, RosClient, wait_for

SAMPLE_EVERY_S = 10.0
WARMUP_S = 30.0


def resident_kib(pid: int) -> int:
    """VmRSS of a process [KiB] (0 when it has gone)."""
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return 0
    found = re.search(r"^VmRSS:\s+(\d+) kB", text, re.MULTILINE)
    return int(found.group(1)) if found else 0


def bag_counts(bag: Path) -> dict[str, int]:
    """Messages per topic in a finished rosbag2."""
    from rosbags.rosbag2 import Reader

    with Reader(bag) as reader:
        return {connection.topic: connection.msgcount for connection in reader.connections}


def bag_stamps(bag: Path) -> set[int]:
    """The header stamps [ns] of the bag's joint_states."""
    from rosbags.rosbag2 import Reader

    from sma_stage.io.rosbag_io import _typestore

    store = _typestore()
    with Reader(bag) as reader:
        connections = [c for c in reader.connections if c.topic == "/joint_states"]
        return {message.header.stamp.sec * 10**9 + message.header.stamp.nanosec
                for message in (store.deserialize_cdr(raw, c.msgtype) for c, _, raw in reader.messages(connections))}


def run(minutes: float, rate_hz: float) -> int:
    seconds = 60.0 * minutes
    domain = int(os.environ.get("ROS_DOMAIN_ID", "0") or 0) or 1 + os.getpid() % 100
    with tempfile.TemporaryDirectory() as work:
        bag = Path(work) / "soak_bag"
        with NodeProcesses(Path(work) / "nodes", domain) as nodes:
            identification = nodes.start("identification_node", {
                "record_bag": str(bag), "excite_duration": seconds + 60.0, "excite_rate_hz": 50.0,
                "model_file": ""}, [CONFIG_DIR / "identification.yaml"])
            wait_for(lambda: "recording into" in identification.log_path.read_text(), 60.0, "the recorder",
                     nodes.check_running)
            compensator = nodes.start("compensator_node", {"rate_hz": 100.0}, [CONFIG_DIR / "compensator.yaml"])
            stage = nodes.start("stage_node", {"rate_hz": rate_hz}, [CONFIG_DIR / "stage.yaml"])
            processes = {"stage": stage, "compensator": compensator, "identification": identification}
            with RosClient(domain, "soak_probe") as client:
                from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
                from sensor_msgs.msg import JointState

                seen: list[int] = []
                client.node.create_subscription(
                    JointState, "joint_states",
                    lambda m: seen.append(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec),
                    QoSProfile(depth=10000, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST))
                client.wait_for_services(["identification/excite", "stage/stop"], 60.0, nodes.check_running)
                ok, message = client.trigger("identification/excite")
                assert ok, message
                started = time.monotonic()
                memory: dict[str, list[tuple[float, int]]] = {name: [] for name in processes}
                while time.monotonic() - started < seconds:
                    nodes.check_running()
                    for name, process in processes.items():
                        memory[name].append((time.monotonic() - started, resident_kib(process.popen.pid)))
                    time.sleep(SAMPLE_EVERY_S)
            stage.popen.terminate()
            stage.popen.wait(30)
            exits = nodes.stop_all()
        published = int(re.findall(r"published (\d+) steps", stage.log_path.read_text())[-1])
        recorded = bag_counts(bag)
        in_bag = bag_stamps(bag)
    probe = set(seen)
    window = (max(min(in_bag), min(probe)), min(max(in_bag), max(probe)))
    inside = {stamp for stamp in probe if window[0] <= stamp <= window[1]}
    missing_from_bag, missing_from_probe = len(inside - in_bag), len({s for s in in_bag if window[0] <= s <= window[1]} - probe)
    print(f"Soak: {minutes:g} min, stage at {rate_hz:g} Hz, compensator at 100 Hz in feedback, excitation at 50 Hz, "
          f"recording joint_states and current_applied; exit statuses {exits}")
    print("\n| topic | published by the stage | in the bag | not in the bag |\n|---|---|---|---|")
    for topic in ("/joint_states", "/current_applied"):
        count = recorded.get(topic, 0)
        print(f"| {topic} | {published} | {count} | {published - count} |")
    print("\n| node | resident set after the warm-up [MiB] | at a third | at two thirds | at the end | growth over the "
          "last third [MiB] |")
    print("|---|---|---|---|---|---|")
    for name, samples in memory.items():
        kept = [kib / 1024 for t, kib in samples if t >= WARMUP_S and kib > 0]
        marks = [kept[0], kept[len(kept) // 3], kept[2 * len(kept) // 3], kept[-1]]
        print(f"| {name} | " + " | ".join(f"{mib:.1f}" for mib in marks) + f" | {marks[3] - marks[2]:+.1f} |")
    print(f"\nThe bag's joint_states against an independent reliable subscriber (this process), over the "
          f"{(window[1] - window[0]) * 1e-9:.1f} s both saw: {len(inside)} messages, {missing_from_bag} missing from the "
          f"bag, {missing_from_probe} missing from the subscriber. The stage published {published - recorded.get('/joint_states', 0)} "
          "more than the bag holds: those before the recorder had discovered it (start-up), or lost.")
    return 1 if missing_from_bag else 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--rate-hz", type=float, default=500.0)
    args = parser.parse_args()
    return run(args.minutes, args.rate_hz)


if __name__ == "__main__":
    with recorded(__file__):
        raise SystemExit(main())
