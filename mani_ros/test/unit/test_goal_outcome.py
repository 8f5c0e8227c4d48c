"""How a finished LC goal is reported to actionlib (finish_goal, duck-typed
so the module stays ROS-free) and the private-parameter reader of the nodes."""
import pytest

from mani_ros.config import load_config
from mani_ros.locomotion import (PREEMPTED, SUCCEEDED, TIMEOUT, CompletionTracker, GoalRunner,
                                 Planner, finish_goal, outcome_text)
from mani_ros.node_support import ParamReader

CONFIG = load_config()


class Result:
    """Stands in for mani_ros/LocomotionControlResult (same constants)."""
    SUCCEEDED, TIMEOUT, PREEMPTED, INVALID_GOAL, BUS_ERROR, MOTOR_POWER_OFF = range(6)

    def __init__(self, outcome=None, status="", task_completed=(), set_orientation=(),
                 set_velocity=()):
        self.outcome, self.status = outcome, status
        self.task_completed = list(task_completed)
        self.set_orientation, self.set_velocity = list(set_orientation), list(set_velocity)


class Feedback:
    def __init__(self, task_completed, status):
        self.task_completed, self.status = task_completed, status


class Goal:
    """Stands in for mani_ros/LocomotionControlGoal."""

    class _Twist:
        class _V:
            x = y = z = 0.0

        def __init__(self):
            self.linear, self.angular = self._V(), self._V()

    def __init__(self, mode=1, vx=0.0, wz=0.0, angles=(), speeds=(), timeout=0.0):
        self.mode, self.timeout = mode, timeout
        self.twist = self._Twist()
        self.twist.linear.x, self.twist.angular.z = vx, wz
        self.steering_angle, self.wheel_velocity = list(angles), list(speeds)


class Server:
    """Records what a SimpleActionServer would be told."""

    def __init__(self, preempt=False, new_goal=False):
        self.calls = []
        self.feedback = []
        self.preempt, self.new_goal = preempt, new_goal

    def is_preempt_requested(self):
        return self.preempt

    def is_new_goal_available(self):
        return self.new_goal

    def is_active(self):
        return not self.calls

    def publish_feedback(self, feedback):
        self.feedback.append(list(feedback.task_completed))

    def set_succeeded(self, result, text):
        self.calls.append(("succeeded", result.outcome, text))
        self.result = result

    def set_aborted(self, result, text):
        self.calls.append(("aborted", result.outcome, text))
        self.result = result

    def set_preempted(self, result, text):
        self.calls.append(("preempted", result.outcome, text))
        self.result = result


@pytest.mark.parametrize("outcome, call, code", [
    (SUCCEEDED, "succeeded", 0), (TIMEOUT, "aborted", 1), (PREEMPTED, "preempted", 2)])
def test_each_outcome_ends_the_goal_with_the_action_constants(outcome, call, code):
    server, result = Server(), Result()
    finish_goal(server, outcome, result, "text")
    assert server.calls == [(call, code, "text")]
    assert result.status == "text"


def test_status_names_silent_wheels_and_limits():
    tracker = CompletionTracker()
    tracker.start()
    for node in (1, 2, 3, 4):
        tracker.arm(node)
    tracker.report(1, True)
    tracker.report(4, True)
    command, _ = Planner(CONFIG).plan(1, 100.0, 0.0, 0.0)   # far beyond MAX_VEL
    text = outcome_text(TIMEOUT, tracker, 2.0, command)
    assert text.startswith("timeout: no task_completed within 2.0 s from "
                           "rear_left (node 2), rear_right (node 3)")
    assert "MAX_VEL" in text


def test_param_reader_reads_private_names_and_reports_bad_values():
    params = {"~rate": "fast", "~timeout": 4}
    errors = []
    p = ParamReader(lambda name, default: params.get(name, default), errors.append)
    assert p("timeout", 1.0) == 4.0
    assert p("rate", 10.0, minimum=1.0) == 10.0
    assert errors == ["parameter ~rate: 'fast' is not a number; using 10.0"]
    assert p("mode", "crab", str, choices=("crab", "ackermann")) == "crab"


class Drives:
    """start()/stop() of a node: record what would be sent, answer at once."""

    def __init__(self, tracker, answer=(1, 2, 3, 4), refuse=None):
        self.tracker, self.answer, self.refuse = tracker, answer, refuse
        self.started, self.stopped = [], 0

    def start(self, command, set_points):
        if self.refuse:
            return self.refuse
        self.started.append(set_points)
        for node in (1, 2, 3, 4):
            self.tracker.arm(node)
        for node in self.answer:
            self.tracker.report(node, True)
        return None

    def stop(self):
        self.stopped += 1
        return "stopped"


def runner(server, tracker, timeout=5.0):
    warnings = []
    clock = iter(range(10 ** 6)).__next__   # one "second" per look at the clock
    return GoalRunner(server, Result, Feedback, Planner(CONFIG), tracker, timeout,
                      lambda: float(clock()), warnings.append, warnings.append), warnings


def test_runner_succeeds_when_the_four_drives_report_and_returns_the_set_points():
    server, tracker = Server(), CompletionTracker()
    lc, _ = runner(server, tracker)
    drives = Drives(tracker)
    lc.execute(Goal(mode=0, angles=[0.0] * 4, speeds=[0.1] * 4), drives.start, drives.stop)
    assert server.calls == [("succeeded", Result.SUCCEEDED, "all four wheels report task_completed")]
    assert server.result.task_completed == [True] * 4
    assert server.result.set_velocity == [drives.started[0][n][1] for n in (1, 2, 3, 4)]
    assert server.feedback[-1] == [True] * 4


def test_runner_times_out_naming_the_silent_node_and_tells_the_node():
    server, tracker = Server(), CompletionTracker()
    lc, warnings = runner(server, tracker, timeout=3.0)
    drives, missing = Drives(tracker, answer=(1, 2, 4)), []
    lc.execute(Goal(vx=0.1), drives.start, drives.stop, on_timeout=missing.extend)
    assert server.calls[0][:2] == ("aborted", Result.TIMEOUT)
    assert "rear_right (node 3)" in server.calls[0][2]
    assert missing == [3] and warnings


def test_runner_refuses_invalid_goals_before_anything_is_sent():
    server, tracker = Server(), CompletionTracker()
    lc, _ = runner(server, tracker)
    drives = Drives(tracker)
    lc.execute(Goal(mode=0, angles=[0.0] * 3, speeds=[0.0] * 4), drives.start, drives.stop)
    assert server.calls[0][:2] == ("aborted", Result.INVALID_GOAL)
    assert server.calls[0][2].startswith("invalid goal: ")
    assert drives.started == []


def test_runner_passes_on_a_refusal_of_the_node():
    server, tracker = Server(), CompletionTracker()
    lc, _ = runner(server, tracker)
    drives = Drives(tracker, refuse=("MOTOR_POWER_OFF", "motor power is off"))
    lc.execute(Goal(vx=0.1), drives.start, drives.stop)
    assert server.calls == [("aborted", Result.MOTOR_POWER_OFF, "motor power is off")]


@pytest.mark.parametrize("new_goal, stops", [(False, 1), (True, 0)])
def test_runner_stops_the_wheels_on_a_cancel_but_not_for_a_new_goal(new_goal, stops):
    server, tracker = Server(preempt=True, new_goal=new_goal), CompletionTracker()
    lc, _ = runner(server, tracker)
    drives = Drives(tracker, answer=())
    lc.execute(Goal(vx=0.1), drives.start, drives.stop)
    assert server.calls[0][:2] == ("preempted", Result.PREEMPTED)
    assert drives.stopped == stops


def test_runner_turns_an_unexpected_error_into_an_aborted_goal():
    server, tracker = Server(), CompletionTracker()
    lc, _ = runner(server, tracker)

    def broken(command, set_points):
        raise RuntimeError("boom")

    lc.execute(Goal(vx=0.1), broken, lambda: "")
    assert server.calls == [("aborted", Result.BUS_ERROR, "internal error: boom")]
