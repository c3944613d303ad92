"""Learning a repeated setpoint through the node executables beside the same loop in process: the simulated stage and
the compensator (the shipped model, the PI loop, `learning_period` 0 and then the sine's period) track a sine of
PERIOD_S over +-300 um for --periods periods, after LEAD_IN_S at its middle (from the compensator's first command); the table gives the RMS error of the first and the last period, the
best, and the periods within 1 % of the sine's span, through the nodes and in process. Prints one table (also to
bench/results/learning_nodes.md).

    .venv/bin/python bench/bench_learning_nodes.py [--time-scale 50] [--periods 10]

Each run starts stage_node (the simulator on simulated time, stepping once per command: `lockstep_timeout`) and
compensator_node (`control_trigger: joint_states`, every STEP_S of simulated time, the setpoints stamped ahead as
bench_watch_nodes.py's Session sends them, so that the preview acts) as processes. In process: StageSimulator and
Compensator with the node's defaults (imc gains for STEP_S, the preview), the same setpoints. ROS_DOMAIN_ID 231 and 232.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))

from bench_watch_nodes import STEP_S, Session  # noqa: E402
from record_results import recorded  # noqa: E402

from sma_stage.control import Compensator  # noqa: E402
from sma_stage.control.compensator import imc_gains  # noqa: E402
from sma_stage.model.kinds import load_any_model_file  # noqa: E402
from sma_stage.nodes.launch import CONFIG_DIR, DEFAULT_MODEL_FILE, NodeProcesses, RosClient, wait_for  # noqa: E402
from sma_stage.plant import StageSimulator  # noqa: E402

PERIOD_S = 50.0
LEAD_IN_S = 60.0  # at the sine's middle before it starts [s]: not scored
MIDDLE_M, AMPLITUDE_M = 0.0, 3e-4
FIRST_DOMAIN = 231  # the benches' 220-232 (the tests take 120-219): bench_watch_nodes.py takes them from 220 up


def sine_from(start_s: float):
    """The setpoint [m] at time t [s]: the middle until start_s, then the sine."""
    return lambda t: MIDDLE_M + AMPLITUDE_M * math.sin(2.0 * math.pi * max(t - start_s, 0.0) / PERIOD_S)


def period_rms_pct(times_s: np.ndarray, positions_m: np.ndarray, setpoint, start_s: float, periods: int) -> np.ndarray:
    """Each period's RMS error [% of the sine's span] of the positions at their times against the setpoint then."""
    wanted = np.array([setpoint(t) for t in times_s])
    error = 100.0 * (positions_m - wanted) / (2.0 * AMPLITUDE_M)
    index = np.floor((times_s - start_s) / PERIOD_S).astype(int)
    return np.array([np.sqrt(np.mean(error[index == k] ** 2)) for k in range(periods)])


def through_nodes(domain: int, time_scale: float, learning_period_s: float, periods: int, out_dir: Path) -> np.ndarray:
    """Per-period RMS errors [%] through the stage and compensator executables."""
    with NodeProcesses(out_dir, domain) as nodes:
        nodes.start("compensator_node", {"rate_hz": 1.0 / STEP_S, "use_sim_time": True,
                                         "control_trigger": "joint_states", "learning_period": learning_period_s},
                    [CONFIG_DIR / "compensator.yaml"])
        with RosClient(domain, "bench_learning_nodes", use_sim_time=True) as client:
            session = Session(client.node)
            client.wait_for_services(["compensator/reload"], 120.0, nodes.check_running)
            nodes.start("stage_node", {"rate_hz": time_scale / STEP_S, "time_scale": time_scale,
                                       "command_timeout": 5.0, "use_sim_time": True, "lockstep_timeout": 0.5},
                        [CONFIG_DIR / "stage.yaml"])
            client.wait_for_services(["stage/stop"], 60.0, nodes.check_running)
            wait_for(lambda: session.now_s() > 1.0, 60.0, "joint_states", nodes.check_running)
            session.profile = sine_from(math.inf)  # the middle, until the compensator commands (discovery done)
            wait_for(lambda: session.states[-1][2] != 0.0, 60.0, "the compensator's first command", nodes.check_running)
            start_s = session.now_s() + LEAD_IN_S
            setpoint = sine_from(start_s)
            session.profile = setpoint
            until_s = start_s + periods * PERIOD_S
            wait_for(lambda: session.now_s() >= until_s, 20.0 * (until_s - start_s) / time_scale + 120.0,
                     f"{until_s:.0f} s of simulated time", nodes.check_running)
            session.profile = None
            with session._lock:
                states = np.array(session.states)
        nodes.stop_all()
    kept = (states[:, 0] >= start_s) & (states[:, 0] < until_s)
    return period_rms_pct(states[kept, 0], states[kept, 1], setpoint, start_s, periods)


def in_process(learning_period_s: float, periods: int) -> np.ndarray:
    """Per-period RMS errors [%] of the same loop on StageSimulator in this process."""
    model = load_any_model_file(DEFAULT_MODEL_FILE)
    stage = StageSimulator(seed=0)
    core = Compensator(model, 5.0, **imc_gains(model, STEP_S), learning_period_s=learning_period_s)
    ahead = round(core.preview_s() / STEP_S)
    setpoint = sine_from(LEAD_IN_S)
    measured, times, positions = stage.state.measured_position_m, [], []
    for k in range(round((LEAD_IN_S + periods * PERIOD_S) / STEP_S)):
        now_s = k * STEP_S
        times.append(now_s)
        positions.append(measured)
        current = core.command(setpoint(now_s), measured, STEP_S if k else 0.0, ahead_m=setpoint(now_s + ahead * STEP_S))
        measured = stage.step(current, STEP_S).measured_position_m
    times_s, kept = np.array(times), slice(round(LEAD_IN_S / STEP_S), None)
    return period_rms_pct(times_s[kept], np.array(positions)[kept], setpoint, LEAD_IN_S, periods)


def cells(rms: np.ndarray) -> str:
    return f"{rms[0]:.2f} / {rms[-1]:.2f} / {rms.min():.2f} | {int(np.sum(rms <= 1.0))} of {rms.size}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--time-scale", type=float, default=50.0)
    parser.add_argument("--periods", type=int, default=10)
    args = parser.parse_args()
    started = time.perf_counter()
    lines = ["| learning_period [s] | nodes: RMS % of the span, first / last / best period | periods within 1 % | "
             "in process: the same | periods within 1 % |", "|---|---|---|---|---|"]
    print("\n".join(lines), flush=True)
    with tempfile.TemporaryDirectory() as scratch:
        for index, learning in enumerate((0.0, PERIOD_S)):
            nodes = through_nodes(FIRST_DOMAIN + index, args.time_scale, learning, args.periods, Path(scratch) / str(index))
            lines.append(f"| {learning:g} | {cells(nodes)} | {cells(in_process(learning, args.periods))} |")
            print(lines[-1], flush=True)
    print(f"\n{time.perf_counter() - started:.0f} s, time scale {args.time_scale:g}")


if __name__ == "__main__":
    with recorded(__file__):
        main()
