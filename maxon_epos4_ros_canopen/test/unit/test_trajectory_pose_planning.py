"""go_to_pose planning: SRDF states, joint limits, and a trajectory the
controller executes within those limits, ending exactly at the state."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from maxon_epos4_ros_canopen.pose_planning import (JointLimit, PlanningError, group_states_from_srdf,
                                                   limits_from_joint_limits, plan_point_to_point,
                                                   target_positions)
from maxon_epos4_ros_canopen.trajectory import TrajectoryExecutor

REPO = Path(__file__).resolve().parents[3]
MOVEIT_CONFIG = REPO / "maxon_epos4_moveit_config" / "config"
SCRIPT = REPO / "maxon_epos4_ros_canopen" / "scripts" / "go_to_pose"
J = ["base_link1_joint", "link1_link2_joint"]


def test_reads_the_packages_srdf_and_limits():
    states = group_states_from_srdf((MOVEIT_CONFIG / "maxon_epos4.srdf").read_text())
    assert target_positions(states, "maxon", "pose1", J) == [0.5, -0.5]
    assert target_positions(states, "maxon", "start", J) == [0.0, 0.0]
    limits = limits_from_joint_limits(yaml.safe_load((MOVEIT_CONFIG / "joint_limits.yaml").read_text()), J)
    assert limits[J[0]] == JointLimit(1.0, 2.0)


@pytest.mark.parametrize("text,message", [
    ("<robot", "not valid XML"),
    ('<robot><group_state name="p" group="g"><joint name="a" value="x"/></group_state></robot>', "not a number"),
    ('<robot><group_state group="g"/></robot>', "lacks its name"),
])
def test_bad_srdf(text, message):
    with pytest.raises(PlanningError) as err:
        group_states_from_srdf(text, "my.srdf")
    assert message in str(err.value) and "my.srdf" in str(err.value)


def test_unknown_state_lists_the_known_ones():
    states = group_states_from_srdf((MOVEIT_CONFIG / "maxon_epos4.srdf").read_text())
    with pytest.raises(PlanningError) as err:
        target_positions(states, "maxon", "pose9", J)
    assert "pose1" in str(err.value) and "start" in str(err.value)
    with pytest.raises(PlanningError) as err:
        target_positions(states, "arm", "pose1", J)
    assert "maxon" in str(err.value)


@pytest.mark.parametrize("entry,message", [
    ({"has_velocity_limits": False}, "no velocity limit"),
    ({"has_velocity_limits": True, "max_velocity": -1}, "max_velocity"),
    ({"has_velocity_limits": True, "max_velocity": 1.0}, "no acceleration limit"),
    ({"has_velocity_limits": True, "max_velocity": 1.0, "has_acceleration_limits": True,
      "max_acceleration": "fast"}, "max_acceleration"),
])
def test_bad_limits(entry, message):
    with pytest.raises(PlanningError) as err:
        limits_from_joint_limits({"joint_limits": {J[0]: entry}}, [J[0]])
    assert message in str(err.value)


def test_default_acceleration_fills_a_missing_limit():
    data = {"joint_limits": {J[0]: {"has_velocity_limits": True, "max_velocity": 1.0}}}
    assert limits_from_joint_limits(data, [J[0]], default_acceleration=3.0)[J[0]] == JointLimit(1.0, 3.0)


@pytest.mark.parametrize("start,goal,vs,acs", [
    ((0.0, 0.0), (0.5, -0.5), 1.0, 1.0),      # triangular for the faster limit
    ((0.0, 0.0), (3.0, -0.2), 0.5, 0.5),      # cruise phase, joint 1 dominates
    ((-1.0, 2.0), (1.0, 2.0), 1.0, 0.25),     # one joint stays put
])
def test_executed_trajectory_respects_limits_and_ends_at_goal(start, goal, vs, acs):
    limits = {J[0]: JointLimit(1.0, 2.0), J[1]: JointLimit(0.8, 1.5)}
    points = plan_point_to_point(J, start, goal, limits, vs, acs, sample_period=0.05)
    assert points[-1].positions == pytest.approx(goal)
    assert points[-1].velocities == pytest.approx((0.0, 0.0))
    times = [p.time_from_start for p in points]
    assert times[0] > 0 and all(b > a for a, b in zip(times, times[1:]))
    ex = TrajectoryExecutor(J)
    ex.reset(0.0, start)
    ex.submit("g", J, points, 0.0, 0.0)
    dt = 0.001
    prev = ex.query_state(0.0)
    for k in range(1, int((times[-1] + 0.1) / dt)):
        s = ex.query_state(k * dt)
        for j, name in enumerate(J):
            assert abs(s.velocities[j]) <= limits[name].max_velocity * vs * 1.001 + 1e-9
            assert abs(s.accelerations[j]) <= limits[name].max_acceleration * acs * 1.001 + 1e-9
            # the line in joint space: never beyond the goal
            lo, hi = sorted((start[j], goal[j]))
            assert lo - 1e-9 <= s.positions[j] <= hi + 1e-9
        prev = s
    assert prev.positions == pytest.approx(goal)


def test_already_there_gives_no_points():
    assert plan_point_to_point(J, (0.5, -0.5), (0.5, -0.5), {j: JointLimit(1, 1) for j in J}) == []


@pytest.mark.parametrize("kw,message", [
    ({"velocity_scaling": 0.0}, "velocity scaling"),
    ({"acceleration_scaling": 1.5}, "acceleration scaling"),
    ({"sample_period": 0.0}, "sample period"),
])
def test_bad_planning_arguments(kw, message):
    with pytest.raises(PlanningError) as err:
        plan_point_to_point(J, (0.0, 0.0), (1.0, 1.0), {j: JointLimit(1, 1) for j in J}, **kw)
    assert message in str(err.value)


def _script(*args):
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True,
                          env={"PYTHONPATH": str(REPO / "maxon_epos4_ros_canopen" / "src"), "PATH": "/usr/bin:/bin"})


def test_go_to_pose_dry_run_prints_the_plan():
    res = _script("pose1", "--dry-run", "--srdf", str(MOVEIT_CONFIG / "maxon_epos4.srdf"),
                  "--joint-limits", str(MOVEIT_CONFIG / "joint_limits.yaml"), "--start", "0", "0")
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    assert "'pose1' 0.5000, -0.5000" in lines[0]
    assert "pos=['0.5000', '-0.5000']" in lines[-1]


def test_go_to_pose_bad_input_exits_2_with_a_reason():
    res = _script("pose9", "--dry-run", "--srdf", str(MOVEIT_CONFIG / "maxon_epos4.srdf"),
                  "--joint-limits", str(MOVEIT_CONFIG / "joint_limits.yaml"), "--start", "0", "0")
    assert res.returncode == 2 and "no state 'pose9'" in res.stderr
    res = _script("pose1", "--dry-run", "--srdf", "/nonexistent.srdf",
                  "--joint-limits", str(MOVEIT_CONFIG / "joint_limits.yaml"), "--start", "0", "0")
    assert res.returncode == 2 and "cannot read /nonexistent.srdf" in res.stderr
