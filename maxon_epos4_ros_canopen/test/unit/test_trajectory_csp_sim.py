"""The CSP example end to end in one process: the driver (with the example's
YAML files), the JointTrajectoryController in its controller manager, and two
virtual EPOS4 on a private python-can virtual channel. What is checked is
what the drives receive (RPDO frames after each SYNC) and hold (0x607A)."""
from __future__ import annotations

import math
from typing import List, Tuple

import pytest

from csp_rig import JOINTS as J, CspRig, Listener, target_mapping, targets_per_sync, wait as rig_wait
from maxon_epos4_ros_canopen import trajectory as tj
from maxon_epos4_ros_canopen.clock import SteppedClock
from maxon_epos4_ros_canopen.driver import Driver
from maxon_epos4_ros_canopen.sim import Simulator
from maxon_epos4_ros_canopen.trajectory import TrajectoryPoint as P

INC_PER_RAD = 83200 / (2 * math.pi)
# How long a wait for a condition may take before the test fails: generous,
# it only bounds how long a failure takes on a loaded host.
TIMEOUT = 15.0
# SYNC periods in a row with one and the same 0x607A that show a joint held
# (while it moves or decelerates, the target changes every period), and the
# SYNC periods after them it must go on holding it (0.3 s at 10 ms).
HOLD_PERIODS = 10
STILL_PERIODS = 30
# SYNC periods of the controller's targets after recover before the drives
# are checked to hold where they stood (about 0.2 s at 10 ms).
SETTLE_PERIODS = 20


def inc(rad: float) -> int:
    return int(round(rad * INC_PER_RAD))


# The clock of the test under way (the rig fixture's): the waits below run on it.
_clock = [SteppedClock()]


@pytest.fixture
def rig():
    _clock[0] = SteppedClock()
    rig = CspRig(clock=_clock[0])
    try:
        ctrl = rig.start()
        yield rig.sim, rig.driver, ctrl, rig.listener, rig.outcomes
    finally:
        rig.close()


def wait(condition, timeout=TIMEOUT) -> bool:
    return rig_wait(condition, timeout, _clock[0])


def caught_up(sim: Simulator) -> bool:
    """Wait until the simulator handled every frame already on the bus (its
    loop advanced the nodes twice more: Simulator.ticks)."""
    start = sim.ticks
    return wait(lambda: sim.ticks >= start + 2)


def flushed(driver: Driver, recorder: Listener) -> None:
    """Wait until the recorder holds every frame of the driver's cycle under
    way now. A cycle publishes its number (Driver.cycles) before its
    callbacks run and its frames go out: once the next number is out, they
    were sent, and a flush of the recorder brings them in."""
    cycle = driver.cycles
    assert wait(lambda: driver.cycles > cycle)
    assert recorder.flush(TIMEOUT)


def last_targets(recorder: Listener, mapping: Tuple[int, int]) -> List[int]:
    """The 0x607A sent last in each complete SYNC period the recorder holds
    (since its last take()), for the periods that carried one."""
    return [p[-1] for p in targets_per_sync(list(recorder.frames), *mapping) if p]


def test_controller_starts_in_csp_without_warnings(rig):
    sim, driver, ctrl, _, _ = rig
    assert [sim.read(n, 0x6061) for n in (1, 2)] == [8, 8]
    assert [sim.read(n, 0x60C2, 1) for n in (1, 2)] == [10, 10]
    assert ctrl.warnings == []


def test_trajectory_reaches_the_drives_every_sync_and_succeeds(rig):
    sim, driver, ctrl, recorder, done = rig
    mapping = {n: target_mapping(sim, n) for n in (1, 2)}
    recorder.take()
    ctrl.submit("g", J, [P((0.25, -0.2), (0.3, -0.3), (), 0.5), P((0.5, -0.5), (0.0, 0.0), (), 1.0)], 0.0)
    assert wait(lambda: done)
    assert [(o.goal_id, o.code) for o in done] == [("g", tj.SUCCESSFUL)], done
    # the cycle that reported success sends its targets after the report
    flushed(driver, recorder)
    assert caught_up(sim)
    frames = recorder.take()
    for node_id, end in ((1, 0.5), (2, -0.5)):
        periods = targets_per_sync(frames, *mapping[node_id])
        assert len(periods) >= 80  # about 1 s of 10 ms SYNC periods
        missed = sum(1 for p in periods if not p)
        assert missed <= len(periods) // 20, "%d of %d SYNC periods without 0x607A" % (missed, len(periods))
        values = [v for p in periods for v in p]
        assert values[-1] == inc(end)
        assert sim.read(node_id, 0x607A) == inc(end)
        # monotonic approach: both points move each joint one way
        steps = [b - a for a, b in zip(values, values[1:])]
        assert all(s * end >= 0 for s in steps)
        # a new target every SYNC while moving (the trajectory is sampled each cycle)
        per_period = [p[-1] for p in periods if p]
        moving = [v for v in per_period if v not in (0, inc(end))]
        assert len(moving) >= 80
        repeats = sum(1 for a, b in zip(moving[5:-5], moving[6:-4]) if a == b)
        assert repeats <= len(moving) // 20, "%d SYNC periods repeated the previous target" % repeats
    assert driver.joints[J[0]].position == pytest.approx(0.5, abs=0.01)
    assert driver.joints[J[1]].position == pytest.approx(-0.5, abs=0.01)


def test_fault_mid_trajectory_aborts_holds_and_recovers_in_place(rig):
    sim, driver, ctrl, recorder, done = rig
    mapping = {n: target_mapping(sim, n) for n in (1, 2)}
    ctrl.submit("g", J, [P((1.0, 1.0), (0.0, 0.0), (), 2.0)], 0.0)
    # let the trajectory run: node 1 a fifth of its way, the goal still on
    assert wait(lambda: sim.read(1, 0x607A) >= inc(0.2))
    assert not done
    sim.inject_fault(2, "emcy", 0x8611)
    assert wait(lambda: done)
    assert done[0].code == tj.PATH_TOLERANCE_VIOLATED and J[1] in done[0].message
    at_abort = sim.read(1, 0x607A)
    # Node 1 decelerates over stop_trajectory_duration (0.2 s), then holds:
    # the controller's stop has come to rest (its desired velocity is zero
    # only at the end), and the drive gets one target HOLD_PERIODS SYNC
    # periods in a row.
    assert wait(lambda: ctrl.last_cycle.desired.velocities[0] == 0.0)
    flushed(driver, recorder)
    recorder.take()  # from here on, only targets of cycles after the stop
    assert wait(lambda: len(last_targets(recorder, mapping[1])) >= HOLD_PERIODS)
    targets = last_targets(recorder, mapping[1])
    held = targets[0]
    assert targets == [held] * len(targets)
    assert at_abort <= held < inc(1.0)
    # held still: STILL_PERIODS more SYNC periods with that target, and the drive has it
    recorder.take()
    assert wait(lambda: len(last_targets(recorder, mapping[1])) >= STILL_PERIODS)
    targets = last_targets(recorder, mapping[1])
    assert targets == [held] * len(targets)
    assert caught_up(sim)
    assert sim.read(1, 0x607A) == held  # node 1 held where it stopped
    with pytest.raises(tj.TrajectoryError):
        ctrl.submit("g2", J, [P((0.0, 0.0), (), (), 1.0)], 0.0)
    assert wait(lambda: sim.read(2, 0x606C) == 0)  # node 2 at rest in its fault
    before = {n: sim.read(n, 0x6064) for n in (1, 2)}
    result = driver.recover()
    assert result.success, result.message
    assert wait(lambda: not ctrl._not_ready and ctrl.last_cycle is not None)
    # recovered in place: SETTLE_PERIODS SYNC periods of the controller's
    # targets, all where the joints stand, and the drives hold them
    flushed(driver, recorder)
    recorder.take()  # from here on, only targets of the controller back in charge
    assert wait(lambda: all(len(last_targets(recorder, m)) >= SETTLE_PERIODS for m in mapping.values()))
    sent = {n: last_targets(recorder, m) for n, m in mapping.items()}
    assert caught_up(sim)
    for node_id in (1, 2):
        position = sim.read(node_id, 0x6064)
        assert abs(position - before[node_id]) < 50, (before[node_id], position)
        assert abs(sim.read(node_id, 0x607A) - position) < 50
        assert all(abs(t - position) < 50 for t in sent[node_id]), (position, sent[node_id])
    # and it follows goals again
    ctrl.submit("g3", J, [P((0.1, 0.1), (0.0, 0.0), (), 1.0)], 0.0)
    assert wait(lambda: len(done) == 2)
    assert done[1].goal_id == "g3" and done[1].code == tj.SUCCESSFUL, done[1]
