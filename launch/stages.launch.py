"""N simulated SMA stages side by side, each a stage and its compensator in one process
(`stage_and_compensator`, which keeps many stages' cycles on time: bench/bench_stages.py), in namespaces
stage_1 ... stage_N.

    ros2 launch sma_stage stages.launch.py count:=4 [params_file:=FILE] [use_sim_time:=true] [time_scale:=1.0]

Each stage's parameters: the installed config/stage.yaml and config/compensator.yaml, then params_file, then
the arguments, and a seed of its own (its index) so the stages' sensor noise differs. The nodes keep their
names (stage, compensator: a launch `name` would rename both nodes of the process). On simulated time each
stage publishes its own clock (/stage_K/clock) and its nodes follow it.
"""

from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

ARGUMENTS = {
    "count": ("2", "number of simulated stages (1 to 64)"),
    "params_file": ("", "a parameter file with stage and compensator sections, read after the installed ones"),
    "use_sim_time": ("false", "true: each stage publishes its own clock and its nodes run on it"),
    "time_scale": ("1.0", "simulated seconds per second"),
}
MAX_STAGES = 64


def stages(context, *_args, **_kwargs) -> list[Node]:
    """One stage_and_compensator process per stage."""
    value = {name: LaunchConfiguration(name).perform(context) for name in ARGUMENTS}
    count = int(value["count"])
    if not 1 <= count <= MAX_STAGES:
        raise ValueError(f"count must be 1 to {MAX_STAGES}, got {count}")
    config = Path(get_package_share_directory("sma_stage")) / "config"
    files = [str(config / "stage.yaml"), str(config / "compensator.yaml")]
    files += [value["params_file"]] if value["params_file"] else []
    sim_time = value["use_sim_time"].lower() in ("true", "1")
    # time_scale reaches both nodes of the process: the stage runs that fast, and the compensator counts stage
    # seconds with it (not applied with use_sim_time, where its clock is the stage's)
    overrides = {"backend": "sim", "time_scale": float(value["time_scale"]), "use_sim_time": sim_time}
    return [Node(package="sma_stage", executable="stage_and_compensator", namespace=f"stage_{index}", parameters=[*files, {**overrides, "seed": index}],
                 remappings=[("/clock", "clock")], output="screen")
            for index in range(1, count + 1)]


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription([DeclareLaunchArgument(name, default_value=default, description=description)
                              for name, (default, description) in ARGUMENTS.items()]
                             + [OpaqueFunction(function=stages)])
