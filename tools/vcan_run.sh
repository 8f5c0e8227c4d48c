#!/usr/bin/env bash
# Run a command where a real SocketCAN vcan0 exists.
#
#   tools/vcan_run.sh COMMAND [ARGS...]
#   tools/vcan_run.sh --which          prints the transport it would use: native or uml
#
# Natively when this kernel has vcan (vcan0 exists, or `ip link add` works);
# otherwise inside Debian's user-mode Linux (linux.uml), which boots a 6.1
# kernel with vcan as an ordinary process over the host file system. Never
# falls back to "no CAN": if neither works it fails.
# VCAN_TRANSPORT=native|uml forces one. Prints the transport used as
# "vcan0: native" or "vcan0: user-mode Linux, kernel X.Y.Z"; exits with the
# command's exit status (read back from a file in UML, whose own exit status
# is not the command's).
set -uo pipefail

REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
[ $# -ge 1 ] || { echo "usage: $0 COMMAND [ARGS...]" >&2; exit 2; }

native_vcan_ready() {
  if ip link show vcan0 >/dev/null 2>&1; then
    ip link set vcan0 up 2>/dev/null || true
    ip link show vcan0 | grep -q "UP" && return 0
    return 1
  fi
  modprobe vcan 2>/dev/null || true
  ip link add dev vcan0 type vcan 2>/dev/null && ip link set vcan0 up 2>/dev/null
}

transport=${VCAN_TRANSPORT:-auto}
if [ "$transport" = auto ]; then
  if native_vcan_ready; then transport=native; else transport=uml; fi
elif [ "$transport" = native ] && ! native_vcan_ready; then
  echo "vcan0: cannot be brought up natively (VCAN_TRANSPORT=native)" >&2
  exit 3
fi

if [ "$1" = --which ]; then
  echo "$transport"
  exit 0
fi

if [ "$transport" = native ]; then
  # A second bus for tests on a device other than vcan0 (best effort).
  { ip link show vcan1 || ip link add dev vcan1 type vcan; } >/dev/null 2>&1
  ip link set vcan1 up >/dev/null 2>&1 || true
  echo "vcan0: native"
  "$@"
  exit $?
fi

if ! command -v linux.uml >/dev/null; then
  echo "vcan0: this kernel has no vcan and user-mode Linux (linux.uml) is not installed: no CAN, nothing run" >&2
  exit 3
fi

rundir="$REPO/.results/uml/run-$$-$(date +%s)"
mkdir -p "$rundir"
# What the command inside needs: its argument vector and our environment.
printf '%q ' "$@" > "$rundir/cmd"
export -p | grep -vE '^declare -x (PWD|OLDPWD|SHLVL|_|TERM|HOSTNAME)=' > "$rundir/env"
echo "$PWD" > "$rundir/cwd"

# UML's console is this process's stdout; its own messages go to uml.log.
linux.uml mem=2G root=/dev/root rootfstype=hostfs rootflags=/ rw quiet loglevel=0 \
  init="$REPO/tools/uml/init.sh" VCAN_RUNDIR="$rundir" \
  con=null con0=null,fd:1 < /dev/null 2> "$rundir/uml.log" | sed -u "s/\r*$//" | grep --line-buffered -vx "Powering off."

if [ ! -f "$rundir/status" ]; then
  echo "vcan0: user-mode Linux ended without a result (see $rundir/uml.log)" >&2
  tail -5 "$rundir/uml.log" >&2
  exit 3
fi
if [ "$(cat "$rundir/status")" = "novcan" ]; then
  echo "vcan0: could not be brought up inside user-mode Linux" >&2
  exit 3
fi
echo "vcan0: user-mode Linux, kernel $(cat "$rundir/kernel")"
exit "$(cat "$rundir/status")"
