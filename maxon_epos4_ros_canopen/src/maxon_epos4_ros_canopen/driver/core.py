"""The CANopen master: ros_canopen's driver services on canopen + python-can.

``Driver`` is the facade; the work is split by concern, each part owning
its fields (cycle.py states the rule and who owns what):

* cycle.py: the control cycle, the axes it owns, its inbox and snapshots;
* lifecycle.py (with configure.py and stopping.py): init, recover, halt,
  shutdown and switch_mode;
* access.py: get/set_object and every SDO transfer (the guarded client);
* link.py: bus plumbing: NMT, reception, heartbeat and SYNC producers.
"""
from __future__ import annotations

import queue
import socket
from typing import Any, Callable, Dict, List, Mapping, Optional, Union

import can

from ..clock import Clock, as_clock
from ..config_schema import DriverConfig
from ..limits import JointLimits
from ..result import Result
from .access import ObjectAccess
from .snapshot import AxisSnapshot
from .cycle import ControlCycle, DriverSnapshot
from .lifecycle import Lifecycle
from .link import Link
from .nodes import NodeTable, Timeouts

__all__ = ["Driver", "DriverSnapshot", "joint_states_stamp"]

CycleCallback = Callable[["Driver"], None]

# Diagnostics keys of the axis counters: commands refused or saturated,
# EMCY lines not logged, and every other counter is a frame dropped as
# malformed or undefined (so a counter added later is never left out).
COMMAND_COUNTERS = frozenset({"refused_commands", "clipped_commands"})
EMCY_NOT_LOGGED = "emcy_not_logged"
TPDO_CONFLICTS = "tpdo_conflicts"  # a TPDO twice in one SYNC period: not dropped, shown on its own


def joint_states_stamp(joints: Mapping[str, AxisSnapshot]) -> Optional[float]:
    """The stamp of a joint_states message of these joints: when the newest
    TPDO their values came from arrived (wall clock, time.time()); None
    before any came."""
    return max((a.stamp for a in joints.values() if a.stamp), default=None)


def _listed(counters: Mapping[str, int], wanted: Callable[[str], bool]) -> str:
    return ", ".join("%s %d" % (n, v) for n, v in sorted(counters.items()) if v and wanted(n)) or "none"


class Driver:
    """ros_canopen's canopen_motor_node driver, minus ROS.

    ``Driver(config)`` loads every node's DCF/EDS and plans what init will
    write (raising ConfigError on any problem); nothing touches the bus
    until ``init()``. Pass ``bus`` to use an already open python-can bus
    (it is then not shut down by the driver).
    """

    def __init__(self, config: DriverConfig, bus: Optional[can.BusABC] = None, *,
                 boot_timeout: float = 5.0, state_timeout: float = 5.0,
                 homing_timeout: float = 60.0, sdo_timeout: float = 1.0, cycle_join_timeout: float = 5.0,
                 shutdown_timeout: Optional[float] = None, clock: Optional[Clock] = None,
                 pdo_bus: Union[can.BusABC, socket.socket, None] = None) -> None:
        """``clock``: every timer and wait of the driver (real time unless
        given: a test's stepped clock runs the driver on virtual time).
        ``shutdown_timeout``: the deadline of shutdown and close as a whole
        (the configuration's ``timeouts/shutdown`` unless given).
        ``pdo_bus``: with ``bus``, a bus that carries the drives' TxPDOs
        and SYNC (and may carry more), which the cycle reads itself
        (driver/cycle_reception.py), or a socket that carries them as
        SocketCAN frames (``struct can_frame``), read as on SocketCAN (made
        non-blocking; the caller closes it); without it a given bus's TxPDOs come
        through the notifier thread. A bus the driver opens itself gets
        its own on SocketCAN (and python-can's virtual bus in stepped
        runs)."""
        self.config = config
        self._timeouts = Timeouts(sdo=sdo_timeout, boot=boot_timeout, state=state_timeout, homing=homing_timeout,
                                  cycle_join=cycle_join_timeout,
                                  shutdown=config.shutdown_timeout if shutdown_timeout is None else shutdown_timeout)
        self._nodes = NodeTable(config)
        inbox: "queue.SimpleQueue[Any]" = queue.SimpleQueue()  # the cycle's; the link posts to it
        self._link = Link(config, self._nodes, self._timeouts, inbox.put, bus, as_clock(clock), pdo_bus)
        self._cycle = ControlCycle(self, self._nodes, self._link, self._timeouts, inbox)
        self._access = ObjectAccess(self._nodes, self._link, self._cycle, self._timeouts)
        self._lifecycle = Lifecycle(self._nodes, self._link, self._cycle, self._access, self._timeouts)

    # ========================================================== settings
    @property
    def sdo_timeout(self) -> float:
        return self._timeouts.sdo

    @sdo_timeout.setter
    def sdo_timeout(self, value: float) -> None:
        self._timeouts.sdo = value

    @property
    def boot_timeout(self) -> float:
        return self._timeouts.boot

    @boot_timeout.setter
    def boot_timeout(self, value: float) -> None:
        self._timeouts.boot = value

    @property
    def state_timeout(self) -> float:
        return self._timeouts.state

    @state_timeout.setter
    def state_timeout(self, value: float) -> None:
        self._timeouts.state = value

    @property
    def homing_timeout(self) -> float:
        return self._timeouts.homing

    @homing_timeout.setter
    def homing_timeout(self, value: float) -> None:
        self._timeouts.homing = value

    @property
    def cycle_join_timeout(self) -> float:
        return self._timeouts.cycle_join

    @cycle_join_timeout.setter
    def cycle_join_timeout(self, value: float) -> None:
        self._timeouts.cycle_join = value

    @property
    def shutdown_timeout(self) -> float:
        return self._timeouts.shutdown

    @shutdown_timeout.setter
    def shutdown_timeout(self, value: float) -> None:
        self._timeouts.shutdown = value

    # ============================================================ state
    @property
    def clock(self) -> Clock:
        return self._link.clock

    @property
    def initialized(self) -> bool:
        return self._lifecycle.initialized

    @property
    def bus(self) -> Optional[can.BusABC]:
        return self._link.bus

    @property
    def network(self) -> Any:
        return self._link.network

    @property
    def sync(self) -> Any:
        return self._link.sync

    @property
    def overruns(self) -> int:
        return self._cycle.overruns

    @property
    def realtime(self) -> Any:
        """The cycle thread's scheduling as it started (realtime.Outcome; None before)."""
        return self._cycle.realtime

    @property
    def bus_error(self) -> Optional[str]:
        return self._cycle.bus_error

    # ============================================================ lookup
    @property
    def joints(self) -> Mapping[str, AxisSnapshot]:
        """name -> the latest immutable snapshot of each joint."""
        return self._cycle.snapshot.axes

    @property
    def cycles(self) -> int:
        return self._cycle.snapshot.cycle

    def snapshot(self) -> DriverSnapshot:
        return self._cycle.snapshot

    def joint(self, name: str) -> Optional[AxisSnapshot]:
        """A joint's snapshot by its name (the node's ``name``) or its node key (``node1``)."""
        n = self._nodes.name(name)
        return None if n is None else self._cycle.snapshot.axes[n]

    def set_limits(self, name: str, limits: JointLimits) -> None:
        """Joint limits (ROS units) every command is saturated to."""
        n = self._nodes.name(name)
        if n is None:
            raise KeyError(name)
        self._cycle.set_limits(n, limits)

    def limits(self, name: str) -> JointLimits:
        return self._cycle.limits[self._nodes.name(name) or name]

    def add_cycle_callback(self, fn: CycleCallback) -> None:
        """fn(driver) runs every cycle in the cycle thread, after the readings
        are fresh (``driver.joints``) and before the RPDOs go out; its
        ``set_command`` calls take effect in the same cycle (CSP trajectories)."""
        self._cycle.callbacks = self._cycle.callbacks + (fn,)

    def remove_cycle_callback(self, fn: CycleCallback) -> None:
        self._cycle.callbacks = tuple(c for c in self._cycle.callbacks if c is not fn)

    # ========================================================== commands
    def set_command(self, name: str, kind: str, value: Any) -> Result:
        """A controller's command for a joint, in ROS units. Checked at once
        against the latest snapshot and again when the cycle applies it; the
        last command before a cycle wins. Saturated to the joint limits."""
        return self._cycle.set_command(name, kind, value)

    def cycle(self) -> None:
        """One control cycle (the cycle thread runs it every update_ms)."""
        self._cycle.cycle()

    # ========================================================= services
    def init(self) -> Result:
        """ros_canopen's init: reset, configure, start, home, enable."""
        return self._lifecycle.init()

    def switch_mode(self, joint_names: Any = None, mode: Any = None) -> Result:
        """Put joints into a mode of operation through their switching_state;
        targets hold the position read over SDO first, so nothing jumps.
        Before init, the mode is remembered and applied by init.
        ``joint_names``: a list of names (one name alone is taken too); any
        other argument is answered with a failed Result."""
        return self._lifecycle.switch_mode(joint_names, mode)

    def halt(self) -> Result:
        """Stop motion. Per node's ``halt_mode``: ``quick_stop`` (default, as
        ros_canopen) brings an enabled drive to Quick Stop Active, where it
        ramps down on its quick stop deceleration; ``halt_bit`` keeps it
        Operation Enabled and stops in place (halt bit in the profile modes,
        the last commanded target in CSP, zero in CSV/CST). Either way the
        joint takes no command until recover."""
        return self._lifecycle.halt()

    def recover(self) -> Result:
        """Fault reset and re-enable; targets hold the position read over SDO
        before enabling, so that nothing jumps to a stale target."""
        return self._lifecycle.recover()

    def shutdown(self) -> Result:
        """Quick stop and disable every drive, stop SYNC, NMT stop, within
        ``shutdown_timeout`` s (the answer names the steps it cut short)."""
        return self._lifecycle.shutdown()

    def close(self) -> None:
        """Leave the drives safe and release the bus (node exit) within
        ``shutdown_timeout`` s; never raises. A service still waiting (init
        homing...) is made to give up first; one that does not let go of
        the driver in time does not keep the drives from being stopped."""
        self._lifecycle.close()

    # ========================================================== objects
    def get_object(self, node_name: str, obj: str, cached: bool = False) -> Result:
        """ros_canopen's get_object; always answers."""
        return self._access.get_object(node_name, obj, cached)

    def set_object(self, node_name: str, obj: str, value: str, cached: bool = False) -> Result:
        """ros_canopen's set_object; always answers. Objects the driver owns
        are refused with the reason."""
        return self._access.set_object(node_name, obj, value, cached)

    # ==================================================== ROS layer/diag
    def published_types(self) -> Dict[str, int]:
        """topic -> CANopen data type of the ROS layer's published objects."""
        return self._access.published_types()

    def read_published(self) -> Dict[str, Any]:
        """topic -> value of every ``publish`` object: from its TPDO when
        mapped, else the cache, read by SDO when forced (``!``) or never read.
        Objects that cannot be read are left out (and logged)."""
        return self._access.read_published()

    def status(self) -> List[Dict[str, Any]]:
        """One dict per node for diagnostics."""
        snap = self._cycle.snapshot
        initialized = self.initialized
        # how long the latest frame read had waited unread: a loaded host
        link = self._link
        reception = link.reception
        lag = max(link.receive_clock.lag(), reception.lag() if reception is not None else 0.0)
        receive_lag_ms = int(round(max(0.0, lag) * 1000))
        # cycles that missed their SYNC period, since start (the host too slow)
        cycles_late = self._cycle.overruns
        out = []
        for a in snap.axes.values():
            out.append({
                "name": a.name, "node_id": a.node_id, "nmt_state": a.nmt_state,
                "state": a.state.value if a.state else "unknown",
                "statusword": "0x%04X" % a.statusword,
                "mode": a.mode_name(), "mode_display": a.mode_display,
                "last_emcy": a.last_emcy, "error_register": "0x%02X" % a.error_register,
                "error": a.error or "", "halted": a.halted, "initialized": initialized,
                "pdo_mapping": a.plan.source, "limits": a.limits.describe(),
                "last_refused_command": a.last_refusal,
                "frames_ignored": _listed(a.counters, lambda n: n not in COMMAND_COUNTERS
                                          and n not in (EMCY_NOT_LOGGED, TPDO_CONFLICTS)),
                "commands_limited": _listed(a.counters, COMMAND_COUNTERS.__contains__),
                "emcy_not_logged": a.counters.get(EMCY_NOT_LOGGED, 0),
                TPDO_CONFLICTS: a.counters.get(TPDO_CONFLICTS, 0),
                "foreign_rpdo_frames": snap.foreign_frames,
                "receive_lag_ms": receive_lag_ms,
                "cycles_late": cycles_late,
                "reading_age_ms": a.describe_ages(),
            })
        return out
