"""One SMA stage: the stage (simulator or SCPI instruments), the compensator and the identification node.

    ros2 launch sma_stage stage.launch.py [namespace:=stage2] [backend:=sim|visa] [hardware_file:=FILE]
        [params_file:=FILE] [use_sim_time:=true] [time_scale:=20.0] [lockstep:=true] [record_bag:=DIR]
        [bag_storage:=mcap]

Each node reads its installed config/<node>.yaml, then params_file (if given; sections `/**/stage:`,
`/**/compensator:`, `/**/identification:` as in the installed files), then the arguments. The stage starts in
its `autostart` state: active on the simulator, inactive on instruments (`ros2 lifecycle set
/[NS/]stage activate` switches the output on; this file never does). In a namespace on simulated time the
nodes follow the stage's own clock (/NS/clock, remapped from /clock).
"""

from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

LOCKSTEP_TIMEOUT_S = 0.5  # [wall s] the stage's wait for the command answering its last position (lockstep:=true)
ARGUMENTS = {
    "namespace": ("", "namespace of the stage's three nodes and topics (empty: the root namespace)"),
    "backend": ("sim", "sim: the embedded physics simulator; visa: SCPI instruments (hardware_file)"),
    "hardware_file": ("", "backend visa: the instruments' YAML (share/sma_stage/config/hardware_example.yaml)"),
    "params_file": ("", "a parameter file with sections for stage, compensator and identification, read after "
                        "the installed config/*.yaml"),
    "use_sim_time": ("false", "true: the simulated stage publishes the clock and every node runs on it"),
    "time_scale": ("1.0", "simulated seconds per second (the simulator; with use_sim_time the clock runs this "
                          "fast)"),
    "lockstep": ("false", "true (the simulator on use_sim_time): the stage steps once the compensator answered its "
                          "last position (lockstep_timeout 0.5 s), the compensator answers each position "
                          "(control_trigger joint_states): the loop of one process, however fast the clock runs"),
    "record_bag": ("", "rosbag2 directory the identification node records current_applied and joint_states "
                       "into (empty: none)"),
    "bag_storage": ("mcap", "storage of record_bag: mcap (Foxglove and PlotJuggler open it) or sqlite3"),
}


def nodes(context, *_args, **_kwargs) -> list[Node]:
    """The three nodes with the arguments' values."""
    value = {name: LaunchConfiguration(name).perform(context) for name in ARGUMENTS}
    config = Path(get_package_share_directory("sma_stage")) / "config"
    sim_time = value["use_sim_time"].lower() in ("true", "1")
    time_scale = float(value["time_scale"])
    remappings = [("/clock", "clock")] if value["namespace"].strip("/") else []

    def files(name: str) -> list[str]:
        return [str(config / f"{name}.yaml")] + ([value["params_file"]] if value["params_file"] else [])

    lockstep = value["lockstep"].lower() in ("true", "1")
    stage = {"backend": value["backend"], "time_scale": time_scale, "use_sim_time": sim_time,
             **({"lockstep_timeout": LOCKSTEP_TIMEOUT_S} if lockstep else {})}
    compensator = {"use_sim_time": sim_time, "time_scale": time_scale,
                   **({"control_trigger": "joint_states"} if lockstep else {})}
    if value["hardware_file"]:
        stage["hardware_file"] = value["hardware_file"]
    identification = {"use_sim_time": sim_time, "excite_time_scale": 1.0 if sim_time else time_scale}
    if value["record_bag"]:
        identification.update(record_bag=value["record_bag"], bag_storage=value["bag_storage"])
    return [
        Node(package="sma_stage", executable="stage_node", name="stage", namespace=value["namespace"],
             parameters=[*files("stage"), stage], remappings=remappings, output="screen"),
        Node(package="sma_stage", executable="compensator_node", name="compensator", namespace=value["namespace"],
             parameters=[*files("compensator"), compensator],
             remappings=remappings, output="screen"),
        Node(package="sma_stage", executable="identification_node", name="identification",
             namespace=value["namespace"], parameters=[*files("identification"), identification],
             remappings=remappings, output="screen"),
    ]


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription([DeclareLaunchArgument(name, default_value=default, description=description)
                              for name, (default, description) in ARGUMENTS.items()]
                             + [OpaqueFunction(function=nodes)])
