"""A refit through the nodes against the same refit in process: the identification node's report (written by
`./run.sh demo`: the paper's identification signal through stage_node on the simulator, recorded and refitted
by identification_node) beside identify_recording on the same signal stepped through the simulator in this
process, with the node's settings (sample rate, duration, held-out fraction, operators, diagnosis rounds,
families). Prints one table (each family's held-out RMS both ways, the effects found, the family chosen) and
writes it to bench/results/refit_nodes.md.

    ./run.sh demo && .venv/bin/python bench/bench_refit_nodes.py [--nodes out/demo/nodes]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))

from record_results import recorded  # noqa: E402

from sma_stage.identify.pipeline import identify_recording  # noqa: E402
from sma_stage.io import make_series  # noqa: E402
from sma_stage.nodes.identification.params import IDENTIFICATION_PARAMS  # noqa: E402
from sma_stage.plant import StageSimulator  # noqa: E402
from sma_stage.signals import paper_identification_signal  # noqa: E402

NODE_DEFAULTS = {param.name: param.default for param in IDENTIFICATION_PARAMS}


def node_settings(nodes_dir: Path) -> dict[str, object]:
    """The identification node's parameters the demo ran it with (its defaults where the file is silent)."""
    path = nodes_dir / "identification_node.params.yaml"
    given = yaml.safe_load(path.read_text())["/**"]["ros__parameters"]
    return {**NODE_DEFAULTS, **given}


def in_process_report(settings: dict[str, object]) -> dict[str, object]:
    """identify_recording on the paper's identification signal stepped through the simulator here."""
    period = 1.0 / float(settings["excite_rate_hz"])
    t = period * np.arange(int(round(float(settings["excite_duration"]) / period)))
    current = paper_identification_signal(t, float(settings["excite_amplitude_start"]),
                                          float(settings["excite_amplitude_end"]), float(settings["excite_period"]),
                                          float(settings["excite_duration"]))
    stage = StageSimulator()
    position = np.array([stage.step(value, period).measured_position_m for value in current])
    found = identify_recording(make_series(t, current, position, "identification"),
                               holdout_fraction=float(settings["holdout_fraction"]),
                               operators=int(settings["operators"]) or None,
                               diagnose_rounds=int(settings["diagnose_rounds"]), workers=2,
                               families=tuple(settings["families"]))
    return found.report


def family_rms(report: dict[str, object]) -> dict[str, float]:
    """Each family's held-out RMS [% of the span], by the family's name in the report."""
    return {row["family"]: row["validation"]["rms_pct"] for row in report.get("families") or []}


def chosen(report: dict[str, object]) -> str:
    rows = [row["family"] for row in report.get("families") or [] if row["chosen"]]
    return rows[0] if rows else "gpi"


def table(nodes: dict[str, object], here: dict[str, object]) -> list[str]:
    lines = ["| | through the nodes | in process | relative difference |", "|---|---|---|---|"]
    for name, value in family_rms(nodes).items():
        other = family_rms(here).get(name, float("nan"))
        lines.append(f"| {name} held-out RMS % | {value:.3f} | {other:.3f} | {100.0 * (value / other - 1.0):+.1f} % |")
    before = [report["diagnosis"]["before"]["validation"]["rms_pct"] for report in (nodes, here)]
    lines.append(f"| plain GPI held-out RMS % | {before[0]:.3f} | {before[1]:.3f} | {100.0 * (before[0] / before[1] - 1.0):+.1f} % |")
    effects = [", ".join(report["diagnosis"]["effects"]) or "none" for report in (nodes, here)]
    lines.append(f"| effects | {effects[0]} | {effects[1]} | {'same' if effects[0] == effects[1] else 'differ'} |")
    families = [chosen(report) for report in (nodes, here)]
    lines.append(f"| family chosen | {families[0]} | {families[1]} | {'same' if families[0] == families[1] else 'differ'} |")
    samples = [f"{report['samples']['identification']} + {report['samples']['validation']}" for report in (nodes, here)]
    lines.append(f"| samples (fit + held out) | {samples[0]} | {samples[1]} | |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--nodes", default=str(REPO / "out" / "demo" / "nodes"),
                        help="the demo's node directory (identified_model.report.json, identification_node.params.yaml)")
    args = parser.parse_args()
    nodes_dir = Path(args.nodes)
    report_path = nodes_dir / "identified_model.report.json"
    if not report_path.is_file():
        parser.error(f"no {report_path}: run ./run.sh demo first")
    started = time.perf_counter()
    nodes = json.loads(report_path.read_text())
    here = in_process_report(node_settings(nodes_dir))
    with recorded(__file__):
        print("\n".join(table(nodes, here)))
        print(f"\n{time.perf_counter() - started:.0f} s (the demo's nodes ran before, `./run.sh demo`)")


if __name__ == "__main__":
    main()
