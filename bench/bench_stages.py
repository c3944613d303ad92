"""Many stages on one machine: N stage and compensator node pairs, each pair in its own namespace (/stage_0
... /stage_<N-1>), from the installed executables, on wall time with their defaults (the compensator in
feedback) but the rate given: one process per pair (`stage_and_compensator`, the default) or per node
(`stage_node` and `compensator_node`, --process-per node).

Cycle timing, two ways: each stage's own count on /diagnostics (a cycle starting more than 1.5 periods after
the previous one is late), and a probe node in this process that records every pair's joint_states stamps
(the stage's tick times) and applies the same rule. The probe runs rclpy's events executor so that it takes
as little of the CPU the stages share as it can. Cross-talk: a setpoint is sent to one stage only; it must move
there and nowhere else.

Run: .venv/bin/python bench/bench_stages.py [--stages 10] [--rate-hz 100] [--seconds 30] [--process-per node]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np
from record_results import recorded

from sma_stage.nodes.launch import CONFIG_DIR, NodeProcesses, RosClient, wait_for

LATE_FACTOR = 1.5
MOVED_M = 50e-6      # the stage given the setpoint must move at least this far
STILL_M = 5e-6       # every other stage must stay within this of where it was
SETPOINT_HOLD_S = 15.0


class Positions:
    """Every joint_states message of every namespace: (stamp [s], position [m])."""

    def __init__(self, client: RosClient, namespaces: list[str]) -> None:
        from sensor_msgs.msg import JointState

        from sma_stage.nodes._common import STATE_SUBSCRIBE_QOS

        self.records: dict[str, list[tuple[float, float]]] = {name: [] for name in namespaces}
        for name in namespaces:
            client.node.create_subscription(JointState, f"{name}/joint_states",
                                            lambda message, name=name: self.on_state(name, message),
                                            STATE_SUBSCRIBE_QOS)

    def on_state(self, name: str, message: object) -> None:
        stamp = message.header.stamp.sec + 1e-9 * message.header.stamp.nanosec
        self.records[name].append((stamp, float(message.position[0])))

    def between(self, name: str, start: int, stop: int | None = None) -> np.ndarray:
        return np.array(self.records[name][start:stop]).reshape(-1, 2)


class CycleCounts:
    """Each stage's latest (cycles, late cycles) from its own /diagnostics, by namespace."""

    def __init__(self, client: RosClient, namespaces: list[str]) -> None:
        from diagnostic_msgs.msg import DiagnosticArray

        self.namespaces = namespaces
        self.latest: dict[str, tuple[int, int]] = {}
        client.node.create_subscription(DiagnosticArray, "/diagnostics", self.on_diagnostics, 50)

    def on_diagnostics(self, message: object) -> None:
        for status in message.status:
            namespace = status.name.split(":")[0].rsplit("/", 1)[0]
            values = {pair.key: pair.value for pair in status.values}
            if namespace in self.namespaces and "late_cycles" in values:
                self.latest[namespace] = (int(values["cycles"]), int(values["late_cycles"]))

    def snapshot(self) -> dict[str, tuple[int, int]]:
        """Every stage's counts now; waits until each stage has published some."""
        wait_for(lambda: set(self.latest) == set(self.namespaces), 10.0, "/diagnostics from every stage")
        return dict(self.latest)


PROCESS_PER = ("pair", "node")


def run(stages: int, rate_hz: float, seconds: float, process_per: str = "pair") -> int:
    namespaces = [f"/stage_{k}" for k in range(stages)]
    domain = int(os.environ.get("ROS_DOMAIN_ID", "0") or 0) or 1 + os.getpid() % 100
    with tempfile.TemporaryDirectory() as work, NodeProcesses(Path(work), domain) as nodes:
        started = time.monotonic()
        stage_file, compensator_file = CONFIG_DIR / "stage.yaml", CONFIG_DIR / "compensator.yaml"
        for name in namespaces:
            if process_per == "pair":
                nodes.start("stage_and_compensator", {"rate_hz": rate_hz}, [stage_file, compensator_file], name)
            else:
                nodes.start("stage_node", {"rate_hz": rate_hz}, [stage_file], namespace=name)
                nodes.start("compensator_node", {"rate_hz": rate_hz}, [compensator_file], namespace=name)
        with RosClient(domain, "stages_probe", executor_kind="events") as client:
            positions = Positions(client, namespaces)
            counts = CycleCounts(client, namespaces)
            wait_for(lambda: all(len(records) > 10 for records in positions.records.values()), 120.0,
                     "joint_states from every stage", nodes.check_running)
            print(f"{len(nodes.processes)} node processes ({process_per} each) up in {time.monotonic() - started:.1f} s; measuring {seconds:g} s "
                  f"at {rate_hz:g} Hz", flush=True)
            first = {name: len(records) for name, records in positions.records.items()}
            counted_first = counts.snapshot()
            time.sleep(seconds)
            last = {name: len(records) for name, records in positions.records.items()}
            counted_last = counts.snapshot()
            rest = {name: positions.between(name, last[name] - 20, last[name])[:, 1].mean() for name in namespaces}
            moved_one = namespaces[len(namespaces) // 2]
            from std_msgs.msg import Float64

            from sma_stage.nodes._common import COMMAND_QOS

            publisher = client.node.create_publisher(Float64, f"{moved_one}/setpoint", COMMAND_QOS)
            wait_for(lambda: client.node.count_subscribers(f"{moved_one}/setpoint") >= 1, 10.0, "the compensator")
            target = rest[moved_one] + 2e-4
            deadline = time.monotonic() + SETPOINT_HOLD_S
            while time.monotonic() < deadline:
                publisher.publish(Float64(data=target))
                time.sleep(0.1)
            print("\n| stage | joint_states | late cycles % (stamps) | late cycles % (node's count) "
                  "| longest interval ms | moved um | setpoint |")
            print("|---|---|---|---|---|---|---|")
            late_all, total_all, crosstalk = 0, 0, []
            for name in namespaces:
                measured = positions.between(name, first[name], last[name])
                intervals = np.diff(measured[:, 0])
                late = int(np.sum(intervals > LATE_FACTOR / rate_hz))
                late_all, total_all = late_all + late, total_all + intervals.size
                now = positions.between(name, len(positions.records[name]) - 20)[:, 1].mean()
                moved = now - rest[name]
                given = name == moved_one
                ok = abs(moved) >= MOVED_M if given else abs(moved) <= STILL_M
                crosstalk.append(ok)
                print(f"| {name} | {intervals.size + 1} | {100 * late / max(intervals.size, 1):.2f} | "
                      f"{late_percent({name: counted_first[name]}, {name: counted_last[name]}):.2f} | "
                      f"{1e3 * intervals.max():.1f} | {1e6 * moved:+.1f} | {'yes' if given else 'no'}"
                      f"{'' if ok else ' (FAIL)'} |")
        exits = nodes.stop_all()
    by_stamps = 100 * late_all / max(total_all, 1)
    by_nodes = late_percent(counted_first, counted_last)
    met = max(by_stamps, by_nodes) <= 1
    print(f"\nlate cycles over all stages: {by_stamps:.2f} % by the stamps, {by_nodes:.2f} % by the nodes' own count "
          f"(target at most 1 %: {'met' if met else 'NOT met'}); cross-talk: {'none' if all(crosstalk) else 'FOUND'}; "
          f"exit statuses {sorted(set(exits.values()))}")
    return 0 if met and all(crosstalk) else 1


def late_percent(first: dict[str, tuple[int, int]], last: dict[str, tuple[int, int]]) -> float:
    """Late cycles between two /diagnostics snapshots, over every stage in them [%]."""
    cycles = sum(last[name][0] - first[name][0] for name in first)
    late = sum(last[name][1] - first[name][1] for name in first)
    return 100.0 * late / max(cycles, 1)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stages", type=int, default=10)
    parser.add_argument("--rate-hz", type=float, default=100.0)
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--process-per", choices=PROCESS_PER, default="pair",
                        help="one process per stage and compensator pair, or per node")
    args = parser.parse_args()
    return run(args.stages, args.rate_hz, args.seconds, args.process_per)


if __name__ == "__main__":
    with recorded(__file__):
        raise SystemExit(main())
