"""The CSP example in one process, for test_trajectory_csp_sim.py and
benchmarks/csp_tracking.py (not a test itself): two virtual EPOS4 and the
driver with the example's YAML files on a private python-can virtual
channel, the JointTrajectoryController started in its controller manager,
and a listener keeping every frame on the channel."""
from __future__ import annotations

import itertools
import os
import threading
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Tuple

import can
import yaml

from maxon_epos4_ros_canopen.clock import REAL, Clock
from maxon_epos4_ros_canopen.config import load_config
from maxon_epos4_ros_canopen.controllers import ControllerManager
from maxon_epos4_ros_canopen.driver import Driver
from maxon_epos4_ros_canopen.sim import NodeConfig, Simulator
from maxon_epos4_ros_canopen.trajectory_controller import JointTrajectoryController

PKG = Path(__file__).resolve().parents[2]
CONFIG = PKG / "config"
JOINTS = ["base_link1_joint", "link1_link2_joint"]
CONTROLLER = "joint_trajectory_controller"
_channels = itertools.count()


MASTER_CONSUMER_2S = "0x007F07D0"  # 0x1016 entry: node 0x7F, 2000 ms


# flush()'s marker: an identifier none of the rig's services or PDOs uses
# (the simulator and the driver take no notice of it).
MARKER = 0x6C0
SYNC_COB_ID = 0x080


def wait(condition: Callable[[], bool], timeout: float, clock: Clock = REAL) -> bool:
    """Whether ``condition`` came to hold within ``timeout`` s of ``clock``
    (the real one polls; a stepped one runs its events meanwhile)."""
    return clock.wait_until(condition, timeout)


class Listener:
    """Every frame on the channel, with its arrival time (on ``clock``): a
    reader thread on the real clock, the clock's pump on a stepped one."""

    def __init__(self, channel: str, clock: Clock = REAL) -> None:
        self.clock = clock
        self.bus = can.Bus(interface="virtual", channel=channel)
        self._marker_bus = can.Bus(interface="virtual", channel=channel)
        self._markers = itertools.count()
        self.frames: List[can.Message] = []
        self.arrivals: List[float] = []
        self._run = True
        self._thread: Optional[threading.Thread] = None
        if clock.stepped:
            clock.add_pump(self.bus, self._seen)
        else:
            self._thread = threading.Thread(target=self._loop, daemon=True)
            self._thread.start()

    def _seen(self, msg: can.Message) -> None:
        self.arrivals.append(self.clock.now())
        self.frames.append(msg)

    def _loop(self) -> None:
        while self._run:
            msg = self.bus.recv(timeout=0.05)
            if msg is not None:
                self._seen(msg)

    def take(self) -> List[can.Message]:
        frames, self.frames, self.arrivals = self.frames, [], []
        return frames

    def flush(self, timeout: float) -> bool:
        """Wait until every frame sent before this call is in ``frames``:
        a marker frame sent now is received after them (the virtual bus
        keeps each receiver's frames in order). False after ``timeout`` s."""
        data = next(self._markers).to_bytes(4, "little")
        self._marker_bus.send(can.Message(arbitration_id=MARKER, data=data, is_extended_id=False))
        return wait(lambda: any(f.arbitration_id == MARKER and bytes(f.data) == data for f in reversed(self.frames)),
                    timeout, self.clock)

    def close(self) -> None:
        self._run = False
        if self._thread is not None:
            self._thread.join(timeout=2)
        else:
            self.clock.remove_pump(self.bus)
        self.bus.shutdown()
        self._marker_bus.shutdown()


class CspRig:
    def __init__(self, adjust: Optional[Callable[[Dict[str, Any]], None]] = None,
                 cycle_hook: Optional[Callable[[JointTrajectoryController], None]] = None,
                 clock: Clock = REAL) -> None:
        """``adjust(params)`` may change the parameters before loading;
        ``cycle_hook(controller)`` runs after the controller's cycle each SYNC;
        ``clock``: the real one (the soak benchmark), or a test's stepped one."""
        self.clock = clock
        self.channel = "csp_rig_%d_%d" % (os.getpid(), next(_channels))
        self.simbus = can.Bus(interface="virtual", channel=self.channel)
        self.sim = Simulator(self.simbus, [NodeConfig(1, str(CONFIG / "epos4_node1.dcf")),
                                           NodeConfig(2, str(CONFIG / "epos4_node2.dcf"))], tick=0.002,
                             clock=clock).start()
        self.params: Dict[str, Any] = {}
        for name in ("canopen_bus_layer.yaml", "controller_2dof_csp.yaml", "node_layer_2dof_csp.yaml"):
            self.params.update(yaml.safe_load((CONFIG / name).read_text()))
        self.params["bus"]["device"] = "virtual:" + self.channel
        # The drives watch the master's heartbeat for 2 s, not the 150 ms init
        # derives from the example's 20 Hz: in one process on a loaded host the
        # heartbeat thread can wait for the GIL that long, and the drives
        # would then rightly stop (test_driver.py's rig does the same).
        self.params["defaults"]["dcf_overlay"]["1016sub1"] = MASTER_CONSUMER_2S
        if adjust is not None:
            adjust(self.params)
        self.driver = Driver(load_config(self.params, "csp_rig", lambda pkg: str(PKG)), clock=clock)
        self.listener = Listener(self.channel, clock)
        self.manager: Optional[ControllerManager] = None
        self.outcomes: List[Any] = []
        self._hook = cycle_hook

    def start(self) -> JointTrajectoryController:
        """init, load and start the controller; raises RuntimeError naming what failed."""
        result = self.driver.init()
        if not result.success:
            raise RuntimeError("driver init failed: %s" % result.message)
        self.manager = ControllerManager(self.driver, list(self.driver.joints), self.params.get)
        loaded = self.manager.load(CONTROLLER)
        if not loaded.success:
            raise RuntimeError(loaded.message)
        ctrl = self.manager.get(CONTROLLER)
        ctrl.clock = self.clock.now  # trajectory time on the rig's clock, as the ROS adapter sets ROS time
        self.driver.add_cycle_callback(lambda driver: self._cycle(ctrl, driver))
        started = self.manager.switch([CONTROLLER], [])
        if not started.success:
            raise RuntimeError("controller did not start: %s" % started.message)
        ctrl.on_outcome.append(self.outcomes.append)
        return ctrl

    def _cycle(self, ctrl: JointTrajectoryController, driver: Driver) -> None:
        ctrl.cycle(driver)
        if self._hook is not None:
            self._hook(ctrl)

    def close(self) -> None:
        if self.manager is not None:
            self.manager.stop_all()
        self.driver.shutdown()
        self.driver.close()
        self.listener.close()
        self.sim.stop()
        self.simbus.shutdown()


def pdo_mapping(sim: Simulator, node_id: int, index: int, comm: int, mapping: int) -> Tuple[int, int]:
    """(COB-ID, byte offset) of object ``index`` in the drive's active PDOs
    whose communication parameters start at ``comm`` (0x1400 RPDOs, 0x1800
    TPDOs) and mapping parameters at ``mapping`` (0x1600, 0x1A00)."""
    for n in range(4):
        cob = sim.read(node_id, comm + n, 1)
        if cob & 0x80000000:
            continue
        offset = 0
        for sub in range(1, sim.read(node_id, mapping + n, 0) + 1):
            entry = sim.read(node_id, mapping + n, sub)
            if entry >> 16 == index:
                return cob & 0x7FF, offset
            offset += (entry & 0xFF) // 8
    raise AssertionError("no PDO of node %d carries 0x%04X" % (node_id, index))


def position_mapping(sim: Simulator, node_id: int) -> Tuple[int, int]:
    """(COB-ID, byte offset) of 0x6064 in the drive's active TPDOs."""
    return pdo_mapping(sim, node_id, 0x6064, 0x1800, 0x1A00)


def target_mapping(sim: Simulator, node_id: int) -> Tuple[int, int]:
    """(COB-ID, byte offset) of 0x607A in the drive's active RPDOs."""
    return pdo_mapping(sim, node_id, 0x607A, 0x1400, 0x1600)


class Forger:
    """Answers each frame on ``cob`` with a copy carrying ``value`` at
    ``offset`` (while ``active``; value None: an exact copy): the driver's
    latest frame is then the forged one."""

    def __init__(self, channel: str, cob: int, offset: int = 0, value: Optional[int] = None) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.cob, self.offset, self.value = cob, offset, value
        self.active = False
        self.sent = 0
        self._run = True
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while self._run:
            msg = self.bus.recv(timeout=0.05)
            if msg is None or msg.arbitration_id != self.cob or not self.active:
                continue
            data = bytearray(msg.data)
            if self.value is not None:
                data[self.offset:self.offset + 4] = self.value.to_bytes(4, "little", signed=True)
            self.bus.send(can.Message(arbitration_id=self.cob, data=bytes(data), is_extended_id=False))
            self.sent += 1

    def close(self) -> None:
        self._run = False
        self._thread.join(timeout=2)
        self.bus.shutdown()


def targets_per_sync(frames, cob, offset):
    """0x607A values sent in each SYNC period, one list per period."""
    periods, current = [], None
    for f in frames:
        if f.arbitration_id == SYNC_COB_ID:
            if current is not None:
                periods.append(current)
            current = []
        elif f.arbitration_id == cob and current is not None:
            current.append(int.from_bytes(f.data[offset:offset + 4], "little", signed=True))
    return periods


class HeldPoints(list):
    """Trajectory points whose first walk waits until ``release`` is set:
    a goal still being validated (10,000 points take a while) for as long
    as a test wants. ``walking`` is set once the walk began."""

    def __init__(self, points) -> None:
        super().__init__(points)
        self.walking = threading.Event()
        self.release = threading.Event()

    def __iter__(self):
        self.walking.set()
        assert self.release.wait(15.0), "never released"
        return super().__iter__()
