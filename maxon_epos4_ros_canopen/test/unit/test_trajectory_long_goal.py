"""A 10,000-point goal preempting a moving one, in the CSP example against
the virtual EPOS4: the driver's cycle goes on while the goal is built (its
SYNCs and targets keep coming), and the preemption continues from the
targets sent last without a step, as the 0x607A frames on the bus show.
(benchmarks/trajectory_preemption.py measures the stall and the steps.)"""
from __future__ import annotations

import math
import threading

import pytest

from csp_rig import JOINTS as J, SYNC_COB_ID, CspRig, HeldPoints, target_mapping, targets_per_sync, wait
from maxon_epos4_ros_canopen.trajectory import TrajectoryPoint as P

INC_PER_RAD = 83200 / (2 * math.pi)
TIMEOUT = 15.0
SPEED = 0.2          # rad/s of joint 1: 26.5 inc per 10 ms SYNC period
BUILDING_CYCLES = 30  # driver cycles that must pass while the long goal is built


def no_path_tolerance(params) -> None:
    """A loaded host can delay the simulated drives past the example's path
    tolerance: here the targets are what is judged, so goals do not abort."""
    for joint in J:
        params["joint_trajectory_controller"]["constraints"][joint]["trajectory"] = 0.0


@pytest.fixture
def rig():
    rig = CspRig(adjust=no_path_tolerance)
    try:
        yield rig, rig.start()
    finally:
        rig.close()


def test_a_long_goal_preempts_a_moving_one_without_a_stall_or_a_step(rig):
    rig, ctrl = rig
    sim, driver, recorder = rig.sim, rig.driver, rig.listener
    mapping = target_mapping(sim, 1)
    # the first goal still runs when the long one comes, however long a
    # loaded host takes to build it (the preempted goal's outcome is checked)
    ctrl.submit("g", J, [P((10 * SPEED, 0.0), (), (), 10.0)], 0.0)
    assert wait(lambda: sim.read(1, 0x607A) > 0.2 * INC_PER_RAD, TIMEOUT)
    recorder.take()
    stamp = ctrl.clock()
    start = ctrl.query_state(stamp).positions
    # the same line on from there, 10,000 points 1 ms apart
    points = HeldPoints([P((start[0] + SPEED * t, 0.0), (), (), t)
                         for t in (0.001 * (i + 1) for i in range(10000))])
    submitted = []
    builder = threading.Thread(target=lambda: submitted.append(ctrl.submit("long", J, points, stamp)), daemon=True)
    builder.start()
    try:
        assert points.walking.wait(TIMEOUT)
        cycles = driver.cycles
        ran = wait(lambda: driver.cycles >= cycles + BUILDING_CYCLES, 5.0)
    finally:
        points.release.set()
    builder.join(TIMEOUT)
    assert ran, "the driver's cycle stopped while a goal was being built"
    assert [o.goal_id for o in submitted] == ["g"]
    assert wait(lambda: driver.cycles >= cycles + BUILDING_CYCLES + 50, TIMEOUT)
    assert recorder.flush(TIMEOUT)
    frames = recorder.take()
    syncs = [f.timestamp for f in frames if f.arbitration_id == SYNC_COB_ID]
    periods = targets_per_sync(frames, *mapping)
    # (the times between the SYNCs before and after the period, the 0x607A
    # step to that period); the targets of a period are sampled in the
    # cycle that sends the SYNC closing it
    steps = [(c_t - a_t, y[-1] - x[-1]) for a_t, c_t, x, y in zip(syncs, syncs[2:], periods, periods[1:])
             if x and y]
    assert len(steps) >= BUILDING_CYCLES + 40
    # Continuous across the preemption: every step is at most what the
    # line's speed gives for the time around it (a cycle that runs late
    # samples the trajectory later, and sends its SYNC later still while
    # another thread holds the interpreter; one SYNC period of slack, and
    # rounding). A restart from elsewhere than where the targets were going
    # would step further, or back.
    per_s = SPEED * INC_PER_RAD
    worst = max(steps, key=lambda gs: abs(gs[1]) - per_s * gs[0])
    assert all(0 <= step <= per_s * (span + 0.010) + 2 for span, step in steps), (worst, steps)
