"""The CSP trajectory controller under forged TxPDO positions, judged from
the virtual EPOS4's own position (its 0x6064 and 0x607A, read by the
simulator), not from what the driver reads.

A forger on the bus answers each of node 1's position TxPDOs with a copy
whose 0x6064 lies far beyond the planned path. Readings may at worst abort
a goal (and its result says so); no forged value becomes a target: the
joint keeps to its planned path, and after an abort, a preemption or a
``recover`` it holds a target the controller sent itself or the one the
driver read over SDO."""
from __future__ import annotations

import math
import threading
import time
from typing import List, Optional

import pytest

from csp_rig import JOINTS as J, CspRig, Forger, position_mapping, wait as rig_wait
from maxon_epos4_ros_canopen import trajectory as tj
from maxon_epos4_ros_canopen.sim import Simulator
from maxon_epos4_ros_canopen.trajectory import TrajectoryPoint as P

INC_PER_RAD = 83200 / (2 * math.pi)
TIMEOUT = 15.0
PATH_TOLERANCE = 0.1  # rad, constraints/<joint>/trajectory in controller_2dof_csp.yaml
FORGED = 1.5          # rad: the position the forger reports for node 1
SETTLE_CYCLES = 30    # driver cycles the drives are watched after recover (0.3 s at 10 ms)


def inc(rad: float) -> int:
    return int(round(rad * INC_PER_RAD))


class Track:
    """The simulator's 0x6064 and 0x607A of node 1, sampled by a thread."""

    def __init__(self, sim: Simulator, node_id: int = 1) -> None:
        self.sim, self.node_id = sim, node_id
        self.positions: List[int] = []
        self.targets: List[int] = []
        self._run = True
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while self._run:
            self.positions.append(self.sim.read(self.node_id, 0x6064))
            self.targets.append(self.sim.read(self.node_id, 0x607A))
            time.sleep(0.003)

    def stop(self) -> "Track":
        self._run = False
        self._thread.join(timeout=2)
        return self


@pytest.fixture
def forged():
    rig = CspRig()
    forger: Optional[Forger] = None
    try:
        ctrl = rig.start()
        cob, offset = position_mapping(rig.sim, 1)
        forger = Forger(rig.channel, cob, offset, inc(FORGED))
        yield rig, ctrl, forger
    finally:
        if forger is not None:
            forger.close()
        rig.close()


def wait(condition, timeout=TIMEOUT) -> bool:
    return rig_wait(condition, timeout)


def cycles_pass(rig: CspRig, n: int) -> bool:
    start = rig.driver.cycles
    return wait(lambda: rig.driver.cycles >= start + n)


def test_forged_positions_never_take_a_joint_off_its_planned_path(forged):
    rig, ctrl, forger = forged
    sim, done = rig.sim, rig.outcomes
    start = sim.read(1, 0x6064)
    forger.active = True
    assert wait(lambda: forger.sent >= 5)
    track = Track(sim)
    ctrl.submit("g", J, [P((0.5, 0.0), (0.0, 0.0), (), 1.0)], 0.0)
    assert wait(lambda: done)
    # the goal is over (a forged reading may abort it): the joint still must
    # not leave the planned path while the controller stops and holds
    assert cycles_pass(rig, 50)
    track.stop()
    forger.active = False
    assert forger.sent > 50
    outcome = done[0]
    assert outcome.goal_id == "g"
    if outcome.code != tj.SUCCESSFUL:
        # the result says why: the path tolerance, by the readings
        assert outcome.code == tj.PATH_TOLERANCE_VIOLATED and "path tolerance" in outcome.message, outcome
    low, high = min(start, inc(0.5)) - inc(PATH_TOLERANCE), max(start, inc(0.5)) + inc(PATH_TOLERANCE)
    assert low <= min(track.targets) and max(track.targets) <= high, (min(track.targets), max(track.targets))
    assert low <= min(track.positions) and max(track.positions) <= high, (min(track.positions),
                                                                          max(track.positions))


def test_recover_under_forged_positions_holds_what_the_driver_read_by_sdo(forged):
    rig, ctrl, forger = forged
    sim, driver = rig.sim, rig.driver
    ctrl.submit("g", J, [P((0.2, 0.0), (0.0, 0.0), (), 0.5)], 0.0)
    assert wait(lambda: rig.outcomes)  # reached, or stopped on the way (a loaded host lags)
    assert wait(lambda: ctrl.last_cycle.desired.velocities[0] == 0.0)
    assert wait(lambda: abs(sim.read(1, 0x6064) - sim.read(1, 0x607A)) < 20)
    sim.inject_fault(2, "emcy", 0x8611)
    assert wait(lambda: ctrl._not_ready != "")
    assert wait(lambda: sim.read(2, 0x606C) == 0)
    forger.active = True
    assert wait(lambda: forger.sent >= 5)
    before = sim.read(1, 0x6064)
    result = driver.recover()
    assert result.success, result.message
    track = Track(sim)
    assert cycles_pass(rig, SETTLE_CYCLES)
    track.stop()
    forger.active = False
    # node 1 stays where it stood: no forged position became its target
    assert all(abs(t - before) < 50 for t in track.targets), (before, min(track.targets), max(track.targets))
    assert all(abs(p - before) < 50 for p in track.positions), (before, min(track.positions),
                                                               max(track.positions))
    # and the controller holds what the driver holds (0x6064 read over SDO)
    held = ctrl.query_state(ctrl.clock()).positions
    assert abs(inc(held[0]) - sim.read(1, 0x607A)) <= 1
    assert abs(inc(held[1]) - sim.read(2, 0x607A)) <= 1
