"""Large records: reading a CSV of N rows (t, input, output) and `gpi_tool fit` on it, each in a fresh process:
rows per second and peak memory (max RSS), and the memory per million rows over the interpreter's own.

Run: .venv/bin/python bench/bench_records.py [--rows 1000000 10000000] [--operators 10] [--skip-fit-above 0]
The CSVs are made here (the shipped model's GPI driven by the paper's identification signal, 1 kHz, noise) in a
temporary folder and removed after.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from record_results import recorded

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from sma_stage.model import forward, load_model_file  # noqa: E402
from sma_stage.signals import paper_identification_signal  # noqa: E402

MEASURE = """
import json, resource, sys, time
started = time.perf_counter()
if sys.argv[1] == "read":
    from sma_stage.io import load_series
    rows = len(load_series(sys.argv[2]))
    status = 0
elif sys.argv[1] == "idle":
    import numpy, scipy, numba, sma_stage.identify.fit, sma_stage.io
    rows, status = 0, 0
else:
    from sma_stage.cli import main
    status = main(["fit", sys.argv[2], "--operators", sys.argv[3], "--out", sys.argv[4]])
    rows = None
print(json.dumps({"status": status, "rows": rows, "seconds": time.perf_counter() - started,
                  "max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def write_record(path: Path, rows: int) -> None:
    """rows samples at 1 kHz of the shipped model driven by the paper's identification signal, with noise."""
    model = load_model_file(REPO / "config" / "model_default.yaml")
    t = np.arange(rows) * 1e-3
    u = paper_identification_signal(np.mod(t, 1000.0), 5.0, 3.6, 250.0, 1000.0)
    y = forward(u, model.parameters, model.operators) + np.random.default_rng(0).normal(0.0, 2e-6, rows)
    with open(path, "w") as file:
        file.write("t,input,output\n")
        for start in range(0, rows, 1_000_000):
            block = np.column_stack([t[start:start + 1_000_000], u[start:start + 1_000_000],
                                     y[start:start + 1_000_000]])
            np.savetxt(file, block, delimiter=",", fmt="%.9g")


def measure(*arguments: str) -> dict:
    """Run MEASURE in a fresh interpreter; its JSON line."""
    done = subprocess.run([sys.executable, "-c", MEASURE, *arguments], capture_output=True, text=True, cwd=REPO)
    if done.returncode != 0:
        raise RuntimeError(done.stderr[-2000:])
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, nargs="+", default=[1_000_000, 10_000_000])
    parser.add_argument("--operators", type=int, default=10)
    parser.add_argument("--skip-fit-above", type=int, default=0, help="no fit for records longer than this (0: fit all)")
    args = parser.parse_args()
    idle = measure("idle")
    print(f"interpreter with numpy, scipy, numba and the package loaded: {idle['max_rss_mb']:.0f} MB\n")
    print("| rows | file [MB] | read [s] | read [rows/s] | read peak [MB] | fit [s] | fit peak [MB] | "
          "fit peak over idle per million rows [MB] |")
    print("|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as folder:
        for rows in args.rows:
            path = Path(folder) / f"record_{rows}.csv"
            write_record(path, rows)
            size_mb = path.stat().st_size / 2**20
            read = measure("read", str(path))
            fit = None
            if not args.skip_fit_above or rows <= args.skip_fit_above:
                started = time.perf_counter()
                fit = measure("fit", str(path), str(args.operators), str(Path(folder) / f"out_{rows}"))
                fit["seconds"] = time.perf_counter() - started
            fit_cells = (f"{fit['seconds']:.1f} | {fit['max_rss_mb']:.0f} | "
                         f"{(fit['max_rss_mb'] - idle['max_rss_mb']) / (rows / 1e6):.0f}" if fit else "- | - | -")
            print(f"| {rows:,} | {size_mb:.0f} | {read['seconds']:.1f} | {rows / read['seconds']:,.0f} | "
                  f"{read['max_rss_mb']:.0f} | {fit_cells} |", flush=True)
            path.unlink()
    return 0


if __name__ == "__main__":
    with recorded(__file__):
        sys.exit(main())
