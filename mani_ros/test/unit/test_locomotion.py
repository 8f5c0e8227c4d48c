"""The ROS-free part of the locomotion_control action servers: goal planning,
the task_completed bookkeeping, the wait with timeout and preemption, and the
simulated joints of locomotion_control_simulation."""
import math
import threading

import pytest

from mani_ros import protocol as p
from mani_ros.config import WHEELS, load_config
from mani_ros.kinematics import KinematicsError
from mani_ros.locomotion import (GOAL_WHEELS, PREEMPTED, SUCCEEDED, TIMEOUT, CompletionTracker,
                                 Planner, SimulatedJoints, optional_float, outcome_text,
                                 wait_for_completion)

CONFIG = load_config()
ACKERMANN, POINT_TURN, CRAB = 1, 2, 3   # action/LocomotionControl.action


def test_planner_turns_goals_into_set_points_per_node():
    planner = Planner(CONFIG)
    command, set_points = planner.plan(ACKERMANN, 0.5, 0.0, 0.0)
    assert sorted(set_points) == [1, 2, 3, 4]
    straight = planner.kinematics.config.STEER_ENC_PPR // 4   # the steering encoder reads 0 at -90 deg
    assert set(set_points.values()) == {(straight, planner.kinematics.speed_to_pps(0.5))}
    _, turning = planner.plan(POINT_TURN, 0.0, 0.0, 0.5)
    # front and rear steer opposite, around straight ahead
    assert turning[p.FRONT_LEFT][0] - straight == -(turning[p.REAR_LEFT][0] - straight) != 0
    _, crab = planner.plan(CRAB, 0.2, 0.2, 0.0)
    assert {o for o, _ in crab.values()} == {straight + CONFIG.STEER_ENC_PPR // 8}   # 45 deg left
    _, wheels = planner.plan(GOAL_WHEELS, 0, 0, 0, [0.1, 0.0, 0.0, -0.1], [0.2, 0.2, 0.2, 0.2])
    assert wheels[p.FRONT_LEFT][0] == straight + round(0.1 * CONFIG.STEER_ENC_PPR / (2 * math.pi))


def test_planner_refuses_bad_goals_with_a_reason():
    planner = Planner(CONFIG)
    with pytest.raises(KinematicsError, match="unknown goal mode 9"):
        planner.plan(9, 0, 0, 0)
    with pytest.raises(KinematicsError, match="need 4 steering angles"):
        planner.plan(GOAL_WHEELS, 0, 0, 0, [0.0], [0.0])


def test_planner_keeps_the_angles_of_stopping_wheels():
    planner = Planner(CONFIG)
    command, _ = planner.plan(ACKERMANN, 0.5, 0.0, 0.5)
    planner.commanded(command)
    stop, _ = planner.plan(ACKERMANN, 0.0, 0.0, 0.0)
    assert {w: c.angle for w, c in stop.wheels.items()} == {w: c.angle for w, c in command.wheels.items()}


def test_tracker_counts_only_armed_nodes_of_the_present_goal():
    tracker = CompletionTracker()
    tracker.report(p.FRONT_LEFT, True)           # late feedback of an older goal
    assert tracker.flags() == [False] * 4
    for node in p.DRIVE_NODES:
        tracker.arm(node)
    tracker.report(p.FRONT_LEFT, True)
    tracker.report(p.REAR_RIGHT, True)
    assert tracker.flags() == [True, False, True, False]
    assert tracker.missing() == [p.REAR_LEFT, p.FRONT_RIGHT]
    assert "rear_left (node 2), front_right (node 4)" in tracker.timeout_text(5.0)
    tracker.start()                              # a new goal
    assert tracker.flags() == [False] * 4 and not tracker.all_done()


class FakeClock:
    def __init__(self):
        self.now = 0.0

    def __call__(self):
        self.now += 0.5
        return self.now


def test_wait_succeeds_when_all_four_report():
    tracker = CompletionTracker()
    for node in p.DRIVE_NODES:
        tracker.arm(node)
    seen = []

    def report_all():
        for node in p.DRIVE_NODES:
            tracker.report(node, True)

    threading.Timer(0.05, report_all).start()
    outcome = wait_for_completion(tracker, 30.0, lambda: False, seen.append)
    assert outcome == SUCCEEDED and seen[0] == [False] * 4 and seen[-1] == [True] * 4


def test_wait_times_out_naming_the_silent_wheel():
    tracker = CompletionTracker()
    for node in p.DRIVE_NODES:
        tracker.arm(node)
        if node != p.REAR_RIGHT:
            tracker.report(node, True)
    outcome = wait_for_completion(tracker, 3.0, lambda: False, lambda flags: None, clock=FakeClock())
    assert outcome == TIMEOUT
    command = Planner(CONFIG).plan(ACKERMANN, 0.1, 0, 0)[0]
    assert outcome_text(outcome, tracker, 3.0, command) == \
        "timeout: no task_completed within 3.0 s from rear_right (node 3)"


def test_wait_stops_on_preemption():
    tracker = CompletionTracker()
    assert wait_for_completion(tracker, 30.0, lambda: True, lambda flags: None) == PREEMPTED


def test_goal_timeout_defaults():
    assert optional_float(0.0, 10.0) == 10.0 and optional_float(float("nan"), 10.0) == 10.0
    assert optional_float(None, 10.0) == 10.0 and optional_float(2.5, 10.0) == 2.5


def test_simulated_joints_reach_the_command_then_report():
    tracker = CompletionTracker()
    joints = SimulatedJoints(CONFIG, tracker)
    command, _ = Planner(CONFIG).plan(ACKERMANN, 0.4, 0.0, 0.4)
    joints.command(command)
    joints.step(0.01)
    assert tracker.flags() == [False] * 4          # steering takes time
    for _ in range(300):
        joints.step(0.01)
    assert tracker.all_done()
    positions, velocities, _ = joints.joint_values()
    assert positions[:4] == pytest.approx([command.wheels[w].angle for w in WHEELS])
    assert velocities[4:] == pytest.approx([command.wheels[w].speed / CONFIG.rover.wheel_radius
                                            for w in WHEELS])
    assert all(rotation > 0 for rotation in positions[4:])
