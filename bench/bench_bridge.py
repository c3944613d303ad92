"""The hardware bridge against the simulator backend, side by side in one run, and the bridge's cycle timing.

Figures: the end-to-end run from the installed executables (excite, refit, the fitted model pushed to the
compensator, then a step to 70 % of the stroke held first by the feedforward alone, then with the PI loop)
once with `backend sim` and once with `backend visa` through pyvisa-py to the loopback SCPI rig
(test/scpi_server.py: a DP832-like supply with two relays and a 34461A-like meter on the same stage
simulator), both on the stage's /clock at the same time scale. Each row: the refit's validation RMS and the
held error [% of the stroke] (mean of the last HOLD_MEAN_S of each hold).

Timing: the bridge alone at --rate-hz on wall time (time scale 1) for --seconds, a current command moving
it; late cycles are those starting more than 1.5 periods after the previous one, counted by the node
(/diagnostics) and, independently, from the joint_states arrivals at a probe.

Run: .venv/bin/python bench/bench_bridge.py [--time-scale 20] [--rate-hz 100] [--seconds 60] [--repeat 1]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml
from record_results import recorded

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "test"))

from scpi_server import LoopbackRig  # noqa: E402  -- the test-only instrument rig

from sma_stage.nodes.launch import CONFIG_DIR, NodeProcesses, RosClient, wait_for  # noqa: E402

EXCITE_S = 500.0
COOL_S = 300.0
HOLD_S = 300.0
HOLD_MEAN_S = 60.0
TARGET_FRACTION = 0.7
LATE_FACTOR = 1.5


def hardware_yaml(rig: LoopbackRig, folder: Path) -> Path:
    """The shipped example as the rig's simulator equivalent (LoopbackRig.simulator_equivalent), as a file."""
    path = folder / "hardware.yaml"
    path.write_text(yaml.safe_dump(rig.simulator_equivalent(
        yaml.safe_load((CONFIG_DIR / "hardware_example.yaml").read_text()))))
    return path


class Positions:
    """joint_states as (stamp [s of the stage's time], position [m]) and wall arrival times [s]."""

    def __init__(self, client: RosClient) -> None:
        from sensor_msgs.msg import JointState

        from sma_stage.nodes._common import STATE_SUBSCRIBE_QOS

        self.stamps: list[float] = []
        self.positions: list[float] = []
        self.arrivals: list[float] = []
        client.node.create_subscription(JointState, "joint_states", self.on_message, STATE_SUBSCRIBE_QOS)

    def on_message(self, message) -> None:
        self.arrivals.append(time.monotonic())
        self.stamps.append(message.header.stamp.sec + 1e-9 * message.header.stamp.nanosec)
        self.positions.append(message.position[0])

    def mean_since(self, since_s: float) -> float:
        stamps = np.asarray(self.stamps)
        return float(np.mean(np.asarray(self.positions)[stamps >= since_s]))

    def wait_stage_time(self, until_s: float, nodes: NodeProcesses, time_scale: float) -> None:
        wait_for(lambda: self.stamps and self.stamps[-1] >= until_s, 3.0 * (until_s - self.stamps[-1]) / time_scale
                 + 30.0, f"stage time {until_s:.0f} s", nodes.check_running)


def end_to_end(backend: str, time_scale: float, folder: Path, domain: int) -> dict[str, float]:
    """One end-to-end run; the refit's validation RMS and the held errors [% of the stroke]."""
    import json

    from std_msgs.msg import Float64, String

    from sma_stage.nodes._common import COMMAND_QOS, REPORT_QOS

    rig = LoopbackRig(time_scale=time_scale) if backend == "visa" else None
    stage = {"rate_hz": 100.0, "time_scale": time_scale, "command_timeout": 5.0, "use_sim_time": True}
    if rig is not None:
        rig.start()
        stage.update(backend="visa", hardware_file=str(hardware_yaml(rig, folder)), autostart="active")
    try:
        with NodeProcesses(folder / f"nodes_{backend}", domain) as nodes:
            nodes.start("stage_node", stage, [CONFIG_DIR / "stage.yaml"])
            nodes.start("compensator_node", {"use_sim_time": True, "feedback": False, "rate_hz": 10.0},
                        [CONFIG_DIR / "compensator.yaml"])
            nodes.start("identification_node", {"excite_duration": EXCITE_S, "use_sim_time": True,
                                                 "model_file": str(folder / f"model_{backend}.yaml")},
                        [CONFIG_DIR / "identification.yaml"])
            with RosClient(domain, "bench_bridge") as client:
                seen = Positions(client)
                client.wait_for_services(["identification/excite", "identification/refit"], 60.0,
                                         nodes.check_running)
                wait_for(lambda: len(seen.stamps) > 10, 30.0, "joint_states", nodes.check_running)
                wait_for(lambda: client.trigger("identification/excite")[0], 30.0, "the excitation to start",
                         nodes.check_running, poll_s=0.2)
                started_s = seen.stamps[-1]
                seen.wait_stage_time(started_s + EXCITE_S + 5.0, nodes, time_scale)
                ok, message = client.trigger("identification/refit", timeout_s=120.0)
                assert ok, message
                report = json.loads(client.latest(String, "identification/report", REPORT_QOS).data)
                excited = np.asarray(seen.positions)[np.asarray(seen.stamps) >= started_s]
                low, high = float(excited.min()), float(excited.max())
                target = low + TARGET_FRACTION * (high - low)
                pushed_s = seen.stamps[-1]
                seen.wait_stage_time(pushed_s + COOL_S, nodes, time_scale)
                states = [client.lifecycle("stage")]
                if states[0] == "inactive":  # on instruments the watchdog deactivated it after the excitation
                    states.append(client.lifecycle("stage", "activate"))
                setpoint = client.node.create_publisher(Float64, "setpoint", COMMAND_QOS)
                wait_for(lambda: client.node.count_subscribers("setpoint") >= 1, 10.0, "the compensator")
                errors = {}
                for mode in ("feedforward", "feedback"):
                    client.set_parameters("compensator", {"feedback": mode == "feedback"})
                    setpoint.publish(Float64(data=target))
                    start_s = seen.stamps[-1]
                    seen.wait_stage_time(start_s + HOLD_S, nodes, time_scale)
                    held = seen.mean_since(start_s + HOLD_S - HOLD_MEAN_S)
                    errors[mode] = 100.0 * abs(held - target) / (high - low)
            nodes.stop_all()
    finally:
        if rig is not None:
            rig.stop()
    return {"validation_rms_pct": float(report["diagnosis"]["after"]["validation"]["rms_pct"]),
            "stroke_um": 1e6 * (high - low), "feedforward_pct": errors["feedforward"],
            "feedback_pct": errors["feedback"], "effect": report["diagnosis"]["effect"],
            "lifecycle": " -> ".join(states)}


def bridge_timing(rate_hz: float, seconds: float, folder: Path, domain: int) -> dict[str, float]:
    """The bridge on wall time at rate_hz: late cycles by the node's count and from the arrivals at a probe."""
    from diagnostic_msgs.msg import DiagnosticArray
    from std_msgs.msg import Float64

    from sma_stage.nodes._common import COMMAND_QOS

    with LoopbackRig(time_scale=1.0) as rig, NodeProcesses(folder / "nodes_timing", domain) as nodes:
        nodes.start("stage_node", {"rate_hz": rate_hz, "backend": "visa", "autostart": "active",
                                   "hardware_file": str(hardware_yaml(rig, folder)), "command_timeout": 5.0})
        with RosClient(domain, "bench_bridge_timing") as client:
            seen = Positions(client)
            statuses: list = []
            client.node.create_subscription(DiagnosticArray, "/diagnostics", statuses.append, 10)
            command = client.node.create_publisher(Float64, "current_cmd", COMMAND_QOS)
            wait_for(lambda: len(seen.arrivals) > 10, 30.0, "joint_states", nodes.check_running)
            first = len(seen.arrivals)
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                command.publish(Float64(data=2.0 * np.sin(2 * np.pi * time.monotonic() / 10.0)))
                time.sleep(0.05)
            arrivals = np.diff(np.asarray(seen.arrivals[first:]))
            values = {pair.key: pair.value for pair in statuses[-1].status[0].values}
        nodes.stop_all()
    return {"cycles": int(values["cycles"]), "node_late_pct": float(values["late_cycles_percent"]),
            "longest_io_ms": float(values["longest_cycle_io_ms"]),
            "probe_late_pct": 100.0 * float(np.mean(arrivals > LATE_FACTOR / rate_hz)),
            "conflicts": rig.conflicts}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--time-scale", type=float, default=20.0)
    parser.add_argument("--rate-hz", type=float, default=100.0)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--repeat", type=int, default=1)
    args = parser.parse_args()
    domain = 150 + os.getpid() % 50
    worst_gap = 0.0
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch)
        if args.repeat:
            print(f"\nend to end, time scale {args.time_scale:g}: step to {100 * TARGET_FRACTION:.0f} % of the stroke")
            print("| run | backend | stage before the step | effect | validation RMS % | stroke um | "
                  "feedforward held error % | PI held error % |")
            print("|---|---|---|---|---|---|---|---|")
        for run in range(args.repeat):
            rows = {backend: end_to_end(backend, args.time_scale, folder, domain) for backend in ("sim", "visa")}
            for backend, row in rows.items():
                print(f"| {run + 1} | {backend} | {row['lifecycle']} | {row['effect']} | {row['validation_rms_pct']:.3f} | "
                      f"{row['stroke_um']:.1f} | {row['feedforward_pct']:.3f} | {row['feedback_pct']:.3f} |",
                      flush=True)
            gap = max(abs(rows["sim"][k] - rows["visa"][k]) for k in ("feedforward_pct", "feedback_pct"))
            worst_gap = max(worst_gap, gap)
            print(f"|  | visa - sim | | | | | {rows['visa']['feedforward_pct'] - rows['sim']['feedforward_pct']:+.3f}"
                  f" | {rows['visa']['feedback_pct'] - rows['sim']['feedback_pct']:+.3f} |", flush=True)
        timing = bridge_timing(args.rate_hz, args.seconds, folder, domain)
    print(f"\nbridge timing, {args.rate_hz:g} Hz for {args.seconds:g} s over the loopback rig")
    print("| cycles | late % (node) | late % (probe arrivals) | longest cycle I/O ms | relay closed under current |")
    print("|---|---|---|---|---|")
    print(f"| {timing['cycles']} | {timing['node_late_pct']:.2f} | {timing['probe_late_pct']:.2f} | "
          f"{timing['longest_io_ms']:.2f} | {timing['conflicts']} |")
    met_figures, met_timing = worst_gap <= 0.5, timing["node_late_pct"] <= 1.0
    figures = (f"largest held-error gap {worst_gap:.3f} % of the stroke (target at most 0.5: "
               f"{'met' if met_figures else 'NOT met'})") if args.repeat else "end to end not run (--repeat 0)"
    print(f"\nbridge vs simulator: {figures}; late cycles {timing['node_late_pct']:.2f} % (target at most 1: "
          f"{'met' if met_timing else 'NOT met'})")
    return 0 if met_figures and met_timing else 1


if __name__ == "__main__":
    with recorded(__file__):
        sys.exit(main())
