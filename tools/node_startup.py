#!/usr/bin/env python3
"""Time from process start to advertised services, for every node of a launch.

    tools/vcan_run.sh bash -c '. tools/env.sh && python3 tools/node_startup.py [--repeat N]'

For each node of the launch files below (the driver, the simulator, the MANI
nodes), with the parameters those launch files set: start a master, load the
parameters, start the node alone with the command line roslaunch would use,
and poll the master until the node's services and topics stop changing. The
figure is the time from the process start to the moment its final set of
services and publications was first complete (rospy's own get_loggers and
set_logger_level leave out), and to the first of its own services.

Needs vcan0 (the driver and the simulator open it): run it through
tools/vcan_run.sh, which uses user-mode Linux where the kernel has no vcan.
"""
from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import time
from typing import Any, Dict, List, Optional, Set, Tuple

LAUNCHES = [
    ("maxon_epos4_ros_canopen", "maxon_epos4_canopen_motor_2dof_pvm.launch", ["sim:=true", "device:=vcan0"]),
    ("mani_ros", "mani.launch", ["sim:=true", "device:=vcan0"]),
]
SETTLE = 3.0      # s without change: the node has advertised all it will
TIMEOUT = 120.0   # s, user-mode Linux on a loaded host
ROSPY_OWN = ("/get_loggers", "/set_logger_level")


def graph_of(master: Any, node: str) -> Set[str]:
    """The services and publications the master lists for `node`."""
    pubs, _, srvs = master.getSystemState()
    out = {"srv " + s for s, nodes in srvs if node in nodes and not s.endswith(ROSPY_OWN)}
    out |= {"pub " + t for t, nodes in pubs if node in nodes and t != "/rosout"}
    return out


def time_node(master: Any, cmd: List[str], name: str, env: Dict[str, str]) -> Tuple[Optional[float], Optional[float], int]:
    """(s to the first own service, s to the final set, size of the set)."""
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    first_srv = None
    last_change, last = t0, set()  # type: float, Set[str]
    try:
        while time.monotonic() - t0 < TIMEOUT and proc.poll() is None:
            now = time.monotonic()
            try:
                seen = graph_of(master, name)
            except Exception:
                seen = last
            if first_srv is None and any(s.startswith("srv ") for s in seen):
                first_srv = now - t0
            if seen != last:
                last, last_change = seen, now
            elif last and now - last_change > SETTLE:
                break
            time.sleep(0.05)
        ready = (last_change - t0) if last else None
        return first_srv, ready, len(last)
    finally:
        _stop(proc)
        # let the master forget the node before the next one starts
        time.sleep(0.5)


def _stop(proc: subprocess.Popen) -> None:
    """SIGINT as roslaunch sends it, SIGKILL after 30 s."""
    for sig, wait in ((signal.SIGINT, 30), (signal.SIGKILL, None)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            break
        try:
            proc.wait(timeout=wait)
            break
        except subprocess.TimeoutExpired:
            continue
    proc.wait()


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=1, help="start each node this many times (median printed)")
    ap.add_argument("--only", default="", help="only nodes whose name contains this")
    ap.add_argument("--replace", action="append", default=[], metavar="NAME=EXECUTABLE",
                    help="start node NAME (e.g. /maxon/canopen_motor) from EXECUTABLE instead, "
                         "to compare two versions of a node in one run")
    args = ap.parse_args(argv)

    import rosgraph
    import roslaunch.config
    import roslaunch.node_args
    import roslaunch.launch
    import rospkg
    from rosmaster.master import Master

    master_proc = Master(port=0)
    master_proc.start()
    uri = master_proc.uri
    env = dict(os.environ, ROS_MASTER_URI=uri)
    os.environ["ROS_MASTER_URI"] = uri
    master = rosgraph.Master("/node_startup", master_uri=uri)
    rp = rospkg.RosPack()
    rows = []
    for pkg, launch, largs in LAUNCHES:
        path = os.path.join(rp.get_path(pkg), "launch", launch)
        config = roslaunch.config.load_config_default([(path, largs)], None)
        config.master.uri = uri
        runner = roslaunch.launch.ROSLaunchRunner("node_startup", config, is_core=False)
        runner._load_parameters()
        for node in config.nodes:
            name = (node.namespace or "/").rstrip("/") + "/" + node.name
            if args.only not in name:
                continue
            cmd = roslaunch.node_args.create_local_process_args(node, config.machines[""])
            label = "%s/%s" % (node.package, node.type)
            for spec in args.replace:
                target, _, executable = spec.partition("=")
                if target == name:
                    cmd = [executable] + cmd[1:]
                    label = executable
            # the spawner only acts on a driver: it waits for services, so it is not timed
            if node.type == "controller_manager":
                continue
            node_env = dict(env, ROS_NAMESPACE=node.namespace or "/")
            node_env.update(dict(node.env_args))
            firsts, readies, size = [], [], 0
            for _ in range(args.repeat):
                first, ready, size = time_node(master, cmd, name, node_env)
                if first is not None:
                    firsts.append(first)
                if ready is not None:
                    readies.append(ready)
            rows.append((name, label, firsts, readies, size))
            print("%-34s %-46s first service %6s s   all advertised %6s s   (%d services+topics, %d runs)" % (
                name, rows[-1][1], _med(firsts), _med(readies), size, args.repeat), flush=True)
    master_proc.stop()
    return 0


def _med(values: List[float]) -> str:
    return "%.2f" % statistics.median(values) if values else "-"


if __name__ == "__main__":
    sys.exit(main())
