"""Helpers of the mani_ros rostest scripts (imported from the scripts beside it)."""
from __future__ import annotations

import time
from typing import Any, Callable, List, Optional

import actionlib
import can
import rospy
from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry

from mani_ros.msg import LocomotionControlAction, LocomotionControlGoal


# How long a command stream may take to move the rover as far as a test asks:
# generous, it only bounds how long a failure takes on a loaded host.
DRIVE_TIMEOUT = 60.0
# How far this test's CAN reader may lag behind the bus: generous, it only
# bounds how long a failure takes on a loaded host.
READER_TIMEOUT = 30.0


def wait_until(condition: Callable[[], bool], timeout: float, step: float = 0.05) -> bool:
    """Poll condition until it holds or timeout [s] passes; returns the last value."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not rospy.is_shutdown():
        if condition():
            return True
        time.sleep(step)
    return bool(condition())


def drive_until(publish: Callable[[], None], condition: Callable[[], bool], timeout: float,
                rate: float = 20.0) -> bool:
    """Call publish (a command stream, as a joystick or a planner sends it)
    at ``rate`` Hz until condition holds or timeout [s] passes; returns the
    last value of condition. On a loaded host the stack answers late: a
    command stream of a fixed length moves the rover a varying distance."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not rospy.is_shutdown():
        if condition():
            return True
        publish()
        time.sleep(1.0 / rate)
    return bool(condition())


def lc_client(timeout: float = 60.0) -> actionlib.SimpleActionClient:
    client = actionlib.SimpleActionClient("locomotion_control", LocomotionControlAction)
    if not client.wait_for_server(rospy.Duration(timeout)):
        raise AssertionError("locomotion_control action server did not come up")
    return client


def twist_goal(mode: int, vx: float = 0.0, vy: float = 0.0, wz: float = 0.0,
               timeout: float = 0.0) -> LocomotionControlGoal:
    twist = Twist()
    twist.linear.x, twist.linear.y, twist.angular.z = vx, vy, wz
    return LocomotionControlGoal(mode=mode, twist=twist, timeout=timeout)


class OdomWatcher:
    """Keeps the latest nav_msgs/Odometry of a topic."""

    def __init__(self, topic: str = "odom") -> None:
        self.latest: Optional[Odometry] = None
        self.count = 0
        self.reset_peak()
        self.sub = rospy.Subscriber(topic, Odometry, self._on, queue_size=10)

    def reset_peak(self) -> None:
        """Start collecting the extremes of twist.linear.x again."""
        self.peak_vx = float("-inf")
        self.low_vx = float("inf")

    def _on(self, msg: Odometry) -> None:
        self.latest = msg
        self.count += 1
        self.peak_vx = max(self.peak_vx, msg.twist.twist.linear.x)
        self.low_vx = min(self.low_vx, msg.twist.twist.linear.x)

    def newer_than(self, stamp: rospy.Time) -> bool:
        """True once a message stamped after ``stamp`` has come. The odometry
        node stamps a message with its clock (the test's) when it computes it."""
        return self.latest is not None and self.latest.header.stamp > stamp

    def at_rest(self, tolerance: float) -> bool:
        """The latest message says the rover stands still (m/s, rad/s)."""
        if self.latest is None:
            return False
        twist = self.latest.twist.twist
        return max(abs(twist.linear.x), abs(twist.linear.y), abs(twist.angular.z)) < tolerance

    def reset(self, service: Callable[[], Any], timeout: float = DRIVE_TIMEOUT) -> Any:
        """Call the odometry reset service and wait for odometry computed after
        it: the messages in flight still carry the old pose. Returns the
        service's answer."""
        answer = service()
        after = rospy.Time.now()
        if not wait_until(lambda: self.newer_than(after), timeout):
            raise AssertionError("no odometry computed after the reset")
        return answer


class TopicLog:
    """Every message of a topic, in order of arrival, since the last clear()."""

    def __init__(self, topic: str, msg_type: type, queue_size: int = 100) -> None:
        self.messages: List[Any] = []
        self.sub = rospy.Subscriber(topic, msg_type, self._on, queue_size=queue_size)

    def _on(self, msg: Any) -> None:
        self.messages.append(msg)

    def clear(self) -> None:
        self.messages = []


class FrameRecorder(can.Listener):
    """Records the frames seen on the test's CAN bus (``~device``, socketcan)."""

    def __init__(self) -> None:
        self.frames: List[can.Message] = []
        self.bus = can.Bus(interface="socketcan", channel=rospy.get_param("~device", "vcan0"))
        self.notifier = can.Notifier(self.bus, [self])

    def close(self) -> None:
        self.notifier.stop()
        self.bus.shutdown()

    def on_message_received(self, msg: can.Message) -> None:
        self.frames.append(msg)

    def clear(self) -> None:
        self.frames = []

    def with_id(self, can_id: int) -> List[can.Message]:
        return [f for f in list(self.frames) if f.arbitration_id == can_id]

    def catch_up(self, timeout: float = READER_TIMEOUT) -> bool:
        """Wait until the reader holds a frame sent after this call: socketcan
        hands a reader the bus's frames in order, each with the kernel's
        timestamp (the clock of time.time()), so every frame sent before the
        call is in then. Needs traffic on the bus: the simulated EPS repeats
        its powerFb (simulation.eps_period)."""
        since = time.time()
        return wait_until(lambda: bool(self.frames) and self.frames[-1].timestamp > since, timeout)
