#!/usr/bin/env python3
"""Example: one EPOS4 in Profile Position Mode, driven from Python.

Run it after `roslaunch maxon_epos4_ros_canopen
maxon_epos4_canopen_motor_1dof_ppm.launch` (add `sim:=true` to use the
virtual EPOS4). It calls the driver's init service, then sends a discrete
sine wave of target positions to the joint's position controller and prints
each target next to the position read back from /maxon/joint_states.

Options (also as private parameters, e.g. _cycles:=1):
  --cycles N       sine periods to run (default: run until Ctrl-C)
  --amplitude INC  amplitude in increments (default 10000)
  --steps N        targets per period (default 20)
  --step-time S    seconds between targets (default 0.5)
  --no-init        do not call driver/init (already initialized)
"""
from __future__ import annotations

import argparse
import math
import sys
import threading
from typing import Optional

import rospy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64
from std_srvs.srv import Trigger

NAMESPACE = "/maxon"
JOINT = "base_link1_joint"
COMMAND_TOPIC = NAMESPACE + "/canopen_motor/base_link1_joint_position_controller/command"


class PositionReader:
    """Keeps the latest position of JOINT from joint_states."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.position: Optional[float] = None
        rospy.Subscriber(NAMESPACE + "/joint_states", JointState, self._on_joint_states, queue_size=1)

    def _on_joint_states(self, msg: JointState) -> None:
        if JOINT in msg.name:
            with self._lock:
                self.position = msg.position[msg.name.index(JOINT)]

    def get(self) -> Optional[float]:
        with self._lock:
            return self.position


def call_trigger(name: str) -> bool:
    service = NAMESPACE + "/driver/" + name
    rospy.loginfo("waiting for %s", service)
    rospy.wait_for_service(service)
    answer = rospy.ServiceProxy(service, Trigger)()
    rospy.loginfo("%s: success=%s %s", service, answer.success, answer.message)
    return answer.success


def main() -> int:
    rospy.init_node("python_example_1dof_ppm")
    parser = argparse.ArgumentParser(description="sine wave of target positions for one EPOS4 (PPM)")
    parser.add_argument("--cycles", type=float, default=rospy.get_param("~cycles", 0.0))
    parser.add_argument("--amplitude", type=float, default=rospy.get_param("~amplitude", 10000.0))
    parser.add_argument("--steps", type=int, default=rospy.get_param("~steps", 20))
    parser.add_argument("--step-time", type=float, default=rospy.get_param("~step_time", 0.5))
    parser.add_argument("--no-init", action="store_true", default=rospy.get_param("~no_init", False))
    args = parser.parse_args(rospy.myargv(sys.argv)[1:])
    if args.steps < 2 or args.step_time <= 0 or not math.isfinite(args.amplitude):
        parser.error("need --steps >= 2, --step-time > 0 and a finite --amplitude")

    reader = PositionReader()
    command = rospy.Publisher(COMMAND_TOPIC, Float64, queue_size=1, latch=True)
    if not args.no_init and not call_trigger("init"):
        return 1

    # Wait until the position controller listens (the spawner starts it after init).
    while command.get_num_connections() == 0 and not rospy.is_shutdown():
        rospy.loginfo_throttle(5.0, "waiting for a subscriber on %s" % COMMAND_TOPIC)
        rospy.sleep(0.1)

    total = int(round(args.cycles * args.steps)) if args.cycles > 0 else None
    step = 0
    rate = rospy.Rate(1.0 / args.step_time)
    print("%6s %14s %14s" % ("step", "target [inc]", "position [inc]"), flush=True)
    while not rospy.is_shutdown() and (total is None or step <= total):
        target = round(args.amplitude * math.sin(2.0 * math.pi * step / args.steps))
        command.publish(Float64(float(target)))
        rate.sleep()
        position = reader.get()
        print("%6d %14.0f %14s" % (step, target, "n/a" if position is None else "%.0f" % position), flush=True)
        step += 1
    command.publish(Float64(0.0))
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except rospy.ROSInterruptException:
        sys.exit(0)
