#!/bin/sh
# PID 1 inside user-mode Linux (see tools/vcan_run.sh): mount what Linux
# needs, load the CAN modules that Debian ships for the UML kernel, bring up
# lo, vcan0 and vcan1, run the command, write its exit status to the run folder on
# the host file system, and power off.
PATH=/usr/sbin:/usr/bin:/sbin:/bin
export PATH
rundir=$VCAN_RUNDIR

mount -t proc proc /proc
mount -t sysfs sysfs /sys
# A private /dev and /dev/shm. /tmp stays the host's: the clone (and so the
# run folder) may live there.
mount -t devtmpfs devtmpfs /dev 2>/dev/null || true
mkdir -p /dev/shm /dev/pts
[ -e /dev/fd ] || ln -s /proc/self/fd /dev/fd
[ -e /dev/stdin ] || ln -s /proc/self/fd/0 /dev/stdin
[ -e /dev/stdout ] || ln -s /proc/self/fd/1 /dev/stdout
[ -e /dev/stderr ] || ln -s /proc/self/fd/2 /dev/stderr
mount -t tmpfs tmpfs /dev/shm
mount -t devpts devpts /dev/pts 2>/dev/null || true
mount -t tmpfs tmpfs /run

kv=$(uname -r)
echo "$kv" > "$rundir/kernel"
# insmod with full paths (dependency order from modules.dep) rather than
# modprobe, which would need /lib/modules/<version> created on the host.
mods=/usr/lib/uml/modules/$kv/kernel
for m in drivers/net/can/dev/can-dev.ko drivers/net/can/vcan.ko net/can/can.ko \
         net/can/can-raw.ko net/can/can-bcm.ko; do
  insmod "$mods/$m" 2>>"$rundir/init.log"
done
ip link set lo up
hostname localhost
if ! { ip link add dev vcan0 type vcan && ip link set vcan0 up; } >>"$rundir/init.log" 2>&1; then
  echo novcan > "$rundir/status"
  poweroff -f
fi
# A second bus for tests that run a stack on a device other than vcan0.
{ ip link add dev vcan1 type vcan && ip link set vcan1 up; } >>"$rundir/init.log" 2>&1

cd "$(cat "$rundir/cwd")" || cd /
# The caller's environment (bash `export -p` form), minus what differs here.
/bin/bash -c ". '$rundir/env'; export HOME=\${HOME:-/root} ROS_HOSTNAME=localhost ROS_MASTER_URI=http://localhost:11311; unset ROS_IP; $(cat "$rundir/cmd")" < /dev/null
echo $? > "$rundir/status"
sync
poweroff -f
