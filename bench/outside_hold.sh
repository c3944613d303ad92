#!/usr/bin/env bash
# Issue 12's outside-client check of holding a setpoint, as a ROS engineer would run it: the three
# installed nodes with their defaults and use_sim_time (stage time_scale 20), `ros2 service call`
# ~/excite then ~/refit, `ros2 topic pub --once /setpoint` at 70 % of the stroke measured during the
# excitation, held for 1,280 s of simulated time. Prints the settled error: the mean position over the
# last 600 s against the setpoint, in % of the stroke, and the ripple about that mean.
#
# Not part of the tests: it needs the real `ros2` CLI, which is not on PyPI. Build it outside the project
# with ../shared/tools/ros2cli_venv.sh (its header says how), and the package with colcon:
#   mkdir -p WS/src && git clone . WS/src/sma_stage && (. R2VENV/bin/activate && cd WS && python -m colcon build)
#
# usage: bench/outside_hold.sh OUT_DIR FEEDBACK(true|false) [ROS_DOMAIN_ID] [R2VENV] [WS]
#   R2VENV default $HOME/.cache/ros2cli_venv; WS (the colcon workspace) default $HOME/sma_ws
# About 4.5 min of wall time on two cores.
set -u
OUT=$1; FEEDBACK=$2; DOMAIN=${3:-77}
R2VENV=${4:-$HOME/.cache/ros2cli_venv}; WS=${5:-$HOME/sma_ws}
INSTALL=$WS/install/sma_stage
mkdir -p "$OUT"
# shellcheck disable=SC1091
source "$R2VENV/bin/activate"
export AMENT_PREFIX_PATH=$INSTALL:$R2VENV PYTHONPATH=$INSTALL/lib/python3.11/site-packages
export ROS_DOMAIN_ID=$DOMAIN RMW_IMPLEMENTATION=rmw_fastrtps_cpp ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST

ros2 run sma_stage stage_node --ros-args -p use_sim_time:=true -p time_scale:=20.0 > "$OUT/stage.log" 2>&1 &
STAGE=$!
ros2 run sma_stage compensator_node --ros-args -p use_sim_time:=true -p "feedback:=$FEEDBACK" > "$OUT/compensator.log" 2>&1 &
COMPENSATOR=$!
ros2 run sma_stage identification_node --ros-args -p use_sim_time:=true > "$OUT/identification.log" 2>&1 &
IDENTIFICATION=$!
# The positions, as `ros2 topic echo` would show them, one CSV line each: simulated stamp [s], position [m].
python - "$OUT/positions.csv" > "$OUT/recorder.log" 2>&1 <<'PY' &
import sys
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import JointState

rclpy.init()
node = rclpy.create_node("outside_recorder", parameter_overrides=[Parameter("use_sim_time", value=True)])
out = open(sys.argv[1], "w", buffering=1)
node.create_subscription(JointState, "joint_states", lambda m: m.position and out.write(
    f"{m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec:.3f},{m.position[0]:.9e}\n"), qos_profile_sensor_data)
try:
    rclpy.spin(node)
except (KeyboardInterrupt, ExternalShutdownException):
    pass
PY
RECORDER=$!
last_stamp() { tail -n 1 "$OUT/positions.csv" | cut -d, -f1; }
sleep 8
until ros2 service call /identification/excite std_srvs/srv/Trigger > "$OUT/excite.txt"; grep -q "success=True" "$OUT/excite.txt"; do
  sleep 2  # refused until the identification node has its first /clock
done
START=$(last_stamp)
until grep -q "excitation finished" "$OUT/identification.log"; do sleep 1; done
END=$(last_stamp)
ros2 service call /identification/refit std_srvs/srv/Trigger > "$OUT/refit.txt"
python - "$OUT/positions.csv" "$START" "$END" > "$OUT/target.txt" <<'PY'
import sys
import numpy as np
d = np.loadtxt(sys.argv[1], delimiter=",")
during = d[(d[:, 0] >= float(sys.argv[2])) & (d[:, 0] <= float(sys.argv[3])), 1]
low, high = during.min(), during.max()
print(f"{low + 0.7 * (high - low):.9e} {low:.9e} {high:.9e}")
PY
read -r SETPOINT LOW HIGH < "$OUT/target.txt"
FROM=$(last_stamp)
ros2 topic pub --once /setpoint std_msgs/msg/Float64 "{data: $SETPOINT}" > "$OUT/setpoint.txt"
while (( $(echo "$(last_stamp) < $FROM + 1280" | bc) )); do sleep 2; done
for wrapper in $STAGE $COMPENSATOR $IDENTIFICATION; do pkill -INT -P "$wrapper"; done
kill -INT $RECORDER; sleep 3; kill $STAGE $COMPENSATOR $IDENTIFICATION 2>/dev/null
python - "$OUT/positions.csv" "$SETPOINT" "$LOW" "$HIGH" "$FEEDBACK" <<'PY'
import sys
import numpy as np
d = np.loadtxt(sys.argv[1], delimiter=",")
setpoint, low, high = (float(v) for v in sys.argv[2:5])
last = d[d[:, 0] >= d[-1, 0] - 600.0, 1]
print(f"feedback {sys.argv[5]}: settled error {100 * abs(last.mean() - setpoint) / (high - low):.3f} % of the "
      f"{1e6 * (high - low):.0f} um stroke; ripple {1e6 * last.std():.2f} um RMS; setpoint {1e6 * setpoint:.1f} um, "
      f"mean {1e6 * last.mean():.1f} um")
PY
grep -o "refit ok.*RMS [0-9.]* % -> [0-9.]* %" "$OUT/identification.log"
