# Source this file to use the built workspace: ROS, the project's packages and
# the .venv Python (python-can, canopen, xacro) on PATH.
_repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
if [ -f /opt/ros/noetic/setup.bash ] && [ -z "${ROS_DISTRO:-}" ]; then
  . /opt/ros/noetic/setup.bash
fi
. "$_repo/.ws/devel/setup.bash"
export PATH="$_repo/.venv/bin:$PATH"
export ROS_HOSTNAME=${ROS_HOSTNAME:-localhost}
export ROS_MASTER_URI=${ROS_MASTER_URI:-http://localhost:11311}
unset _repo
