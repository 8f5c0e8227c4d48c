"""JointTrajectoryController inside the controller manager, against a fake driver.

The fake records every position command: those are the 0x607A targets the
real driver would put on the bus at each SYNC.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Dict, List

import pytest

from csp_rig import HeldPoints
from maxon_epos4_ros_canopen import trajectory as tj
from maxon_epos4_ros_canopen.cia402 import State
from maxon_epos4_ros_canopen.controllers import ControllerManager
from maxon_epos4_ros_canopen.trajectory import TrajectoryError, TrajectoryPoint as P
from maxon_epos4_ros_canopen.trajectory_controller import (TYPE_NAME, JointTrajectoryController,
                                                           interpolation_period_problem)

J = ["base_link1_joint", "link1_link2_joint"]
DT = 0.01


@dataclass
class Result:
    success: bool
    message: str = ""
    value: str = ""


class FakeDriver:
    """Joints follow their position command exactly, one cycle later."""

    def __init__(self, period=(10, -3)):
        self.joints = {j: SimpleNamespace(position=0.0, velocity=0.0, state=State.OPERATION_ENABLED,
                                          mode=None, mode_display=0, error=None, halted=False,
                                          target_position=0.0) for j in J}
        self.commands: Dict[str, List[float]] = {j: [] for j in J}
        self.modes: List[tuple] = []
        self.tried: List[str] = []
        self.config = SimpleNamespace(sync=SimpleNamespace(interval_ms=10.0))
        self.period = period

    def switch_mode(self, joint_names, mode):
        self.modes.append((tuple(joint_names), mode))
        for j in joint_names:
            self.joints[j].mode = self.joints[j].mode_display = mode
        return Result(True)

    def set_command(self, joint, kind, value):
        assert kind == "position"
        self.tried.append(joint)
        if self.joints[joint].state is not State.OPERATION_ENABLED:
            return Result(False, "not operation enabled")
        self.commands[joint].append(value)
        self.joints[joint].target_position = value
        return Result(True)

    def get_object(self, joint, obj, cached):
        return Result(True, value=str({"60C2sub1": self.period[0], "60C2sub2": self.period[1]}[obj]))

    def follow(self):
        for j in J:
            if self.commands[j]:
                self.joints[j].position = self.commands[j][-1]


PARAMS = {
    "joint_trajectory_controller": {
        "type": TYPE_NAME, "joints": J, "required_drive_mode": 8,
        "constraints": {"goal_time": 0.5, "stopped_velocity_tolerance": 0.05,
                        J[0]: {"trajectory": 0.2, "goal": 0.01}, J[1]: {"trajectory": 0.2, "goal": 0.01}},
    },
}


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def started(period=(10, -3)):
    driver = FakeDriver(period)
    manager = ControllerManager(driver, J, PARAMS.get)
    assert manager.load("joint_trajectory_controller").success
    ctrl = manager.get("joint_trajectory_controller")
    clock = Clock()
    ctrl.clock = clock
    outcome = manager.switch(["joint_trajectory_controller"], [])
    assert outcome.success, outcome.message
    results = []
    ctrl.on_outcome.append(results.append)
    return driver, ctrl, clock, results


def run(driver, ctrl, clock, seconds):
    for _ in range(int(round(seconds / DT))):
        clock.t += DT
        ctrl.cycle(driver)
        driver.follow()


def test_a_starved_cycle_does_not_fail_a_goal_on_readings_from_before_the_starvation():
    driver, ctrl, clock, results = started()
    ctrl.submit("g", J, [P((0.5, -0.5), (), (), 1.0)], 0.0)
    run(driver, ctrl, clock, 0.9)
    stale = {j: driver.joints[j].position for j in J}
    assert abs(stale[J[0]] - 0.5) > 0.01
    # 2.5 s without a cycle; the drives reached the goal meanwhile, but the
    # first cycle after takes in readings 2.5 s old
    taken_at = clock.t
    clock.t += 2.5
    for j in J:
        driver.joints[j].motion_age = lambda: clock.t - taken_at
    ctrl.cycle(driver)
    assert results == []
    for j, end in zip(J, (0.5, -0.5)):
        driver.joints[j].position = end
        driver.joints[j].motion_age = lambda: 0.002
    clock.t += DT
    ctrl.cycle(driver)
    assert [r.code for r in results] == [tj.SUCCESSFUL], results


def test_start_switches_to_csp_and_checks_interpolation_period():
    driver, ctrl, _, _ = started()
    assert driver.modes == [(tuple(J), 8)]
    assert ctrl.warnings == []
    _, ctrl2, _, _ = started(period=(0, -3))
    assert len(ctrl2.warnings) == 2 and "60C2sub1" in ctrl2.warnings[0]


def test_interpolation_period_problem():
    assert interpolation_period_problem("j", 10, -3, 10.0) == ""
    assert interpolation_period_problem("j", 1, -2, 10.0) == ""
    assert "0 ms" in interpolation_period_problem("j", 0, -3, 10.0)
    assert "disabled" in interpolation_period_problem("j", 10, -3, 0.0)


def test_trajectory_sets_a_target_every_cycle_and_succeeds():
    driver, ctrl, clock, results = started()
    ctrl.submit("g", J, [P((0.25, -0.25), (0.3, -0.3), (), 1.0), P((0.5, -0.5), (0.0, 0.0), (), 2.0)], 0.0)
    run(driver, ctrl, clock, 2.5)
    assert len(driver.commands[J[0]]) == 250
    assert driver.commands[J[0]][99] == pytest.approx(0.25, abs=1e-6)   # at t = 1.0 s
    assert driver.commands[J[0]][-1] == pytest.approx(0.5) and driver.commands[J[1]][-1] == pytest.approx(-0.5)
    assert [(r.goal_id, r.code) for r in results] == [("g", tj.SUCCESSFUL)]


def test_wrong_joint_is_rejected_and_nothing_moves():
    driver, ctrl, clock, results = started()
    with pytest.raises(TrajectoryError) as err:
        ctrl.submit("g", ["base_link1_joint", "elbow"], [P((1.0, 1.0), (), (), 1.0)], 0.0)
    assert err.value.code == tj.INVALID_JOINTS
    run(driver, ctrl, clock, 0.1)
    assert set(driver.commands[J[0]]) == {0.0}


def faulted_mid_goal(after_fault: float):
    """A 2 s goal whose second joint faults 1 s in, then ``after_fault`` s
    more: started()'s four."""
    driver, ctrl, clock, results = started()
    ctrl.submit("g", J, [P((1.0, 1.0), (), (), 2.0)], 0.0)
    run(driver, ctrl, clock, 1.0)
    driver.joints[J[1]].state = State.FAULT
    run(driver, ctrl, clock, after_fault)
    return driver, ctrl, clock, results


def test_fault_mid_trajectory_aborts_and_holds_after_recover():
    driver, ctrl, clock, results = faulted_mid_goal(0.1)
    assert [(r.goal_id, r.code) for r in results] == [("g", tj.PATH_TOLERANCE_VIOLATED)]
    assert "fault" in results[0].message and J[1] in results[0].message
    # the healthy joint decelerates to rest, the faulted one gets nothing
    driver.tried.clear()
    run(driver, ctrl, clock, 0.4)
    assert J[1] not in driver.tried and driver.tried.count(J[0]) == 40
    ramp = driver.commands[J[0]][-50:]
    assert all(b >= a for a, b in zip(ramp, ramp[1:])) and ramp[-1] == ramp[-10]
    assert ramp[-1] < 1.0
    with pytest.raises(TrajectoryError) as err:
        ctrl.submit("g2", J, [P((0.0, 0.0), (), (), 1.0)], 0.0)
    assert "fault" in err.value.message
    # recover: the drive is enabled again where it stands; the controller holds there
    held = driver.joints[J[0]].position
    driver.joints[J[1]].state = State.OPERATION_ENABLED
    n = len(driver.commands[J[0]])
    run(driver, ctrl, clock, 0.5)
    assert driver.commands[J[0]][n:] == pytest.approx([held] * 50)


def test_joint_leaving_csp_aborts():
    driver, ctrl, clock, results = started()
    ctrl.submit("g", J, [P((1.0, 1.0), (), (), 2.0)], 0.0)
    run(driver, ctrl, clock, 0.5)
    driver.joints[J[0]].mode_display = 1
    run(driver, ctrl, clock, 0.05)
    assert len(results) == 1 and results[0].code == tj.PATH_TOLERANCE_VIOLATED
    assert "not Cyclic Synchronous Position" in results[0].message


def test_stopping_the_controller_ends_the_goal_and_stops_commands():
    driver, ctrl, clock, results = started()
    ctrl.submit("g", J, [P((1.0, 1.0), (), (), 2.0)], 0.0)
    run(driver, ctrl, clock, 0.5)
    manager_stop = ctrl.stopping(driver)
    ctrl.state = "stopped"
    n = len(driver.commands[J[0]])
    run(driver, ctrl, clock, 0.2)
    assert len(driver.commands[J[0]]) == n
    assert manager_stop is None and len(results) == 1 and "stopped" in results[0].message
    with pytest.raises(TrajectoryError):
        ctrl.submit("g2", J, [P((1.0, 1.0), (), (), 2.0)], 0.0)


def test_halt_or_driver_error_aborts_and_refuses_goals():
    driver, ctrl, clock, results = started()
    ctrl.submit("g", J, [P((1.0, 1.0), (), (), 2.0)], 0.0)
    run(driver, ctrl, clock, 0.3)
    driver.joints[J[0]].halted = True
    run(driver, ctrl, clock, 0.05)
    assert len(results) == 1 and "halted" in results[0].message
    driver.joints[J[0]].halted = False
    driver.joints[J[1]].error = "heartbeat lost"
    with pytest.raises(TrajectoryError) as err:
        run(driver, ctrl, clock, 0.05)
        ctrl.submit("g2", J, [P((1.0, 1.0), (), (), 2.0)], 0.0)
    assert "heartbeat lost" in err.value.message


def test_refused_command_aborts_the_goal():
    driver, ctrl, clock, results = started()
    ctrl.submit("g", J, [P((1.0, 1.0), (), (), 2.0)], 0.0)
    driver.set_command = lambda joint, kind, value: Result(False, "outside limits")
    run(driver, ctrl, clock, 0.05)
    assert len(results) == 1 and "outside limits" in results[0].message


@pytest.mark.parametrize("params,text", [
    ({"type": TYPE_NAME, "joints": J, "required_drive_mode": 1}, "required_drive_mode"),
    ({"type": TYPE_NAME, "joints": J, "constraints": {"goal_time": "x"}}, "goal_time"),
    ({"type": TYPE_NAME, "joints": ["nope"]}, "unknown joint"),
    ({"type": TYPE_NAME, "joints": J, "stop_trajectory_duration": -1}, "stop_trajectory_duration"),
    ({"type": TYPE_NAME, "joints": J, "allow_partial_joints_goal": "yes"}, "allow_partial_joints_goal"),
])
def test_bad_controller_parameters_fail_to_load(params, text):
    manager = ControllerManager(FakeDriver(), J, {"jtc": params}.get)
    outcome = manager.load("jtc")
    assert not outcome.success and text in outcome.message


def test_goals_beyond_the_drivers_joint_limits_are_invalid():
    driver = FakeDriver()
    driver.joints[J[0]].limits = SimpleNamespace(lower=-1.0, upper=1.0)
    manager = ControllerManager(driver, J, PARAMS.get)
    manager.load("joint_trajectory_controller")
    assert manager.switch(["joint_trajectory_controller"], []).success
    ctrl = manager.get("joint_trajectory_controller")
    with pytest.raises(TrajectoryError) as err:
        ctrl.submit("g", J, [P((1.5, 0.0), (), (), 1.0)], 0.0)
    assert err.value.code == tj.INVALID_GOAL and "limits" in err.value.message
    ctrl.submit("g", J, [P((0.5, 3.0), (), (), 1.0)], 0.0)  # joint 2 has no limits


def test_query_state_samples_the_trajectory():
    driver, ctrl, clock, _ = started()
    ctrl.submit("g", J, [P((1.0, 2.0), (), (), 2.0)], 0.0)
    s = ctrl.query_state(clock.t + 1.0)
    assert s.positions == pytest.approx((0.5, 1.0))
    assert isinstance(ctrl, JointTrajectoryController)


def test_forged_readings_end_a_goal_but_never_become_targets():
    driver, ctrl, clock, results = started()
    ctrl.submit("g", J, [P((1.0, 1.0), (), (), 2.0)], 0.0)
    run(driver, ctrl, clock, 0.5)
    sent = driver.commands[J[0]][-1]
    for _ in range(60):  # a forger reports 5 rad every cycle
        driver.joints[J[0]].position = 5.0
        clock.t += DT
        ctrl.cycle(driver)
    assert [(r.goal_id, r.code) for r in results] == [("g", tj.PATH_TOLERANCE_VIOLATED)]
    assert "path tolerance" in results[0].message
    after = driver.commands[J[0]][driver.commands[J[0]].index(sent) + 1:]
    # from the target sent last: on along the path, decelerating to rest
    assert all(sent <= c <= 1.0 for c in after) and after[-1] == after[-10]
    assert after[-1] - sent < 0.5 * 0.2  # v * stop_trajectory_duration / 2 at 0.5 rad/s


def test_refused_command_holds_the_targets_sent_last_not_the_readings():
    driver, ctrl, clock, results = started()
    ctrl.submit("g", J, [P((1.0, 1.0), (), (), 2.0)], 0.0)
    run(driver, ctrl, clock, 0.5)
    sent = {j: driver.commands[j][-1] for j in J}
    for j in J:
        driver.joints[j].position = sent[j] - 0.15  # forged, inside the path tolerance (0.2)
    refuse = driver.set_command
    driver.set_command = lambda joint, kind, value: Result(False, "outside limits")
    clock.t += DT
    ctrl.cycle(driver)
    assert len(results) == 1 and "outside limits" in results[0].message
    driver.set_command = refuse
    run(driver, ctrl, clock, 0.1)
    assert driver.commands[J[0]][-10:] == pytest.approx([sent[J[0]]] * 10)
    assert driver.commands[J[1]][-10:] == pytest.approx([sent[J[1]]] * 10)


def test_after_recover_the_controller_holds_the_drivers_own_target():
    driver, ctrl, clock, results = faulted_mid_goal(0.4)
    # recover: the driver enables each drive at its 0x6064 read over SDO and
    # holds it (target_position); the TxPDO reading says something else
    for j, held in zip(J, (0.61, 0.47)):
        driver.joints[j].target_position = held
        driver.joints[j].position = 4.0
    driver.joints[J[1]].state = State.OPERATION_ENABLED
    n = {j: len(driver.commands[j]) for j in J}
    for _ in range(30):
        clock.t += DT
        ctrl.cycle(driver)
    assert driver.commands[J[0]][n[J[0]]:] == pytest.approx([0.61] * 30)
    assert driver.commands[J[1]][n[J[1]]:] == pytest.approx([0.47] * 30)


def test_the_cycle_runs_while_a_long_goal_is_built_and_preemption_takes_no_step():
    driver, ctrl, clock, results = started()
    ctrl.submit("g", J, [P((1.0, 1.0), (), (), 2.0)], 0.0)  # 0.5 rad/s: 0.005 rad per cycle
    run(driver, ctrl, clock, 0.5)
    start = ctrl.query_state(clock.t).positions
    # the same line on, at 10,000 points: a goal that takes long to build
    points = HeldPoints([P((start[0] + 0.5 * t, start[1] + 0.5 * t), (), (), t)
                         for t in (0.001 * (i + 1) for i in range(10000))])
    submitted = []
    builder = threading.Thread(target=lambda: submitted.append(ctrl.submit("long", J, points, 0.0)))
    builder.start()
    assert points.walking.wait(5.0)
    cycled = threading.Event()

    def cycles():  # 20 cycles while the goal is being built
        run(driver, ctrl, clock, 0.2)
        cycled.set()
    worker = threading.Thread(target=cycles, daemon=True)
    worker.start()
    ran = cycled.wait(5.0)
    points.release.set()
    builder.join(10.0)
    worker.join(10.0)
    assert ran, "the cycle waited for a goal being built"
    assert [o.goal_id for o in submitted] == ["g"]  # preempted
    run(driver, ctrl, clock, 0.3)
    targets = driver.commands[J[0]]
    steps = [b - a for a, b in zip(targets, targets[1:])]
    assert max(abs(s) for s in steps[5:]) <= 0.005 + 1e-9, max(steps[5:])
    assert targets[-1] == pytest.approx(start[0] + 0.5 * 0.5, abs=0.011)
