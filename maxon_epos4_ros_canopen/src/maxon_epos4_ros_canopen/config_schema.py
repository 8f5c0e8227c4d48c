"""What the driver's configuration holds: the frozen dataclasses
``load_config`` (config.py) returns, ``ConfigError``, and the values some
options may take (modes, switching states, default units, PDO layouts, halt
modes).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Mapping, Optional, Tuple

from .cia402 import MODE_SHORT_NAMES
from .objects import ObjectKey
from .units import Expression

__all__ = [
    "ConfigError",
    "BusConfig",
    "SyncConfig",
    "RealtimeConfig",
    "HeartbeatConfig",
    "PublishConfig",
    "NodeConfig",
    "ControllerConfig",
    "DriverConfig",
    "SUPPORTED_DRIVE_MODES",
    "SWITCHING_STATES",
    "DEFAULT_UNITS",
    "PDO_LAYOUTS",
    "HALT_MODES",
    "SOCKETCAN_PLUGIN",
    "DEFAULT_SHUTDOWN_TIMEOUT",
]

# CiA 402 modes of operation this driver can switch to.
SUPPORTED_DRIVE_MODES = {int(m): short for m, short in MODE_SHORT_NAMES.items()}

# switching_state takes canopen_402's InternalState numbers. (The seed's
# comment "2 # (Operation_Enable)" is wrong about the name: in canopen_402
# 2 is Switch_On_Disabled and 5 is Operation_Enable.)
SWITCHING_STATES = {
    2: "switch_on_disabled",
    3: "ready_to_switch_on",
    4: "switched_on",
    5: "operation_enabled",
}

# canopen_motor_node's defaults: ROS units rad, rad/s against a drive in
# milli-degrees. Users of the seeds override all of them.
DEFAULT_UNITS = {
    "pos_to_device": "rint(rad2deg(pos)*1000)",
    "pos_from_device": "deg2rad(obj6064)/1000",
    "vel_to_device": "rint(rad2deg(vel)*1000)",
    "vel_from_device": "deg2rad(obj606C)/1000",
    "eff_to_device": "rint(eff)",
    "eff_from_device": "0",
}

# Node layer ``pdo_layout``: the DCF's own PDO mapping (default) or the
# driver's compact one (see driver/plan.py and docs/driver.md).
PDO_LAYOUTS = ("dcf", "compact")
# Node layer ``halt_mode``: what driver/halt does. ``quick_stop`` as
# ros_canopen's Motor402 (Operation Enabled -> Quick Stop Active: the drive
# ramps down on 0x6085, then acts on 0x605A); ``halt_bit``: controlword
# bit 8 in the profile modes and homing, the drive decelerates on its
# profile and stays Operation Enabled; the cyclic modes have no halt bit and
# stop with the drive's quick stop either way (driver/modes.py).
HALT_MODES = ("quick_stop", "halt_bit")

SOCKETCAN_PLUGIN = "can::SocketCANInterface"

# ``timeouts/shutdown`` (s): the driver's shutdown and close end within it.
# Long enough for a quick stop ramp and its confirmation over SDO, well
# short of roslaunch's 15 s between SIGINT and SIGTERM.
DEFAULT_SHUTDOWN_TIMEOUT = 5.0


class ConfigError(Exception):
    """A configuration mistake; the message names the key and the source."""

    def __init__(self, source: str, key: str, problem: str) -> None:
        self.source = source
        self.key = key
        self.problem = problem
        super().__init__("%s: %s: %s" % (source, key, problem))


@dataclass(frozen=True)
class BusConfig:
    device: str = "can0"
    loopback: bool = False
    driver_plugin: str = SOCKETCAN_PLUGIN
    master_allocator: str = "canopen::SimpleMaster::Allocator"
    bitrate: Optional[int] = None  # bit/s, for adapters opened with one (not SocketCAN)


@dataclass(frozen=True)
class SyncConfig:
    interval_ms: float = 0.0   # 0: no SYNC producer
    update_ms: float = 0.0     # period of the control cycle
    overflow: int = 0          # 0: SYNC without counter, else counter 1..overflow
    # SYNC from the kernel's broadcast manager (SocketCAN) with the cycle
    # paced between SYNCs, instead of the cycle sending each SYNC itself;
    # on other adapters (python-can's virtual bus) the cycle sends it anyway
    kernel_timer: bool = True


@dataclass(frozen=True)
class RealtimeConfig:
    """The cycle thread's scheduling (driver/realtime.py): SCHED_FIFO at
    ``priority`` where the process may, memory locked when asked."""
    enabled: bool = True
    priority: int = 50          # as ros2_control's controller manager thread
    lock_memory: bool = False


@dataclass(frozen=True)
class HeartbeatConfig:
    rate: float
    can_id: int
    data: bytes
    extended: bool = False
    msg: str = ""


@dataclass(frozen=True)
class PublishConfig:
    spec: str          # as written, e.g. "1003sub0!"
    key: ObjectKey
    force: bool        # "!": read from the device each time
    topic: str         # "<node name>_<object string>"


@dataclass(frozen=True)
class NodeConfig:
    key: str                      # the entry's key ("node1") or list position
    node_id: int
    name: str                     # joint name
    eds_file: str                 # resolved, absolute path
    eds_pkg: Optional[str]
    dcf_overlay: Tuple[Tuple[ObjectKey, str, str], ...]  # (key, value, key as written)
    switching_state: int
    pos_to_device: Expression
    pos_from_device: Expression
    vel_to_device: Expression
    vel_from_device: Expression
    eff_to_device: Expression
    eff_from_device: Expression
    publish: Tuple[PublishConfig, ...]
    motor_allocator: str = "canopen::Motor402::Allocator"
    extra: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))
    # "dcf": the DCF's PDO mapping; "compact": the driver's own, only what
    # ``modes`` need (driver/plan.py). modes: the node's ``modes`` key, else
    # the required_drive_mode of the controllers naming this joint.
    pdo_layout: str = "dcf"
    halt_mode: str = "quick_stop"
    modes: Tuple[int, ...] = ()
    # pdo_layout compact: the TxPDOs other than the statusword's and the
    # position's come every N-th SYNC (CiA 301 transmission type N)
    readings_every: int = 1


@dataclass(frozen=True)
class ControllerConfig:
    name: str
    type: str
    joints: Tuple[str, ...]
    publish_rate: Optional[float]
    required_drive_mode: Optional[int]
    constraints: Mapping[str, Any]
    params: Mapping[str, Any]     # everything else the controller may use
    group: bool                   # "joints:" list rather than "joint:"


@dataclass(frozen=True)
class DriverConfig:
    source: str
    bus: BusConfig
    sync: SyncConfig
    heartbeat: Optional[HeartbeatConfig]
    nodes: Tuple[NodeConfig, ...]
    joint_names: Tuple[str, ...]
    controllers: Tuple[ControllerConfig, ...]
    warnings: Tuple[str, ...]
    realtime: RealtimeConfig = RealtimeConfig()
    shutdown_timeout: float = DEFAULT_SHUTDOWN_TIMEOUT  # timeouts/shutdown

    def node(self, name_or_key: str) -> NodeConfig:
        for n in self.nodes:
            if name_or_key in (n.name, n.key):
                return n
        raise KeyError(name_or_key)

    def controller(self, name: str) -> ControllerConfig:
        for c in self.controllers:
            if c.name == name:
                return c
        raise KeyError(name)
