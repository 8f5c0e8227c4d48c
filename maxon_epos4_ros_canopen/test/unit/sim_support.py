"""Helpers for the virtual EPOS4 tests (no tests here): the DCFs, enabling
a drive over SDO, and a recorder of its ramps. The rig itself (simulator,
canopen client, frame recorder on a stepped clock) is conftest.py's
``sim_rig`` fixture."""
import os
import struct
from typing import List

import can
import canopen

from maxon_epos4_ros_canopen.clock import Clock
from maxon_epos4_ros_canopen.sim import NodeConfig  # noqa: F401 (the tests take it from here)

_PKG = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
CONFIG = os.path.join(_PKG, "config")
NODE1 = os.path.join(CONFIG, "epos4_node1.dcf")
NODE2 = os.path.join(CONFIG, "epos4_node2.dcf")
NODE1_HM = os.path.join(CONFIG, "epos4_node1_hm.dcf")
# Vendor DCFs live beside the repository: <repo>/../shared/vendor_dcf
VENDOR_DIR = os.path.join(os.path.dirname(os.path.dirname(_PKG)), "shared", "vendor_dcf")

def enable(node: canopen.RemoteNode, mode: int) -> None:
    """Mode, then shutdown/switch on/enable operation, over SDO."""
    node.sdo[0x6060].raw = mode
    for cw in (0x0006, 0x0007, 0x000F):
        node.sdo[0x6040].raw = cw
    assert node.sdo[0x6041].raw & 0x6F == 0x27


INC_PER_S_PER_RPM = 3200 / 60.0  # the project's DCFs: 3200 increments per turn


class RampRecorder:
    """Position and velocity of one node from its TxPDO3 (0x6064, 0x30D3 sub 1)
    at every SYNC the recorder sends: the slow-down a drive performs, seen
    from the bus, without timing anything (the deceleration follows from
    velocity and distance alone)."""

    def __init__(self, rig, node_id: int = 1, sync_period: float = 0.01):
        self.rig, self.cob = rig, 0x380 + node_id
        rig.send(0x000, bytes([0x01, node_id]))  # operational: PDOs flow
        self.task = rig.send_periodic(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False),
                                      sync_period)
        self.samples: List = []
        self.frames: List[can.Message] = []  # every frame seen while recording

    def stop(self) -> None:
        self.task.stop()

    def record_until_rest(self, timeout: float = 20.0) -> List:
        """(position, velocity) samples from now until the velocity stays 0."""
        self.samples, self.frames = [], []
        rest = 0
        end = self.rig.clock.now() + timeout
        while self.rig.clock.now() < end and rest < 5:
            msg = self.rig.recorder.next(0.1)
            if msg is not None:
                self.frames.append(msg)
            if msg is None or msg.arbitration_id != self.cob or len(msg.data) != 8:
                continue
            position, velocity = struct.unpack("<ii", bytes(msg.data))
            self.samples.append((position, velocity))
            rest = rest + 1 if velocity == 0 else 0
        return self.samples

    def deceleration(self, high: float = 0.8, low: float = 0.2) -> float:
        """rpm/s between the first sample under ``high`` x the start velocity
        and the last one above ``low`` x it: a = (v1^2 - v2^2) / (2 d)."""
        v0 = max(abs(v) for _, v in self.samples)
        window = [(p, v) for p, v in self.samples if low * v0 <= abs(v) <= high * v0]
        assert len(window) >= 2, "too few samples on the ramp: %s" % self.samples
        (p1, v1), (p2, v2) = window[0], window[-1]
        distance = abs(p2 - p1) / INC_PER_S_PER_RPM  # rpm x s
        return (v1 * v1 - v2 * v2) / (2.0 * distance)


def spin_up(node: canopen.RemoteNode, rig, rpm: int = 1000) -> None:
    """Profile velocity mode at ``rpm`` (0x6084 and 0x6085 left as the test set them)."""
    enable(node, 3)
    node.sdo[0x60FF].raw = rpm
    assert rig.wait(lambda: node.sdo[0x606C].raw > 0.95 * rpm)


WALL_OFFSET = 1000.0  # ScriptedClock's wall clock: its monotonic time plus this


class ScriptedClock(Clock):
    """Time a test script moves itself (``t``), for a simulator loop whose
    receives the script's bus answers at scripted times."""

    def __init__(self) -> None:
        self.t = 100.0

    def now(self) -> float:
        return self.t

    def wall(self) -> float:
        return self.t + WALL_OFFSET
