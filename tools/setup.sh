#!/usr/bin/env bash
# Idempotent setup used by `make demo` and `make test`:
#   1. system packages (Debian 12: ROS 1 from Debian, user-mode Linux, can-utils;
#      Ubuntu with ROS Noetic: rosdep),
#   2. .venv from the system Python with the pinned PyPI packages (and
#      .venv38 from a Python 3.8, built in the background meanwhile),
#   3. the catkin workspace .ws/ (inside the clone, ignored by git).
# Nothing outside the clone is touched except system packages.
set -euo pipefail

REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$REPO"
log() { printf '[setup] %s\n' "$*"; }

# --- 1. system packages -------------------------------------------------------
DEBIAN_PACKAGES=(
  ros-core python3-rospy python3-rostest librostest-dev python3-actionlib
  python3-actionlib-tools python3-std-srvs python3-std-msgs ros-std-msgs
  libstd-msgs-dev python3-sensor-msgs python3-nav-msgs python3-geometry-msgs
  python3-trajectory-msgs python3-diagnostic-msgs python3-diagnostic-updater
  python3-tf2-ros catkin ros-message-generation ros-message-runtime
  python3-genpy python3-genmsg rosbash python3-catkin-pkg python3-rospkg
  ros-robot-state-publisher can-utils joint-state-publisher
  ros-trajectory-msgs libtrajectory-msgs-dev ros-actionlib-msgs libactionlib-msgs-dev
  ros-sensor-msgs libsensor-msgs-dev ros-std-srvs libstd-srvs-dev
  ros-geometry-msgs libgeometry-msgs-dev ros-nav-msgs libnav-msgs-dev
  ros-diagnostic-msgs libdiagnostic-msgs-dev libroscpp-dev libactionlib-dev
  python3-tf2-geometry-msgs libtf2-msgs-dev ros-tf2-msgs python3-tf2-msgs
  user-mode-linux kmod iproute2 python3-venv python3-yaml make g++ cmake
  python3-matplotlib  # benchmark plots (Debian's, built against Debian's numpy)
  # what a user's own package needs to build on this workspace
  # (catkin_create_pkg PKG std_msgs std_srvs rospy roscpp roslib)
  libroslib-dev librospack-dev python3-roslib
)

os_id=$( . /etc/os-release 2>/dev/null; echo "${ID:-unknown}-${VERSION_ID:-}" )
ROS_SETUP=""
if [ -f /opt/ros/noetic/setup.bash ]; then
  # Ubuntu 20.04 with ROS Noetic from the ROS repositories: use the system ROS
  # and rosdep for the package dependencies (see README.md).
  ROS_SETUP=/opt/ros/noetic/setup.bash
  # shellcheck disable=SC1090
  set +u; . "$ROS_SETUP"; set -u
  if command -v rosdep >/dev/null; then
    log "ROS Noetic found: rosdep install"
    rosdep install --from-paths "$REPO" --ignore-src -r -y || log "rosdep reported missing keys (see above)"
  fi
elif [ "$os_id" = "debian-12" ]; then
  missing=()
  for p in "${DEBIAN_PACKAGES[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
  done
  if [ ${#missing[@]} -gt 0 ]; then
    log "installing ${#missing[@]} Debian packages: ${missing[*]}"
    SUDO=""; [ "$(id -u)" = 0 ] || SUDO=sudo
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
  else
    log "Debian packages: all present"
  fi
else
  log "unsupported system '$os_id': install ROS 1 (Noetic) yourself, then run this again"
  exit 1
fi

# --- 2a. Python 3.8 (ROS Noetic's) for the ROS-free unit tests ---------------
# Wherever a 3.8 interpreter exists (PYTHON38, python3.8 on PATH or pyenv's),
# .venv38 gets the same requirements (their markers pick python-can 4.5
# there); tools/run_tests.sh runs the ROS-free unit tests with it, so that
# code a Noetic robot cannot run fails here first. No ROS in it.
SYS_PY=/usr/bin/python3
req_hash=$(sha256sum requirements.txt | cut -d' ' -f1)
find_python38() {
  local candidate
  for candidate in "${PYTHON38:-}" "$(command -v python3.8 || true)" \
      "${PYENV_ROOT:-$HOME/.pyenv}"/versions/3.8*/bin/python /root/.pyenv/versions/3.8*/bin/python; do
    [ -n "$candidate" ] && [ -x "$candidate" ] || continue
    "$candidate" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 8))' 2>/dev/null && { echo "$candidate"; return 0; }
  done
  return 1
}
make_venv38() {
  rm -rf .venv38
  if "$py38" -m venv .venv38 && .venv38/bin/pip install -q --disable-pip-version-check -r requirements.txt; then
    echo "$req_hash" > .venv38/.requirements.sha256
  else
    log ".venv38 could not be made: the Python 3.8 run of the unit tests will report that"
    rm -rf .venv38
  fi
}
venv38_pid=""
if py38=$(find_python38); then
  if [ ! -x .venv38/bin/python ] || [ "$(cat .venv38/.requirements.sha256 2>/dev/null)" != "$req_hash" ]; then
    # pip runs on one core: .venv and the workspace build take the other meanwhile
    log "creating .venv38 from $py38 for the ROS-free unit tests, beside .venv and the workspace"
    venv38_log=$(mktemp)
    make_venv38 > "$venv38_log" 2>&1 &
    venv38_pid=$!
  else
    log ".venv38: up to date"
  fi
else
  log "no Python 3.8 interpreter: the ROS-free unit tests run under $("$SYS_PY" -V 2>&1) only"
fi

# --- 2b. Python environment --------------------------------------------------
if [ ! -x .venv/bin/python ] || [ "$(cat .venv/.requirements.sha256 2>/dev/null)" != "$req_hash" ]; then
  log "creating .venv from $SYS_PY with the pinned requirements"
  rm -rf .venv
  "$SYS_PY" -m venv --system-site-packages .venv
  .venv/bin/pip install -q --disable-pip-version-check -r requirements.txt
  echo "$req_hash" > .venv/.requirements.sha256
else
  log ".venv: up to date"
fi

# --- 3. catkin workspace ------------------------------------------------------
# .ws/src holds links to the packages of this clone. .ws/CATKIN_IGNORE keeps a
# user's outer workspace (clone inside ~/catkin_ws/src) from finding them twice.
mkdir -p .ws/src
touch .ws/CATKIN_IGNORE
wanted=()
for pkg in maxon_epos4_ros1 maxon_epos4_ros_canopen maxon_epos4_moveit_config mani_ros; do
  [ -f "$pkg/package.xml" ] && wanted+=("$pkg")
done
# compat/ holds ros_canopen's and ros_control's package names Debian lacks
# (message packages, canopen_motor_node, controller_manager, xacro); link one
# in only where the system does not have it already.
for dir in compat/*/; do
  pkg=$(basename "$dir")
  [ -f "$dir/package.xml" ] || continue
  if ROS_PACKAGE_PATH=/usr/share:/opt/ros/noetic/share rospack find "$pkg" >/dev/null 2>&1; then
    log "system provides $pkg: compat/$pkg not used"
  else
    wanted+=("compat/$pkg")
  fi
done
# Refresh the links: drop stale ones, add the wanted ones.
for link in .ws/src/*; do
  [ -L "$link" ] || continue
  keep=0
  for w in "${wanted[@]}"; do [ "$(basename "$w")" = "$(basename "$link")" ] && keep=1; done
  [ $keep = 1 ] || rm -f "$link"
done
for w in "${wanted[@]}"; do
  ln -sfn "$REPO/$w" ".ws/src/$(basename "$w")"
done

log "building the workspace (.ws) with .venv/bin/python3"
(
  # One build at a time: parallel test runs share this workspace.
  exec 9> .ws/.build.lock
  flock 9
  cd .ws
  set +u
  [ -n "$ROS_SETUP" ] && . "$ROS_SETUP"
  set -u
  # /usr/bin first: catkin must find Debian's python3 and its catkin_pkg.
  # The .venv python (Debian's, plus canopen/python-can) goes into the
  # shebang of the devel-space relays rosrun/roslaunch start nodes through.
  PATH=/usr/bin:$PATH catkin_make -DPYTHON_EXECUTABLE="$REPO/.venv/bin/python3" -DCMAKE_BUILD_TYPE=Release \
      > build.log 2>&1 || { tail -40 build.log; echo "[setup] catkin_make failed (full log: .ws/build.log)"; exit 1; }
)
log "workspace built: source tools/env.sh to use it"
if [ -n "$venv38_pid" ]; then
  wait "$venv38_pid" || true
  cat "$venv38_log"
  rm -f "$venv38_log"
  [ -x .venv38/bin/python ] && log ".venv38 made"
fi
