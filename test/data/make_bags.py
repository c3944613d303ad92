"""Record the small rosbag2 directories of test/data from the simulated stage through the identification node.

The installed stage_node and identification_node run as processes (sma_stage.nodes.launch); the
identification node records current_cmd and joint_states into a bag through its `record_bag` parameter
while its ~/excite drives the paper's identification signal, sped up (stage time_scale = excite_time_scale).

    .venv/bin/python test/data/make_bags.py [--out test/data]

writes (replacing old copies):
  excitation_sqlite3/   600 s of signal (4.8 s of wall time), sqlite3 storage
  excitation_mcap/      the same with mcap storage (a separate recording)
  no_joint_states/      the identification node alone: current_cmd only, joint_states never published
  truncated_mcap/       excitation_mcap with its .mcap file cut to half its length
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

from sma_stage.nodes.end_to_end import default_domain_id
from sma_stage.nodes.launch import CONFIG_DIR, NodeProcesses, RosClient, wait_for

TIME_SCALE = 125.0   # simulated s per wall s
RATE_HZ = 50.0       # stage steps and excitation samples per wall s: 2.5 s of simulated time each
SIGNAL_S = 600.0     # of the paper's identification signal (period 250 s, amplitude 5 A falling to 3.6 A)


def record(path: Path, storage: str, with_stage: bool, signal_s: float, domain_id: int) -> None:
    """Run the nodes, excite once, stop them (the identification node finishes the bag on SIGTERM)."""
    identification = {"record_bag": str(path), "bag_storage": storage, "excite_duration": signal_s,
                      "excite_time_scale": TIME_SCALE, "excite_rate_hz": RATE_HZ}
    with NodeProcesses(path.parent / "logs", domain_id) as nodes:
        if with_stage:
            nodes.start("stage_node", {"rate_hz": RATE_HZ, "time_scale": TIME_SCALE, "command_timeout": 5.0},
                        [CONFIG_DIR / "stage.yaml"])
        nodes.start("identification_node", identification, [CONFIG_DIR / "identification.yaml"])
        with RosClient(domain_id, "make_bags") as client:
            services = ["identification/excite"] + (["stage/stop"] if with_stage else [])
            client.wait_for_services(services, 120.0, nodes.check_running)
            if with_stage:
                wait_for(lambda: client.node.count_publishers("joint_states") >= 1, 30.0, "the stage")
                time.sleep(0.2)
            ok, message = client.trigger("identification/excite")
            if not ok:
                raise RuntimeError(message)
            time.sleep(signal_s / TIME_SCALE + 0.1)
        exits = nodes.stop_all()
    if any(exits.values()) or not (path / "metadata.yaml").is_file():
        raise RuntimeError(f"recording {path} failed: exit codes {exits}, see {path.parent / 'logs'}")


def truncated_copy(source: Path, target: Path) -> None:
    """A copy of a bag directory whose storage file keeps only the first half of its bytes."""
    shutil.copytree(source, target)
    (storage,) = target.glob("*.mcap")
    storage.write_bytes(storage.read_bytes()[: storage.stat().st_size // 2])


def main(argv: list[str] | None = None) -> int:
    """Record every bag into a scratch folder, then move them into --out."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent)
    args = parser.parse_args(argv)
    domain_id = default_domain_id()
    with tempfile.TemporaryDirectory(dir=args.out) as scratch:
        scratch = Path(scratch)
        record(scratch / "excitation_sqlite3", "sqlite3", True, SIGNAL_S, domain_id)
        record(scratch / "excitation_mcap", "mcap", True, SIGNAL_S, domain_id)
        record(scratch / "no_joint_states", "sqlite3", False, 100.0, domain_id)
        truncated_copy(scratch / "excitation_mcap", scratch / "truncated_mcap")
        for name in ("excitation_sqlite3", "excitation_mcap", "no_joint_states", "truncated_mcap"):
            shutil.rmtree(args.out / name, ignore_errors=True)
            (scratch / name).rename(args.out / name)
            size = sum(f.stat().st_size for f in (args.out / name).iterdir())
            print(f"{args.out / name}: {size / 1000:.1f} kB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
