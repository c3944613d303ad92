"""The identification node recording onto a disk that fills up (needs root: the disk is a small tmpfs mounted
here). A probe floods current_applied and joint_states; after a few seconds a file takes all the free space
but --left MiB. Prints, per storage: how the recording ended (the node's [ERROR] line), whether the node still
runs and stops with status 0, the messages in the bag as read back, and the node's memory growth.

Run: sudo .venv/bin/python bench/bench_full_disk.py [--size-mb 128] [--left 1] [--seconds 20]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from record_results import recorded

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from sma_stage.io import read_bag  # noqa: E402
from sma_stage.nodes.launch import CONFIG_DIR, NodeProcesses, RosClient, wait_for  # noqa: E402


def rss_mb(pid: int) -> float:
    """Resident memory of a process [MiB]."""
    return int(Path(f"/proc/{pid}/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def flood(client: RosClient, stop: threading.Event) -> None:
    """Publish current_applied and joint_states as fast as this process can."""
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64

    from sma_stage.nodes._common import COMMAND_QOS, STATE_PUBLISH_QOS

    inputs = client.node.create_publisher(Float64, "current_applied", COMMAND_QOS)
    outputs = client.node.create_publisher(JointState, "joint_states", STATE_PUBLISH_QOS)
    k = 0
    while not stop.is_set():
        inputs.publish(Float64(data=float(k % 100) * 0.01))
        message = JointState(name=["stage_x"], position=[1e-6 * (k % 100)], velocity=[0.0])
        message.header.stamp = client.node.get_clock().now().to_msg()
        outputs.publish(message)
        k += 1


def run(storage: str, mount: Path, left_mb: int, seconds: float, domain: int) -> str:
    """One recording onto the mounted disk; its table row."""
    bag = mount / f"bag_{storage}"
    with NodeProcesses(Path(tempfile.mkdtemp()), domain) as nodes, RosClient(domain, "flood") as client:
        node = nodes.start("identification_node", {"record_bag": str(bag), "bag_storage": storage},
                           [CONFIG_DIR / "identification.yaml"])
        wait_for(lambda: "identification ready" in node.log_path.read_text(), 60.0, "the node", nodes.check_running)
        stop = threading.Event()
        flooding = threading.Thread(target=flood, args=(client, stop), daemon=True)
        flooding.start()
        time.sleep(2.0)
        start_rss = rss_mb(node.popen.pid)
        filler = mount / "filler"
        free = os.statvfs(mount).f_bavail * os.statvfs(mount).f_frsize
        subprocess.run(["fallocate", "-l", str(max(free - left_mb * 2**20, 0)), str(filler)], check=False)
        time.sleep(seconds)
        end_rss = rss_mb(node.popen.pid)
        running = node.running
        stop.set()
        flooding.join()
        node.popen.terminate()
        status = node.popen.wait(30)
        nodes.forget(node)
        log = node.log_path.read_text()
        errors = [line for line in log.splitlines() if "[ERROR]" in line or "Traceback" in line]
        filler.unlink(missing_ok=True)
    try:
        messages = f"{len(read_bag(bag, min_samples=1, input_topic='/current_applied')):,} samples"
    except Exception as error:  # noqa: BLE001 -- the table says what the reader said
        messages = f"unreadable: {' '.join(str(error).split())[:80]}"
    line = errors[0].split("]: ", 1)[-1] if errors else "no error line"
    return (f"| {storage} | {line[:160]} | {'yes' if running else 'no'} | {status} | {messages} | "
            f"{end_rss - start_rss:+.1f} |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size-mb", type=int, default=128)
    parser.add_argument("--left", type=int, default=1, help="MiB left free when the disk is filled")
    parser.add_argument("--seconds", type=float, default=20.0, help="how long the flood goes on after that")
    parser.add_argument("--domain", type=int, default=230)
    args = parser.parse_args()
    os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    mount = Path(tempfile.mkdtemp(prefix="full_disk_"))
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={args.size_mb}m", "tmpfs", str(mount)], check=True)
    try:
        print(f"tmpfs of {args.size_mb} MiB, filled to {args.left} MiB free 2 s into a flood, then "
              f"{args.seconds:g} s more\n")
        print("| storage | how the recording ended | node still running | exit status | bag read back | "
              "memory growth after the fill [MiB] |")
        print("|---|---|---|---|---|---|")
        for number, storage in enumerate(("sqlite3", "mcap")):
            print(run(storage, mount, args.left, args.seconds, args.domain + number), flush=True)
    finally:
        subprocess.run(["umount", str(mount)], check=False)
    return 0


if __name__ == "__main__":
    with recorded(__file__):
        sys.exit(main())
