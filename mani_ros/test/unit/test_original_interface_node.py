"""original_interface reports the inner locomotion_control goal's answer even
when it comes before send_goal has returned. rospy's SimpleActionClient drops
such an answer (ros/actionlib#206): a goal refused at once (motor power off)
then left the original Locomotion goal waiting until it was preempted.

The node runs with actionlib's transport replaced by a server that answers
inside send_goal, the way a fast refusal meets a descheduled client thread on
a loaded host."""
from __future__ import annotations

import glob
import importlib.machinery
import importlib.util
import os
import sys
import threading
from typing import Any, List

import pytest

actionlib = pytest.importorskip("actionlib", reason="actionlib (Debian python3-actionlib)")
rospy = pytest.importorskip("rospy", reason="rospy (Debian python3-rospy)")
from actionlib_msgs.msg import GoalStatus  # noqa: E402

import mani_ros  # noqa: E402  (the ROS-free core, see conftest.py)

NODE = os.path.normpath(os.path.join(os.path.dirname(__file__), "..", "..", "nodes", "original_interface"))


def _with_generated_messages() -> None:
    """Add the workspace's generated mani_ros.msg/.srv to the core package."""
    for entry in sys.path:
        for found in glob.glob(os.path.join(entry, "mani_ros", "msg", "__init__.py")):
            generated = os.path.dirname(os.path.dirname(found))
            if generated not in mani_ros.__path__:
                mani_ros.__path__.append(generated)
            return
    pytest.fail("mani_ros.msg is not on sys.path: build the workspace (tools/setup.sh) "
                "and source tools/env.sh, as tools/run_tests.sh does")


def _load_node() -> Any:
    _with_generated_messages()
    loader = importlib.machinery.SourceFileLoader("mani_original_interface_node", NODE)
    spec = importlib.util.spec_from_loader(loader.name, loader)
    module = importlib.util.module_from_spec(spec)
    loader.exec_module(module)
    return module


class _Handle:
    """A goal handle as actionlib keeps it: already answered."""

    def __init__(self, status: int, result: Any) -> None:
        self.status, self.result = status, result

    def get_comm_state(self) -> int:
        return actionlib.CommState.DONE

    def get_goal_status(self) -> int:
        return self.status

    def get_goal_status_text(self) -> str:
        return ""

    def get_result(self) -> Any:
        return self.result

    def cancel(self) -> None:
        pass


class _AnswersAtOnce:
    """actionlib's ActionClient, its server answering inside send_goal."""

    answer: _Handle

    def __init__(self, *_args: Any) -> None:
        pass

    def wait_for_server(self, _timeout: Any = None) -> bool:
        return True

    def send_goal(self, _goal: Any, transition_cb: Any = None, feedback_cb: Any = None) -> _Handle:
        handle = self.answer
        if transition_cb is not None:
            transition_cb(handle)
        return handle


class _Server:
    """The node's own SimpleActionServer: what it was told to answer."""

    def __init__(self, *_args: Any, **_kwargs: Any) -> None:
        self.answers: List[tuple] = []
        self.answered = threading.Event()

    def start(self) -> None:
        pass

    def is_preempt_requested(self) -> bool:
        return False

    def is_new_goal_available(self) -> bool:
        return False

    def is_active(self) -> bool:
        return True

    def publish_feedback(self, _feedback: Any) -> None:
        pass

    def set_succeeded(self, result: Any, text: str = "") -> None:
        self.answers.append(("succeeded", list(result.sequence), text))
        self.answered.set()

    def set_aborted(self, result: Any, text: str = "") -> None:
        self.answers.append(("aborted", list(result.sequence), text))
        self.answered.set()

    def set_preempted(self, result: Any, text: str = "") -> None:
        self.answers.append(("preempted", list(result.sequence), text))
        self.answered.set()


@pytest.fixture
def node(monkeypatch):
    module = _load_node()
    for owner in (actionlib, actionlib.action_client, actionlib.simple_action_client):
        monkeypatch.setattr(owner, "ActionClient", _AnswersAtOnce)
    monkeypatch.setattr(actionlib, "SimpleActionServer", _Server)
    monkeypatch.setattr(rospy, "get_param", lambda _name, default=None: default)
    monkeypatch.setattr(rospy, "Service", lambda *_args, **_kwargs: None)
    monkeypatch.setattr(rospy, "loginfo", lambda *_args, **_kwargs: None)
    # SimpleActionClient's waits read ROS time; wall time here.
    monkeypatch.setattr(rospy.rostime, "_rostime_initialized", True)
    return module


def _run_goal(interface: Any, x: float) -> None:
    from mani_ros.msg import LocomotionGoal, MoveControl   # generated: after _load_node
    goal = LocomotionGoal(command=MoveControl(x=x))
    worker = threading.Thread(target=interface.execute, args=(goal,), daemon=True)
    worker.start()
    # generous: the goal is answered at once, this only bounds a broken node
    assert interface.server.answered.wait(20.0), "the Locomotion goal was never answered"


def test_a_refusal_that_came_before_send_goal_returned_aborts_the_goal(node):
    refusal = node.LocomotionControlResult(outcome=node.LocomotionControlResult.MOTOR_POWER_OFF,
                                           task_completed=[False] * 4,
                                           status="motor power is off (powerFb 0): goal refused")
    _AnswersAtOnce.answer = _Handle(GoalStatus.ABORTED, refusal)
    interface = node.OriginalInterface()
    _run_goal(interface, 0.1)
    assert interface.server.answers == [
        ("aborted", [0, 0, 0, 0], "motor power is off (powerFb 0): goal refused")]


def test_a_success_that_came_before_send_goal_returned_succeeds(node):
    done = node.LocomotionControlResult(outcome=node.LocomotionControlResult.SUCCEEDED,
                                        task_completed=[True] * 4, status="all wheels done")
    _AnswersAtOnce.answer = _Handle(GoalStatus.SUCCEEDED, done)
    interface = node.OriginalInterface()
    _run_goal(interface, 0.1)
    assert interface.server.answers == [("succeeded", [1, 1, 1, 1], "all wheels done")]
