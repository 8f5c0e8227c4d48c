"""Trajectory core: what the drives would be commanded every SYNC, and how goals end."""
from __future__ import annotations

import math

import pytest

from maxon_epos4_ros_canopen import trajectory as tj
from maxon_epos4_ros_canopen.cia402 import OperationMode, State
from maxon_epos4_ros_canopen.trajectory import TrajectoryError, TrajectoryExecutor, TrajectoryPoint as P
from maxon_epos4_ros_canopen.trajectory_tolerances import (DEFAULT_STOPPED_VELOCITY_TOLERANCE, JointTolerance,
                                                           merge_goal_tolerances, tolerances_from_constraints)

J = ("base_link1_joint", "link1_link2_joint")
DT = 0.01  # SYNC period of the CSP example


def executor(**kw) -> TrajectoryExecutor:
    ex = TrajectoryExecutor(J, **kw)
    ex.reset(0.0, (0.0, 0.0))
    return ex


def run(ex: TrajectoryExecutor, t0: float, t1: float, actual=None):
    """Update every SYNC period from t0 to t1; actual follows desired unless given."""
    out = []
    n = int(round((t1 - t0) / DT))
    last = ex.query_state(t0).positions
    for i in range(n + 1):
        t = t0 + i * DT
        pos = actual(t) if actual else last
        o = ex.update(t, pos, None)
        last = o.desired.positions
        out.append((t, o))
    return out


def outcomes(samples):
    return [o.outcome for _, o in samples if o.outcome is not None]


# --- sampling ---------------------------------------------------------------

def test_cubic_passes_through_points_with_their_velocities():
    ex = executor()
    ex.submit("g", J, [P((1.0, -1.0), (0.5, 0.0), (), 1.0), P((2.0, 0.0), (0.0, 0.0), (), 2.0)], 0.0, 0.0)
    s = ex.query_state(1.0)
    assert s.positions == pytest.approx((1.0, -1.0))
    assert s.velocities == pytest.approx((0.5, 0.0))
    assert ex.query_state(2.0).positions == pytest.approx((2.0, 0.0))
    # starts at the held state, at rest
    s0 = ex.query_state(0.0)
    assert s0.positions == pytest.approx((0.0, 0.0)) and s0.velocities == pytest.approx((0.0, 0.0))


def test_quintic_matches_accelerations_and_is_continuous():
    ex = executor()
    ex.submit("g", J, [P((1.0, 1.0), (1.0, 0.0), (0.5, -0.5), 1.0), P((2.0, 0.0), (0.0, 0.0), (0.0, 0.0), 2.0)],
              0.0, 0.0)
    s = ex.query_state(1.0)
    assert s.accelerations == pytest.approx((0.5, -0.5))
    eps = 1e-6
    a, b = ex.query_state(1.0 - eps), ex.query_state(1.0 + eps)
    assert a.positions == pytest.approx(b.positions, abs=1e-5)
    assert a.velocities == pytest.approx(b.velocities, abs=1e-4)
    assert a.accelerations == pytest.approx(b.accelerations, abs=1e-3)
    assert ex.query_state(2.0).accelerations == pytest.approx((0.0, 0.0))


def test_positions_only_interpolate_linearly():
    ex = executor()
    ex.submit("g", J, [P((1.0, 2.0), (), (), 2.0)], 0.0, 0.0)
    s = ex.query_state(0.5)
    assert s.positions == pytest.approx((0.25, 0.5))
    assert s.velocities == pytest.approx((0.5, 1.0))


def test_segment_order_is_what_both_points_carry():
    ex = executor()
    # point 1 carries velocities, point 2 only positions: the 1 -> 2 segment is linear
    ex.submit("g", J, [P((1.0, 1.0), (0.0, 0.0), (), 1.0), P((2.0, 3.0), (), (), 2.0)], 0.0, 0.0)
    assert ex.query_state(1.5).positions == pytest.approx((1.5, 2.0))
    assert ex.query_state(1.25).velocities == pytest.approx((1.0, 2.0))


def test_goal_joint_order_is_mapped_to_controller_order():
    ex = executor()
    ex.submit("g", (J[1], J[0]), [P((0.3, 0.7), (), (), 1.0)], 0.0, 0.0)
    assert ex.query_state(1.0).positions == pytest.approx((0.7, 0.3))


def test_holds_last_point_after_the_end():
    ex = executor()
    ex.submit("g", J, [P((0.5, -0.5), (0.0, 0.0), (), 1.0)], 0.0, 0.0)
    s = ex.query_state(5.0)
    assert s.positions == pytest.approx((0.5, -0.5)) and s.velocities == (0.0, 0.0)


# --- validation -------------------------------------------------------------

@pytest.mark.parametrize("names,code", [
    (("base_link1_joint", "nope"), tj.INVALID_JOINTS),
    (("base_link1_joint", "base_link1_joint"), tj.INVALID_JOINTS),
    (("base_link1_joint",), tj.INVALID_JOINTS),  # partial goals are off by default
])
def test_wrong_joint_names_are_rejected(names, code):
    ex = executor()
    with pytest.raises(TrajectoryError) as err:
        ex.submit("g", names, [P((1.0,) * len(names), (), (), 1.0)], 0.0, 0.0)
    assert err.value.code == code
    assert ex.goal is None


@pytest.mark.parametrize("points,text", [
    ([P((1.0, 1.0), (), (), 1.0), P((2.0, 2.0), (), (), 1.0)], "increase"),
    ([P((1.0, 1.0), (), (), 2.0), P((2.0, 2.0), (), (), 1.0)], "increase"),
    ([P((1.0,), (), (), 1.0)], "positions"),
    ([P((1.0, 1.0), (1.0,), (), 1.0)], "velocities"),
    ([P((1.0, 1.0), (0.0, 0.0), (0.0,), 1.0)], "accelerations"),
    ([P((1.0, 1.0), (), (0.0, 0.0), 1.0)], "no velocities"),
    ([P((float("nan"), 1.0), (), (), 1.0)], "finite"),
    ([P((1.0, 1.0), (float("inf"), 0.0), (), 1.0)], "finite"),
    ([P((1.0, 1.0), (), (), float("nan"))], "increase"),
    ([P((1.0, 1.0), (), (), 0.0)], "position step"),
    ([P((1.0, 1.0), (), (), -0.5), P((2.0, 2.0), (), (), 1.0)], "increase"),
])
def test_malformed_goals_are_invalid(points, text):
    ex = executor()
    with pytest.raises(TrajectoryError) as err:
        ex.submit("g", J, points, 0.0, 0.0)
    assert err.value.code == tj.INVALID_GOAL
    assert text in err.value.message


def test_positions_outside_limits_are_invalid():
    ex = executor(position_limits={J[0]: (-1.0, 1.0)})
    with pytest.raises(TrajectoryError) as err:
        ex.submit("g", J, [P((1.5, 0.0), (), (), 1.0)], 0.0, 0.0)
    assert err.value.code == tj.INVALID_GOAL and "limits" in err.value.message


def test_old_header_stamp_is_rejected():
    ex = executor()
    with pytest.raises(TrajectoryError) as err:
        ex.submit("g", J, [P((1.0, 1.0), (), (), 1.0)], stamp=5.0, now=10.0)
    assert err.value.code == tj.OLD_HEADER_TIMESTAMP


def test_rejected_goal_leaves_the_running_one_untouched():
    ex = executor()
    ex.submit("g1", J, [P((1.0, 1.0), (), (), 1.0)], 0.0, 0.0)
    with pytest.raises(TrajectoryError):
        ex.submit("g2", ("x", "y"), [P((1.0, 1.0), (), (), 1.0)], 0.0, 0.5)
    assert ex.goal.goal_id == "g1"
    assert ex.query_state(1.0).positions == pytest.approx((1.0, 1.0))


def test_partial_goal_holds_other_joints_when_allowed():
    ex = executor(allow_partial_joints_goal=True)
    ex.reset(0.0, (0.2, 0.4))
    ex.submit("g", (J[1],), [P((1.0,), (), (), 1.0)], 0.0, 0.0)
    assert ex.query_state(1.0).positions == pytest.approx((0.2, 1.0))


def test_points_in_the_past_are_dropped_and_future_stamp_waits():
    ex = executor()
    # stamp 1 s in the past: the first point (at 0.5 s) is already over
    ex.submit("g", J, [P((5.0, 5.0), (), (), 0.5), P((1.0, 1.0), (), (), 2.0)], stamp=9.0, now=10.0)
    assert ex.query_state(10.0).positions == pytest.approx((0.0, 0.0))
    assert ex.query_state(11.0).positions == pytest.approx((1.0, 1.0))
    ex2 = executor()
    ex2.submit("g", J, [P((1.0, 1.0), (), (), 1.0)], stamp=3.0, now=1.0)
    assert ex2.query_state(2.9).positions == pytest.approx((0.0, 0.0))
    assert ex2.query_state(3.5).positions == pytest.approx((0.5, 0.5))


# --- preemption, cancel, abort ----------------------------------------------

def test_preempting_goal_splices_without_a_step():
    ex = executor()
    ex.submit("g1", J, [P((2.0, -2.0), (0.0, 0.0), (), 2.0)], 0.0, 0.0)
    first = run(ex, 0.0, 1.0)
    before = ex.query_state(1.0)
    preempted = ex.submit("g2", J, [P((-1.0, 1.0), (0.0, 0.0), (), 3.0)], 0.0, 1.0)
    assert preempted.goal_id == "g1" and preempted.code == tj.SUCCESSFUL and "preempted" in preempted.message
    after = ex.query_state(1.0)
    assert after.positions == pytest.approx(before.positions)
    assert after.velocities == pytest.approx(before.velocities)
    second = run(ex, 1.0, 4.5)
    positions = [o.desired.positions for _, o in first + second]
    steps = [max(abs(b - a) for a, b in zip(p, q)) for p, q in zip(positions, positions[1:])]
    # the fastest a cubic through these points moves is 1.5 rad/s (+ splice): a
    # step > 3 rad/s * DT would be a jump the drive cannot follow
    assert max(steps) < 3.0 * DT
    assert positions[-1] == pytest.approx((-1.0, 1.0))
    assert [o.goal_id for o in outcomes(second)] == ["g2"]


def test_cancel_decelerates_then_holds():
    ex = executor(stop_trajectory_duration=0.2)
    ex.submit("g", J, [P((2.0, 2.0), (), (), 2.0)], 0.0, 0.0)  # linear: 1 rad/s
    assert ex.cancel("other", 1.0) is False
    assert ex.cancel("g", 1.0) is True
    assert ex.goal is None
    s = ex.query_state(1.0)
    assert s.positions == pytest.approx((1.0, 1.0)) and s.velocities == pytest.approx((1.0, 1.0))
    end = ex.query_state(1.2)
    assert end.positions == pytest.approx((1.1, 1.1)) and end.velocities == pytest.approx((0.0, 0.0))
    assert ex.query_state(3.0).positions == pytest.approx((1.1, 1.1))
    samples = [ex.query_state(1.0 + k * DT).positions[0] for k in range(21)]
    assert all(b >= a for a, b in zip(samples, samples[1:]))  # no reversal while stopping


def test_abort_holds_measured_positions():
    ex = executor()
    ex.submit("g", J, [P((2.0, 2.0), (), (), 2.0)], 0.0, 0.0)
    out = ex.abort(1.0, (0.7, 0.8), tj.PATH_TOLERANCE_VIOLATED, "joint 'x': drive is fault")
    assert out.goal_id == "g" and out.code == tj.PATH_TOLERANCE_VIOLATED and "fault" in out.message
    assert ex.update(1.5, (0.7, 0.8)).desired.positions == pytest.approx((0.7, 0.8))
    assert ex.abort(2.0, (0.7, 0.8), tj.PATH_TOLERANCE_VIOLATED, "again") is None


def test_empty_trajectory_stops_and_succeeds():
    ex = executor()
    ex.submit("g1", J, [P((2.0, 2.0), (), (), 2.0)], 0.0, 0.0)
    pre = ex.submit("g2", J, [], 0.0, 1.0)
    assert pre.goal_id == "g1"
    res = outcomes(run(ex, 1.0, 2.0))
    assert [(o.goal_id, o.code) for o in res] == [("g2", tj.SUCCESSFUL)]


# --- tolerances -------------------------------------------------------------

def test_path_tolerance_violation_aborts_and_stops_from_the_target_sent_last():
    tol = tolerances_from_constraints(J, {J[0]: {"trajectory": 0.1}})
    ex = executor(tolerances=tol)
    ex.submit("g", J, [P((2.0, 0.0), (), (), 2.0)], 0.0, 0.0)
    samples = run(ex, 0.0, 1.0, actual=lambda t: (0.0, 0.0))  # joint 1 does not move
    res = outcomes(samples)
    assert len(res) == 1 and res[0].code == tj.PATH_TOLERANCE_VIOLATED
    assert "base_link1_joint" in res[0].message
    t_abort = next(t for t, o in samples if o.outcome)
    assert t_abort == pytest.approx(0.11, abs=DT)  # first cycle the error exceeds 0.1 rad
    # Readings judge, they never steer: the stop starts at the target sent
    # last (0.1 rad at 1 rad/s, one cycle before the abort) and decelerates
    # over stop_trajectory_duration (0.2 s) to 0.1 + 1.0 * 0.2 / 2, not at
    # the reading (0.0).
    sent = next(o.desired for t, o in samples if t == pytest.approx(t_abort - DT))
    assert sent.positions[0] == pytest.approx(t_abort - DT)
    assert ex.query_state(1.0).positions == pytest.approx((sent.positions[0] + 0.1, 0.0))


def test_goal_tolerance_waits_goal_time_then_fails():
    tol = tolerances_from_constraints(J, {"goal_time": 0.5, J[0]: {"goal": 0.01}, J[1]: {"goal": 0.01}})
    ex = executor(tolerances=tol)
    ex.submit("g", J, [P((1.0, 1.0), (), (), 1.0)], 0.0, 0.0)
    res = outcomes(run(ex, 0.0, 2.0, actual=lambda t: (min(t, 1.0), 0.95)))
    assert len(res) == 1 and res[0].code == tj.GOAL_TOLERANCE_VIOLATED
    assert "link1_link2_joint" in res[0].message


def test_goal_reached_late_within_goal_time_succeeds():
    tol = tolerances_from_constraints(J, {"goal_time": 0.5, J[0]: {"goal": 0.01}, J[1]: {"goal": 0.01}})
    ex = executor(tolerances=tol)
    ex.submit("g", J, [P((1.0, 1.0), (), (), 1.0)], 0.0, 0.0)
    samples = run(ex, 0.0, 2.0, actual=lambda t: (min(t / 1.2, 1.0),) * 2)
    res = outcomes(samples)
    assert [o.code for o in res] == [tj.SUCCESSFUL]
    assert next(t for t, o in samples if o.outcome) == pytest.approx(1.19, abs=0.02)


def goal_running_until(t: float) -> TrajectoryExecutor:
    """A goal to (1, 1) at 1 s, goal tolerance 0.01 within goal_time 0.5 s,
    followed exactly until ``t``."""
    tol = tolerances_from_constraints(J, {"goal_time": 0.5, J[0]: {"goal": 0.01}, J[1]: {"goal": 0.01}})
    ex = executor(tolerances=tol)
    ex.submit("g", J, [P((1.0, 1.0), (), (), 1.0)], 0.0, 0.0)
    assert outcomes(run(ex, 0.0, t)) == []
    return ex


def test_a_starved_cycle_judges_the_goal_on_readings_that_arrived_after_the_deadline():
    # The cycle ran last 0.2 s before the trajectory's end, then not for
    # 2.5 s: its first readings after that are still the ones from before
    # the end (the notifier that takes frames in was starved too). The
    # joint stood on its goal meanwhile; only a reading taken after the
    # deadline may say it did not.
    ex = goal_running_until(0.8)
    stale = ex.query_state(0.8).positions
    assert abs(stale[0] - 1.0) > 0.05
    o = ex.update(3.3, stale, None, readings_at=0.8)
    assert o.outcome is None, o.outcome
    o = ex.update(3.31, (1.0, 1.0), None, readings_at=3.305)
    assert o.outcome is not None and o.outcome.code == tj.SUCCESSFUL


def test_a_reading_from_before_the_end_is_no_success():
    ex = goal_running_until(0.99)
    # a reading at 0.995 stands within 0.01 of the goal, but the trajectory
    # had not ended then: the joint may go on past it
    o = ex.update(1.2, (0.999, 0.999), None, readings_at=0.995)
    assert o.outcome is None
    o = ex.update(1.21, (1.0, 1.0), None, readings_at=1.205)
    assert o.outcome is not None and o.outcome.code == tj.SUCCESSFUL


def test_a_fresh_reading_off_the_goal_after_the_deadline_fails_it_and_says_how_old_it_was():
    ex = goal_running_until(0.99)
    assert ex.update(1.6, (1.0, 0.9), None, readings_at=1.45).outcome is None  # read before the deadline
    o = ex.update(1.61, (1.0, 0.9), None, readings_at=1.58)
    assert o.outcome is not None and o.outcome.code == tj.GOAL_TOLERANCE_VIOLATED
    assert "link1_link2_joint" in o.outcome.message and "read 30 ms before" in o.outcome.message


def test_readings_that_never_come_after_the_deadline_are_judged_after_stale_cycles():
    ex = goal_running_until(0.99)
    ends = []
    for k in range(tj.STALE_READING_CYCLES + 1):
        o = ex.update(1.51 + k * DT, (1.0, 0.9), None, readings_at=0.9)
        ends.append(o.outcome)
    assert ends[:-1] == [None] * tj.STALE_READING_CYCLES
    assert ends[-1] is not None and ends[-1].code == tj.GOAL_TOLERANCE_VIOLATED
    assert "no reading after the deadline" in ends[-1].message


def test_stopped_velocity_tolerance_delays_success():
    ex = executor(tolerances=tolerances_from_constraints(J, {"stopped_velocity_tolerance": 0.05}))
    ex.submit("g", J, [P((1.0, 1.0), (), (), 1.0)], 0.0, 0.0)
    hits = []
    for k in range(200):
        t = k * DT
        vel = (0.2, 0.0) if t < 1.3 else (0.0, 0.0)
        o = ex.update(t, ex.query_state(t).positions, vel)
        if o.outcome:
            hits.append((t, o.outcome.code))
    assert len(hits) == 1 and hits[0][1] == tj.SUCCESSFUL and hits[0][0] == pytest.approx(1.3, abs=DT)


def test_goal_tolerances_override_defaults():
    base = tolerances_from_constraints(J, {J[0]: {"trajectory": 0.1, "goal": 0.02}, J[1]: {"goal": 0.02}})
    merged = merge_goal_tolerances(base, [(J[0], 0.5, 0.0, 0.0)], [(J[0], -1.0, 0.0, 0.0), (J[1], 0.0, 0.3, 0.0)],
                                   0.0)
    assert merged.path[J[0]].position == 0.5
    assert merged.goal[J[0]].position == 0.0  # -1: not checked
    assert merged.goal[J[1]] == JointTolerance(0.02, 0.3, 0.0)
    with pytest.raises(TrajectoryError) as err:
        merge_goal_tolerances(base, [("ghost", 1.0, 0.0, 0.0)], [], 0.0)
    assert err.value.code == tj.INVALID_GOAL and "ghost" in err.value.message


@pytest.mark.parametrize("constraints,text", [
    ({"goal_time": -1.0}, "goal_time"),
    ({"stopped_velocity_tolerance": "fast"}, "stopped_velocity_tolerance"),
    ({J[0]: {"goal": float("nan")}}, "base_link1_joint/goal"),
    ({J[0]: {"path": 0.1}}, "unknown keys"),
    ({"elbow": {"goal": 0.1}}, "elbow"),
])
def test_bad_constraints_name_the_key(constraints, text):
    with pytest.raises(ValueError) as err:
        tolerances_from_constraints(J, constraints, "/maxon/canopen_motor/joint_trajectory_controller/constraints")
    assert text in str(err.value) and "constraints" in str(err.value)


def test_constraints_defaults():
    tol = tolerances_from_constraints(J, None)
    assert tol.goal_time == 0.0 and tol.stopped_velocity_tolerance == DEFAULT_STOPPED_VELOCITY_TOLERANCE
    assert tol.goal[J[0]].velocity == DEFAULT_STOPPED_VELOCITY_TOLERANCE


# --- readiness --------------------------------------------------------------

def test_csp_readiness():
    assert tj.csp_readiness_problem("j", State.OPERATION_ENABLED, 8) == ""
    assert tj.csp_readiness_problem("j", State.OPERATION_ENABLED, OperationMode.CYCLIC_SYNC_POSITION) == ""
    assert "not Cyclic Synchronous Position" in tj.csp_readiness_problem("j", State.OPERATION_ENABLED, 1)
    assert "fault" in tj.csp_readiness_problem("j", State.FAULT, 8)
    assert "unknown" in tj.csp_readiness_problem("j", None, 8)


def test_controller_needs_joint_state_before_goals():
    ex = TrajectoryExecutor(J)
    with pytest.raises(TrajectoryError) as err:
        ex.submit("g", J, [P((1.0, 1.0), (), (), 1.0)], 0.0, 0.0)
    assert err.value.code == tj.INVALID_GOAL
    assert math.isfinite(DT)
