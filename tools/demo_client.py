#!/usr/bin/env python3
"""Client half of the demo (tools/demo_session.sh): the commands a user
types, then the joint states printed while the joint moves."""
import subprocess
import sys
import time

import rospy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64

NS = "/maxon"
JOINT = "base_link1_joint"
COMMAND_TOPIC = NS + "/canopen_motor/" + JOINT + "_position_controller/command"
TARGETS = [10000.0, -5000.0, 0.0]  # inc, as in the seeds (no unit conversion)
PROFILE_VELOCITY = 200  # rpm, slow enough to watch the joint move
TOLERANCE = 20.0  # inc


def shell(cmd: str) -> str:
    print("$ " + cmd, flush=True)
    out = subprocess.run(cmd, shell=True, capture_output=True, text=True, timeout=120)
    text = (out.stdout + out.stderr).strip()
    print("  " + text.replace("\n", "\n  "), flush=True)
    if out.returncode != 0:
        raise RuntimeError("command failed: " + cmd)
    return text


def main() -> int:
    start = time.monotonic()
    deadline = start + 180.0
    print("[demo] roslaunch is starting the driver node and the virtual EPOS4 beside the ROS master; waiting for "
          "the driver's services (about 20 s under user-mode Linux)", flush=True)
    said = ""
    while True:
        listing = subprocess.run(["rosservice", "list"], capture_output=True, text=True)
        if NS + "/driver/init" in listing.stdout:
            break
        stage = ("the driver node is starting (importing rospy, canopen, reading its DCF)"
                 if listing.returncode == 0 else "the ROS master is starting")
        if stage != said:
            print("[demo] %4.0f s: %s" % (time.monotonic() - start, stage), flush=True)
            said = stage
        if time.monotonic() > deadline:
            print("the driver's services did not appear", flush=True)
            return 1
        time.sleep(1.0)
    print("[demo] %4.0f s: the driver offers its services" % (time.monotonic() - start), flush=True)

    if "success: True" not in shell("rosservice call " + NS + "/driver/init"):
        return 1
    # The seeds' SDO services: set the profile velocity, read it back.
    shell("rosservice call %s/driver/set_object %s '!!str 6081' '!!str %d' false" % (NS, JOINT, PROFILE_VELOCITY))
    if "value: \"%d\"" % PROFILE_VELOCITY not in shell(
            "rosservice call %s/driver/get_object %s '!!str 6081' false" % (NS, JOINT)):
        return 1
    rospy.init_node("maxon_epos4_demo", anonymous=True, disable_signals=True)
    latest = {}

    def on_state(msg: JointState) -> None:
        if JOINT in msg.name:
            i = msg.name.index(JOINT)
            latest["position"] = msg.position[i]
            latest["velocity"] = msg.velocity[i] if msg.velocity else 0.0

    rospy.Subscriber(NS + "/joint_states", JointState, on_state, queue_size=10)
    pub = rospy.Publisher(COMMAND_TOPIC, Float64, queue_size=1, latch=True)
    time.sleep(1.0)
    for target in TARGETS:
        print("$ rostopic pub %s std_msgs/Float64 -- %g" % (COMMAND_TOPIC, target), flush=True)
        pub.publish(Float64(target))
        t0 = time.monotonic()
        reached = False
        while time.monotonic() - t0 < 60.0:
            time.sleep(0.2)
            if "position" in latest:
                print("  t=%5.2fs  %s position=%9.1f inc  velocity=%8.1f rpm" % (
                    time.monotonic() - t0, JOINT, latest["position"], latest["velocity"]), flush=True)
                if abs(latest["position"] - target) <= TOLERANCE and abs(latest["velocity"]) < 1.0:
                    reached = True
                    break
        if not reached:
            print("  target %g not reached" % target, flush=True)
            return 1
        print("  reached %g" % target, flush=True)
    shell("rosservice call " + NS + "/driver/shutdown")
    print("demo finished: the simulated EPOS4 followed %d targets" % len(TARGETS), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
