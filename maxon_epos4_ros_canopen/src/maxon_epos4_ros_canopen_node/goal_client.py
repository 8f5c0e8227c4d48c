"""One goal at a time on an action server, as actionlib's SimpleActionClient
offers, without the race that loses an answer that comes at once.

rospy's SimpleActionClient keeps the handle of the goal it sent only once
``ActionClient.send_goal`` has returned, and drops every status and result
that arrives for another handle ("Got a transition callback on a goal
handle that we're not tracking", ros/actionlib#206, not fixed before ROS 1's
end of life). A goal the server rejects or finishes at once can be answered
in between, most often on a loaded host: the answer is dropped, and the
client waits for it until its timeout. This client asks the goal handle
itself, which actionlib keeps up to date whatever its callbacks do.
"""
from __future__ import annotations

import threading
import time
from typing import Any, Callable, Optional

import actionlib
import rospy
from actionlib_msgs.msg import GoalStatus

_POLL_S = 0.1  # a wait also looks at the handle this often: a notify may come before the wait


class GoalClient:
    """send_goal, send_goal_and_wait, wait_for_result, get_state,
    get_result, cancel_goal as SimpleActionClient has them, for the latest
    goal sent."""

    def __init__(self, action: str, action_type: Any) -> None:
        self._client = actionlib.ActionClient(action, action_type)
        self._changed = threading.Condition()
        self._handle: Optional[actionlib.ClientGoalHandle] = None

    def wait_for_server(self, timeout: rospy.Duration = rospy.Duration()) -> bool:
        return self._client.wait_for_server(timeout)

    def send_goal(self, goal: Any, feedback_cb: Optional[Callable[[Any], None]] = None) -> None:
        """Send ``goal``; it replaces the one tracked before (which the server
        preempts or not, as it decides)."""
        def on_transition(_handle: Any) -> None:
            with self._changed:
                self._changed.notify_all()

        def on_feedback(handle: Any, feedback: Any) -> None:
            # feedback of an earlier goal, or one that came before send_goal
            # returned, is not this goal's
            if feedback_cb is not None and handle == self._handle:
                feedback_cb(feedback)
        self._handle = self._client.send_goal(goal, on_transition, on_feedback)

    def wait_for_result(self, timeout: rospy.Duration = rospy.Duration()) -> bool:
        """Whether the goal is done within ``timeout`` (zero: no limit)."""
        handle = self._handle
        if handle is None:
            return False
        deadline = None if timeout.is_zero() else time.monotonic() + timeout.to_sec()
        with self._changed:
            while handle.get_comm_state() != actionlib.CommState.DONE:
                remaining = _POLL_S if deadline is None else min(_POLL_S, deadline - time.monotonic())
                if remaining <= 0.0 or rospy.is_shutdown():
                    return False
                self._changed.wait(remaining)
        return True

    def send_goal_and_wait(self, goal: Any, execute_timeout: rospy.Duration = rospy.Duration(),
                           preempt_timeout: rospy.Duration = rospy.Duration()) -> int:
        """Send ``goal`` and wait for its end, as SimpleActionClient does:
        a goal not done within ``execute_timeout`` (zero: no limit) is
        canceled, and its end awaited ``preempt_timeout`` more. The goal's
        state."""
        self.send_goal(goal)
        if not self.wait_for_result(execute_timeout):
            self.cancel_goal()
            self.wait_for_result(preempt_timeout)
        return self.get_state()

    @property
    def handle(self) -> Optional[actionlib.ClientGoalHandle]:
        """actionlib's handle of the latest goal sent (None: none yet)."""
        return self._handle

    def get_state(self) -> int:
        """The goal's actionlib_msgs/GoalStatus status; LOST when none was sent."""
        return GoalStatus.LOST if self._handle is None else self._handle.get_goal_status()

    def get_goal_status_text(self) -> str:
        return "" if self._handle is None else self._handle.get_goal_status_text()

    def get_result(self) -> Any:
        return None if self._handle is None else self._handle.get_result()

    def cancel_goal(self) -> None:
        if self._handle is not None:
            self._handle.cancel()
