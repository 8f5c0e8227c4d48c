#!/usr/bin/env bash
# The seeds' session, scripted: roslaunch the 1-DOF PPM example with the
# virtual EPOS4 on vcan0, `rosservice call /maxon/driver/init`, command a few
# targets on the position controller's topic and print the joint states as
# the joint moves, then shut the driver down.
set -uo pipefail
REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$REPO"
set +u; . tools/env.sh; set -u
export ROS_LOG_DIR="$REPO/.results/demo/ros_log"
mkdir -p "$ROS_LOG_DIR"

launch_log="$REPO/.results/demo/roslaunch.log"
echo "\$ roslaunch maxon_epos4_ros_canopen maxon_epos4_canopen_motor_1dof_ppm.launch sim:=true device:=vcan0"
roslaunch maxon_epos4_ros_canopen maxon_epos4_canopen_motor_1dof_ppm.launch sim:=true device:=vcan0 \
    > "$launch_log" 2>&1 &
launch_pid=$!
trap 'kill -INT $launch_pid 2>/dev/null; wait $launch_pid 2>/dev/null' EXIT

python3 "$REPO/tools/demo_client.py" "$@"
status=$?
if [ $status != 0 ]; then
  echo "--- the demo failed; last lines of roslaunch's output ($launch_log):"
  tail -30 "$launch_log"
fi
exit $status
