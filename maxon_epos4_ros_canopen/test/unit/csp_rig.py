"""The CSP example in one process, for test_trajectory_csp_sim.py and
benchmarks/csp_tracking.py (not a test itself): two virtual EPOS4 and the
driver with the example's YAML files on a private python-can virtual
channel, the JointTrajectoryController started in its controller manager,
and a listener keeping every frame on the channel."""
from __future__ import annotations

import itertools
import os
import threading
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional

import can
import yaml

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


def wait(condition: Callable[[], bool], timeout: float) -> bool:
    """Poll ``condition`` until it holds (True) or ``timeout`` s passed (False)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.01)
    return False


class Listener:
    """Every frame on the channel, with its arrival time (time.monotonic())."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self._marker_bus = can.Bus(interface="virtual", channel=channel)
        self._markers = itertools.count()
        self.frames: List[can.Message] = []
        self.arrivals: List[float] = []
        self._run = True
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while self._run:
            msg = self.bus.recv(timeout=0.05)
            if msg is not None:
                self.arrivals.append(time.monotonic())
                self.frames.append(msg)

    def take(self) -> List[can.Message]:
        frames, self.frames, self.arrivals = self.frames, [], []
        return frames

    def flush(self, timeout: float) -> bool:
        """Wait until every frame sent before this call is in ``frames``:
        a marker frame sent now is received after them (the virtual bus
        keeps each receiver's frames in order). False after ``timeout`` s."""
        data = next(self._markers).to_bytes(4, "little")
        self._marker_bus.send(can.Message(arbitration_id=MARKER, data=data, is_extended_id=False))
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if any(f.arbitration_id == MARKER and bytes(f.data) == data for f in reversed(self.frames)):
                return True
            time.sleep(0.005)
        return False

    def close(self) -> None:
        self._run = False
        self._thread.join(timeout=2)
        self.bus.shutdown()
        self._marker_bus.shutdown()


class CspRig:
    def __init__(self, adjust: Optional[Callable[[Dict[str, Any]], None]] = None,
                 cycle_hook: Optional[Callable[[JointTrajectoryController], None]] = None) -> None:
        """``adjust(params)`` may change the parameters before loading;
        ``cycle_hook(controller)`` runs after the controller's cycle each SYNC."""
        self.channel = "csp_rig_%d_%d" % (os.getpid(), next(_channels))
        self.simbus = can.Bus(interface="virtual", channel=self.channel)
        self.sim = Simulator(self.simbus, [NodeConfig(1, str(CONFIG / "epos4_node1.dcf")),
                                           NodeConfig(2, str(CONFIG / "epos4_node2.dcf"))], tick=0.002).start()
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
        self.driver = Driver(load_config(self.params, "csp_rig", lambda pkg: str(PKG)))
        self.listener = Listener(self.channel)
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
