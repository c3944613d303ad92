#!/usr/bin/env bash
# Build, outside the project, a venv with the real `ros2` CLI and `ros2 launch` (jazzy) to check the launch
# files as a ROS user runs them. Not a dependency of the package or its tests.
#
# usage: tools/ros2launch_venv.sh ROS2CLI_VENV_SH [VENV]
#   ROS2CLI_VENV_SH  the ros2cli venv script (builds ros2cli + rosidl_runtime_py on the project's ROS wheels)
#   VENV             default: $HOME/.cache/ros2cli_venv
# Needs MIRROR_DIR holding bare git dirs of github ros2/ros2cli, ros2/rosidl_runtime_py, ros2/launch and
# ros2/launch_ros (as ros2+launch/repo, ...), and MAIN_DIR the project checkout with its .venv.
# Then: colcon build the package, `. VENV/bin/activate`, `export AMENT_PREFIX_PATH=<install/sma_stage>:VENV`,
# `ros2 launch sma_stage stage.launch.py namespace:=stage2`.
set -euo pipefail

SCRIPT=${1:?pass the path of ros2cli_venv.sh}
VENV=${2:-$HOME/.cache/ros2cli_venv}
BRANCH=jazzy
bash "$SCRIPT" "$VENV"

SRC=$(mktemp -d)
trap 'rm -rf "$SRC"' EXIT
git --git-dir="$MIRROR_DIR/ros2+launch/repo" archive "$BRANCH" launch launch_xml launch_yaml | tar -x -C "$SRC"
git --git-dir="$MIRROR_DIR/ros2+launch_ros/repo" archive "$BRANCH" launch_ros ros2launch | tar -x -C "$SRC"
PIP=("$VENV/bin/python" -m pip install -q --disable-pip-version-check)
export PYTHONWARNINGS=ignore
"${PIP[@]}" "osrf-pycommon==2.0.2"
for p in launch launch_xml launch_yaml launch_ros ros2launch; do
  "${PIP[@]}" --no-deps --no-build-isolation "$SRC/$p"
done
# launch_ros imports composition_interfaces (for composable nodes, which sma_stage's launch files do not use);
# no PyPI wheel holds it, so the venv gets a module with the one name launch_ros reads at import.
STUB="$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')/composition_interfaces"
mkdir -p "$STUB"
echo '"""Import stand-in: composable nodes are not available in this venv."""' > "$STUB/__init__.py"
printf '%s\n' '"""Import stand-in: composable nodes are not available in this venv."""' '' '' \
  'class LoadNode:' '    class Request:' '        pass' > "$STUB/srv.py"
echo "launch $(git --git-dir="$MIRROR_DIR/ros2+launch/repo" describe --tags --always "$BRANCH"), launch_ros" \
  "$(git --git-dir="$MIRROR_DIR/ros2+launch_ros/repo" describe --tags --always "$BRANCH")"
AMENT_PREFIX_PATH="$VENV" "$VENV/bin/ros2" launch --help | sed -n '1,2p'
