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

# The master first, waited for as long as it takes: roslaunch gives a master
# it starts itself 10 s to answer, which a slow user-mode Linux guest can
# miss ("could not contact master"). With a master running, roslaunch starts
# only rosout and the launch file's nodes.
# (A command started in the background of a script ignores SIGINT: the
# master is stopped with SIGTERM.)
master_log="$REPO/.results/demo/rosmaster.log"
rosmaster --core -p 11311 > "$master_log" 2>&1 &
master_pid=$!
launch_pid=
trap 'kill -INT $launch_pid 2>/dev/null; wait $launch_pid 2>/dev/null; kill -TERM $master_pid 2>/dev/null; wait $master_pid 2>/dev/null' EXIT
for _ in $(seq 1 240); do
  python3 -c 'import rosgraph, sys; sys.exit(0 if rosgraph.is_master_online() else 1)' 2>/dev/null && break
  kill -0 $master_pid 2>/dev/null || { echo "the ROS master exited:"; tail -20 "$master_log"; exit 1; }
  sleep 0.5
done

launch_log="$REPO/.results/demo/roslaunch.log"
echo "\$ roslaunch maxon_epos4_ros_canopen maxon_epos4_canopen_motor_1dof_ppm.launch sim:=true device:=vcan0"
roslaunch maxon_epos4_ros_canopen maxon_epos4_canopen_motor_1dof_ppm.launch sim:=true device:=vcan0 \
    > "$launch_log" 2>&1 &
launch_pid=$!

python3 "$REPO/tools/demo_client.py" "$@"
status=$?
if [ $status != 0 ]; then
  echo "--- the demo failed; last lines of roslaunch's output ($launch_log):"
  tail -30 "$launch_log"
fi
exit $status
