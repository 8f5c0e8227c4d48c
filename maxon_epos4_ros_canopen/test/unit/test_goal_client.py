"""GoalClient keeps the server's answer to a goal even when it comes before
send_goal has returned, which actionlib's SimpleActionClient drops
(ros/actionlib#206): on a loaded host a goal rejected at once then never
reported a result (csp_trajectory's test_03 under two CPU hogs)."""
from __future__ import annotations

import threading

import pytest

actionlib = pytest.importorskip("actionlib", reason="actionlib (Debian python3-actionlib) is the client's base")
rospy = pytest.importorskip("rospy", reason="rospy (Debian python3-rospy)")
from actionlib_msgs.msg import GoalStatus  # noqa: E402

from maxon_epos4_ros_canopen_node import goal_client  # noqa: E402


class _Handle:
    """A goal handle as actionlib keeps it, its state set by the test."""

    def __init__(self, done: bool, status: int, result: object = None) -> None:
        self.done, self.status, self.result = done, status, result
        self.canceled = False

    def get_comm_state(self) -> int:
        return actionlib.CommState.DONE if self.done else actionlib.CommState.ACTIVE

    def get_goal_status(self) -> int:
        return self.status

    def get_goal_status_text(self) -> str:
        return "text of %d" % self.status

    def get_result(self) -> object:
        return self.result

    def cancel(self) -> None:
        self.canceled = True


class _ServerAnswering:
    """An ActionClient whose server answers each goal with ``handles`` in
    turn; ``at_once``: its transition callback runs before send_goal returns."""

    handles: list = []
    at_once = True

    def __init__(self, *_args: object) -> None:
        self.callbacks: list = []

    def wait_for_server(self, _timeout: object) -> bool:
        return True

    def send_goal(self, goal: object, transition_cb=None, feedback_cb=None):
        handle = self.handles.pop(0)
        self.callbacks.append((handle, transition_cb, feedback_cb))
        if self.at_once:
            transition_cb(handle)
            feedback_cb(handle, "feedback before the handle was known")
        return handle


@pytest.fixture
def server(monkeypatch):
    monkeypatch.setattr(goal_client.actionlib, "ActionClient", _ServerAnswering)
    _ServerAnswering.at_once = True
    return _ServerAnswering


def test_an_answer_that_came_before_send_goal_returned_is_kept(server):
    server.handles = [_Handle(True, GoalStatus.REJECTED, "invalid joints")]
    client = goal_client.GoalClient("/ctrl/follow_joint_trajectory", object)
    client.send_goal("goal")
    assert client.wait_for_result(rospy.Duration(5.0))
    assert client.get_state() == GoalStatus.REJECTED
    assert client.get_result() == "invalid joints"
    assert client.get_goal_status_text() == "text of %d" % GoalStatus.REJECTED


def test_a_later_answer_wakes_the_waiter_and_a_missing_one_times_out(server):
    server.at_once = False
    first, second = _Handle(False, GoalStatus.ACTIVE), _Handle(False, GoalStatus.ACTIVE)
    server.handles = [first, second]
    client = goal_client.GoalClient("/ctrl/follow_joint_trajectory", object)
    assert client.get_state() == GoalStatus.LOST and not client.wait_for_result(rospy.Duration(0.1))
    client.send_goal("goal")
    assert not client.wait_for_result(rospy.Duration(0.3))

    def finish() -> None:
        first.done, first.status = True, GoalStatus.SUCCEEDED
        handle, transition_cb, _ = client._client.callbacks[0]
        transition_cb(handle)
    threading.Timer(0.2, finish).start()
    assert client.wait_for_result(rospy.Duration(10.0))
    assert client.get_state() == GoalStatus.SUCCEEDED
    # a second goal is tracked from then on; canceling reaches its handle
    client.send_goal("second goal")
    assert client.get_state() == GoalStatus.ACTIVE
    client.cancel_goal()
    assert second.canceled and not first.canceled


def test_feedback_of_another_goal_is_not_passed_on(server):
    server.at_once = False
    first, second = _Handle(False, GoalStatus.ACTIVE), _Handle(False, GoalStatus.ACTIVE)
    server.handles = [first, second]
    client = goal_client.GoalClient("/ctrl/follow_joint_trajectory", object)
    seen = []
    client.send_goal("goal", feedback_cb=seen.append)
    client.send_goal("second goal", feedback_cb=seen.append)
    for handle, _, feedback_cb in client._client.callbacks:
        feedback_cb(handle, "feedback of %s" % ("first" if handle is first else "second"))
    assert seen == ["feedback of second"]


def test_send_goal_and_wait_keeps_an_answer_at_once_and_cancels_on_timeout(server):
    rejected, running = _Handle(True, GoalStatus.REJECTED, "bad goal"), _Handle(False, GoalStatus.ACTIVE)
    server.handles = [rejected, running]
    client = goal_client.GoalClient("/locomotion_control", object)
    assert client.send_goal_and_wait("goal", rospy.Duration(5.0)) == GoalStatus.REJECTED
    assert client.handle is rejected and client.get_result() == "bad goal"
    server.at_once = False
    assert client.send_goal_and_wait("goal", rospy.Duration(0.1), rospy.Duration(0.1)) == GoalStatus.ACTIVE
    assert client.handle is running and running.canceled and not rejected.canceled
