"""Run the user story through the real `ros2` CLI against `ros2 launch sma_stage stage.launch.py`: launch a
namespaced simulated stage on sim time, excite, refit, send a setpoint, read the position, read the residual,
set on_drift, roll back to the model before, read the history on ~/report, stop with Ctrl-C.
Prints one line per step and exits 1 when one fails. Not a test of the suite: it needs `ros2` with
`ros2 launch` (tools/ros2launch_venv.sh) and the package built with colcon on AMENT_PREFIX_PATH.

    python tools/launch_user_story.py --out /tmp/story [--namespace stage2] [--time-scale 25] [--wall-clock]

--wall-clock runs without use_sim_time: the simulator time_scale times faster than the wall clock, every node
counting stage seconds through its time_scale.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

STORY_PARAMS = """/**/identification:
  ros__parameters:
    excite_duration: 500.0
    model_file: {model}
"""


def ros2(*args: str, timeout: float = 60.0) -> str:
    """Output of one `ros2` command (stdout and stderr)."""
    done = subprocess.run(["ros2", *args], capture_output=True, text=True, timeout=timeout)
    return done.stdout + done.stderr


def call_trigger(service: str) -> tuple[bool, str]:
    """(success, message) of a std_srvs/Trigger call through `ros2 service call`."""
    text = ros2("service", "call", service, "std_srvs/srv/Trigger", timeout=300.0)
    found = re.search(r"success=(True|False), message='(.*)'\)", text, re.S)
    return (found.group(1) == "True", found.group(2)) if found else (False, text.strip()[-300:])


def wait_for(predicate, timeout_s: float, period_s: float = 1.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(period_s)
    return False


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--namespace", default="stage2")
    parser.add_argument("--time-scale", type=float, default=25.0)
    parser.add_argument("--wall-clock", action="store_true", help="without use_sim_time")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    params = args.out / "story_params.yaml"
    params.write_text(STORY_PARAMS.format(model=args.out / "model.yaml"))
    ns = "/" + args.namespace.strip("/")
    log = (args.out / "launch.log").open("w")
    launch = subprocess.Popen(
        ["ros2", "launch", "sma_stage", "stage.launch.py", f"namespace:={args.namespace}", f"use_sim_time:={str(not args.wall_clock).lower()}",
         f"time_scale:={args.time_scale}", f"record_bag:={args.out / 'bag'}", f"params_file:={params}"],
        stdout=log, stderr=subprocess.STDOUT, env={**os.environ, "PYTHONUNBUFFERED": "1"},
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # a shell's background job ignores it
    failures = 0

    def step(name: str, ok: bool, detail: str) -> None:
        nonlocal failures
        failures += not ok
        print(f"{'ok  ' if ok else 'FAIL'} {name}: {' '.join(detail.split())[:300]}", flush=True)

    try:
        wanted = [f"{ns}/{name}" for name in ("compensator", "identification", "stage")]
        nodes: list[str] = []

        def all_up() -> bool:
            nodes[:] = ros2("node", "list", "--no-daemon").split()
            return sorted(nodes) == wanted

        step("launch: the three nodes in the namespace, once each", wait_for(all_up, 60.0), " ".join(nodes))
        state: list[str] = []
        active = wait_for(lambda: state.append(ros2("lifecycle", "get", f"{ns}/stage")) or
                          state[-1].startswith("active"), 30.0)
        step("stage active", active, state[-1])
        ok, message = call_trigger(f"{ns}/identification/excite")
        step("excite", ok, message)
        refit: list[tuple[bool, str]] = []

        def refitted() -> bool:
            refit.append(call_trigger(f"{ns}/identification/refit"))
            return refit[-1][0] or "excitation is running" not in refit[-1][1]

        wait_for(refitted, 120.0, 3.0)
        step("refit", refit[-1][0], refit[-1][1])
        published = ros2("topic", "pub", "--once", "-w", "1", f"{ns}/setpoint", "std_msgs/msg/Float64",
                         "{data: 0.0002}")
        time.sleep(15.0)
        echo = ros2("topic", "echo", "--once", f"{ns}/joint_states", "sensor_msgs/msg/JointState")
        found = re.search(r"position:\s*\n-\s*([-0-9.e]+)", echo)
        position = float(found.group(1)) if found else float("nan")
        step("setpoint 200 um held", abs(position - 2e-4) < 2e-5, f"position {position * 1e6:.1f} um; {published}")
        residual = ros2("topic", "echo", "--once", f"{ns}/identification/residual", "sensor_msgs/msg/JointState")
        step("the model watch's residual", "position:" in residual, residual[:120])
        changed = ros2("param", "set", f"{ns}/identification", "on_drift", "refit")
        step("on_drift refit", "successful" in changed, changed)
        ok, message = call_trigger(f"{ns}/identification/rollback")
        step("rollback to the model before the refit", ok, message)
        report = ros2("topic", "echo", "--once", "--full-length", f"{ns}/identification/report", "std_msgs/msg/String")
        step("the history on ~/report", "rollback" in report and "~/refit" in report, report[-200:])
    finally:
        started = time.monotonic()
        launch.send_signal(signal.SIGINT)
        try:
            code = launch.wait(timeout=30.0)
        except subprocess.TimeoutExpired:
            launch.kill()
            code = None
        log.close()
    text = (args.out / "launch.log").read_text()
    left = subprocess.run(["pgrep", "-f", "lib/sma_stage/"], capture_output=True, text=True).stdout.split()
    step("Ctrl-C: launch and nodes end", code == 0 and not left,
         f"exit {code} after {time.monotonic() - started:.1f} s, processes left {left}")
    step("no traceback or error in the log", "Traceback" not in text and "[ERROR]" not in text,
         "; ".join(line for line in text.splitlines() if "Traceback" in line or "[ERROR]" in line)[:300])
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
