"""Shared rig for the virtual EPOS4 tests: a simulator on its own python-can
``virtual`` channel, an independent canopen client and a raw-frame observer.
(No tests here; the name only keeps the file among the simulator's tests.)"""
import itertools
import math
import os
import struct
import sys
import time
from typing import Callable, List, Optional

import can
import canopen

_PKG = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
try:
    import maxon_epos4_ros_canopen  # noqa: F401
except ImportError:
    sys.path.insert(0, os.path.join(_PKG, "src"))

from maxon_epos4_ros_canopen.sim import NodeConfig, Simulator  # noqa: E402

CONFIG = os.path.join(_PKG, "config")
NODE1 = os.path.join(CONFIG, "epos4_node1.dcf")
NODE2 = os.path.join(CONFIG, "epos4_node2.dcf")
NODE1_HM = os.path.join(CONFIG, "epos4_node1_hm.dcf")
# Vendor DCFs live beside the repository: <repo>/../shared/vendor_dcf
VENDOR_DIR = os.path.join(os.path.dirname(os.path.dirname(_PKG)), "shared", "vendor_dcf")

_counter = itertools.count()


class Rig:
    """Simulator + canopen client + raw observer on one private virtual channel."""

    def __init__(self, nodes: List[NodeConfig], tick: float = 0.002):
        self.channel = "virtual_epos4_test_%d_%d" % (os.getpid(), next(_counter))
        self.simbus = can.Bus(interface="virtual", channel=self.channel)
        self.raw = can.Bus(interface="virtual", channel=self.channel)
        self.sim = Simulator(self.simbus, nodes, tick=tick).start()
        self.net = canopen.Network()
        self.net.NOTIFIER_CYCLE = 0.05  # faster disconnect; no effect on traffic
        self.net.connect(interface="virtual", channel=self.channel)

    def remote(self, node_id: int, dcf: str = NODE1) -> canopen.RemoteNode:
        node = canopen.RemoteNode(node_id, dcf)
        self.net.add_node(node)
        return node

    def drive(self, node_id: int, dcf: str = NODE1) -> canopen.BaseNode402:
        node = canopen.BaseNode402(node_id, dcf)
        self.net.add_node(node)
        return node

    def send(self, cob_id: int, data: bytes = b"", remote: bool = False) -> None:
        self.raw.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False,
                                  is_remote_frame=remote, dlc=0 if remote else len(data)))

    def drain(self) -> None:
        while self.raw.recv(timeout=0) is not None:
            pass

    def expect(self, match: Callable[[can.Message], bool], timeout: float = 5.0) -> Optional[can.Message]:
        """First frame seen by the observer that satisfies ``match``, or None."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            msg = self.raw.recv(timeout=min(0.05, max(0.0, end - time.monotonic())))
            if msg is not None and match(msg):
                return msg
        return None

    def handled(self, seconds: float = 0.0, timeout: float = 10.0) -> List[can.Message]:
        """Evidence for a check that a drive did NOT do something: wait
        until the simulator has handled every frame sent before this call
        and its clock ran on for at least ``seconds`` (counted in its loop's
        ticks, Simulator.ticks: two more than the period needs), then the
        frames the observer saw meanwhile: everything the nodes sent."""
        start = self.sim.ticks
        ticks = 2 + int(math.ceil(seconds / self.sim.tick_period))
        assert self.wait(lambda: self.sim.ticks >= start + ticks, timeout), "the simulator stands still"
        frames = []
        msg = self.raw.recv(timeout=0)
        while msg is not None:
            frames.append(msg)
            msg = self.raw.recv(timeout=0)
        return frames

    def collect(self, seconds: float) -> List[can.Message]:
        end, frames = time.monotonic() + seconds, []
        while time.monotonic() < end:
            msg = self.raw.recv(timeout=0.01)
            if msg is not None:
                frames.append(msg)
        return frames

    @staticmethod
    def wait(condition: Callable[[], bool], timeout: float = 10.0) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if condition():
                return True
            time.sleep(0.01)
        return condition()

    def close(self) -> None:
        self.sim.stop()
        self.net.disconnect()
        self.raw.shutdown()
        self.simbus.shutdown()


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

    def __init__(self, rig: Rig, node_id: int = 1, sync_period: float = 0.01):
        self.rig, self.cob = rig, 0x380 + node_id
        rig.send(0x000, bytes([0x01, node_id]))  # operational: PDOs flow
        self.task = rig.raw.send_periodic(can.Message(arbitration_id=0x080, data=b"",
                                                      is_extended_id=False), sync_period)
        self.samples: List = []
        self.frames: List[can.Message] = []  # every frame seen while recording

    def stop(self) -> None:
        self.task.stop()

    def record_until_rest(self, timeout: float = 20.0) -> List:
        """(position, velocity) samples from now until the velocity stays 0."""
        self.samples, self.frames = [], []
        rest = 0
        end = time.monotonic() + timeout
        while time.monotonic() < end and rest < 5:
            msg = self.rig.raw.recv(timeout=0.1)
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


def spin_up(node: canopen.RemoteNode, rig: Rig, rpm: int = 1000) -> None:
    """Profile velocity mode at ``rpm`` (0x6084 and 0x6085 left as the test set them)."""
    enable(node, 3)
    node.sdo[0x60FF].raw = rpm
    assert rig.wait(lambda: node.sdo[0x606C].raw > 0.95 * rpm)
