"""Shared rig for the virtual EPOS4 tests: a simulator on its own python-can
``virtual`` channel, an independent canopen client and a raw-frame observer.
(No tests here; the name only keeps the file among the simulator's tests.)"""
import itertools
import os
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
