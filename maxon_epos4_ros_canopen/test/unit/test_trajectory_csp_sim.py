"""The CSP example end to end in one process: the driver (with the example's
YAML files), the JointTrajectoryController in its controller manager, and two
virtual EPOS4 on a private python-can virtual channel. What is checked is
what the drives receive (RPDO frames after each SYNC) and hold (0x607A)."""
from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))  # csp_rig beside this file (any import mode)
from csp_rig import JOINTS as J, CspRig  # noqa: E402

from maxon_epos4_ros_canopen import trajectory as tj  # noqa: E402
from maxon_epos4_ros_canopen.sim import Simulator  # noqa: E402
from maxon_epos4_ros_canopen.trajectory import TrajectoryPoint as P  # noqa: E402

INC_PER_RAD = 83200 / (2 * math.pi)
SYNC = 0x80


def inc(rad: float) -> int:
    return int(round(rad * INC_PER_RAD))


@pytest.fixture
def rig():
    rig = CspRig()
    try:
        ctrl = rig.start()
        yield rig.sim, rig.driver, ctrl, rig.listener, rig.outcomes
    finally:
        rig.close()


def wait(condition, timeout=15.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.01)
    return False


def target_mapping(sim: Simulator, node_id: int):
    """(COB-ID, byte offset) of 0x607A in the drive's active RPDOs."""
    for n in range(4):
        cob = sim.read(node_id, 0x1400 + n, 1)
        if cob & 0x80000000:
            continue
        offset = 0
        for sub in range(1, sim.read(node_id, 0x1600 + n, 0) + 1):
            entry = sim.read(node_id, 0x1600 + n, sub)
            if entry >> 16 == 0x607A:
                return cob & 0x7FF, offset
            offset += (entry & 0xFF) // 8
    raise AssertionError("no RPDO carries 0x607A")


def targets_per_sync(frames, cob, offset):
    """0x607A values sent in each SYNC period, one list per period."""
    periods, current = [], None
    for f in frames:
        if f.arbitration_id == SYNC:
            if current is not None:
                periods.append(current)
            current = []
        elif f.arbitration_id == cob and current is not None:
            current.append(int.from_bytes(f.data[offset:offset + 4], "little", signed=True))
    return periods


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
    time.sleep(0.05)
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
    ctrl.submit("g", J, [P((1.0, 1.0), (0.0, 0.0), (), 2.0)], 0.0)
    time.sleep(0.6)
    sim.inject_fault(2, "emcy", 0x8611)
    assert wait(lambda: done)
    assert done[0].code == tj.PATH_TOLERANCE_VIOLATED and J[1] in done[0].message
    at_abort = sim.read(1, 0x607A)
    time.sleep(0.4)  # node 1 decelerates over stop_trajectory_duration (0.2 s), then holds
    held = sim.read(1, 0x607A)
    assert at_abort <= held < inc(1.0)
    time.sleep(0.3)
    assert sim.read(1, 0x607A) == held  # node 1 held where it stopped
    with pytest.raises(tj.TrajectoryError):
        ctrl.submit("g2", J, [P((0.0, 0.0), (), (), 1.0)], 0.0)
    result = driver.recover()
    assert result.success, result.message
    assert wait(lambda: not ctrl._not_ready and ctrl.last_cycle is not None)
    time.sleep(0.2)
    for node_id in (1, 2):
        assert abs(sim.read(node_id, 0x607A) - sim.read(node_id, 0x6064)) < 50
    # and it follows goals again
    ctrl.submit("g3", J, [P((0.1, 0.1), (0.0, 0.0), (), 1.0)], 0.0)
    assert wait(lambda: len(done) == 2)
    assert done[1].goal_id == "g3" and done[1].code == tj.SUCCESSFUL, done[1]
