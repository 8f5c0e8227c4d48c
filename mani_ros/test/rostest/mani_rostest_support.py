"""Helpers of the mani_ros rostest scripts (imported from the scripts beside it)."""
from __future__ import annotations

import time
from typing import Any, Callable, List, Optional

import can
import rospy
from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry

from maxon_epos4_ros_canopen import bus_watch
from maxon_epos4_ros_canopen.bus_watch import poll
from maxon_epos4_ros_canopen_node.goal_client import GoalClient
from mani_ros.msg import LocomotionControlAction, LocomotionControlGoal


# How long the nodes of a launch file may take to come up (slow in user-mode
# Linux): generous, it only bounds how long a failure takes.
STARTUP_TIMEOUT = 120.0
# How long a command stream may take to move the rover as far as a test asks:
# generous, it only bounds how long a failure takes on a loaded host.
DRIVE_TIMEOUT = 60.0
# How far this test's CAN reader may lag behind the bus: generous, it only
# bounds how long a failure takes on a loaded host.
READER_TIMEOUT = 30.0
# How long a node may take to handle an input (a frame, a message) and show
# it on a topic: generous, it only bounds how long a failure takes on a
# loaded host.
HANDLED_TIMEOUT = 30.0
# An id no MANI node sends or reads (docs/mani_protocol.md): the frame a test
# puts on a bus without traffic of its own to catch its reader up.
MARKER_ID = 0x7FF


def wait_until(condition: Callable[[], bool], timeout: float, step: float = 0.05) -> bool:
    """Poll condition until it holds or timeout [s] passes; returns the last value."""
    return poll(condition, timeout, step, stop=rospy.is_shutdown)


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


def lc_client(timeout: float = 60.0) -> GoalClient:
    """A client of locomotion_control. Not actionlib's SimpleActionClient:
    it loses an answer that comes before its send_goal returns (an invalid
    goal's, on a loaded host), and then reports LOST (goal_client.py)."""
    client = GoalClient("locomotion_control", LocomotionControlAction)
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

    def after(self, call: Callable[[], Any], what: str, timeout: float = DRIVE_TIMEOUT) -> Any:
        """Call ``call`` (a service, say) and wait for odometry computed after
        it has returned: the messages in flight were computed before and say
        nothing about its effect. Returns what ``call`` returned."""
        answer = call()
        after = rospy.Time.now()
        if not wait_until(lambda: self.newer_than(after), timeout):
            raise AssertionError("no odometry computed after %s" % what)
        return answer

    def reset(self, service: Callable[[], Any], timeout: float = DRIVE_TIMEOUT) -> Any:
        """Call the odometry reset service and wait for odometry computed after
        it: the messages in flight still carry the old pose. Returns the
        service's answer."""
        return self.after(service, "the reset", timeout)


class TopicLog:
    """Every message of a topic, in order of arrival, since the last clear()."""

    def __init__(self, topic: str, msg_type: type, queue_size: int = 100) -> None:
        self.messages: List[Any] = []
        self.sub = rospy.Subscriber(topic, msg_type, self._on, queue_size=queue_size)

    def _on(self, msg: Any) -> None:
        self.messages.append(msg)

    def clear(self) -> None:
        self.messages = []

    def stamped_after(self, stamp: rospy.Time) -> Optional[Any]:
        """The first message (of a stamped type) whose header says it was
        made after ``stamp``, or None. A node that stamps what it publishes
        with its clock (the test's) says by it when it handled the input."""
        for msg in list(self.messages):
            if msg.header.stamp > stamp:
                return msg
        return None


class FrameRecorder(bus_watch.FrameRecorder):
    """Records the frames seen on the test's CAN bus (``~device``, socketcan)
    from the moment it is made."""

    def __init__(self, channel: Optional[str] = None) -> None:
        """channel: the CAN interface; None: the test's ``~device``."""
        self.channel = channel or rospy.get_param("~device", "vcan0")
        super().__init__(can.Bus(interface="socketcan", channel=self.channel), marker_id=MARKER_ID,
                         marker_bus=lambda: can.Bus(interface="socketcan", channel=self.channel))
        self.start(drain=False)

    def catch_up(self, timeout: float = READER_TIMEOUT) -> bool:
        """Wait until the reader holds a frame sent after this call: socketcan
        hands a reader the bus's frames in order, each with the kernel's
        timestamp (the clock of time.time()), so every frame sent before the
        call is in then. Needs traffic on the bus: the simulated EPS repeats
        its powerFb (simulation.eps_period)."""
        since = time.time()
        return wait_until(lambda: bool(self.frames) and self.frames[-1].timestamp > since, timeout)

    def catch_up_by_marker(self, timeout: float = READER_TIMEOUT) -> bool:
        """catch_up for a bus that carries no traffic of its own (one that
        must stay silent): bus_watch.FrameRecorder.flush, a marker frame
        (MARKER_ID, eight random bytes) from a second socket, which socketcan
        hands this reader like any other socket's frame; every frame sent
        before it is in then. Markers never show in ``frames``."""
        return self.flush(timeout)
