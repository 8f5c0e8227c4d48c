"""The CANopen master: ros_canopen's driver services on canopen + python-can.

Threads and who owns what (docs/driver.md has the picture):

* the cycle thread runs every ``sync/update_ms`` and owns the axes: at the
  top of each cycle it drains the inbox (commands, state requests from the
  services, heartbeats and EMCYs from the CAN notifier), reads the latest
  TPDO frames, publishes an immutable snapshot, runs the cycle callbacks
  (the trajectory controller), and sends the RxPDOs and SYNC;
* service calls (init, halt, recover, shutdown, switch_mode, get/set_object)
  run in their callers' threads, one state-changing service at a time; they
  talk to the drives over SDO and to the axes only through the inbox, and
  wait on snapshots;
* canopen's notifier thread only hands frames over: TPDOs to the receiver's
  latest-frame slots, everything else to the inbox.

While no cycle runs (before init, after shutdown) the service holding the
service lock owns the axes; starting the cycle thread hands them over and
joining it hands them back.
"""
from __future__ import annotations

import logging
import os
import queue
import random
import struct
import threading
import time
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from types import MappingProxyType
from typing import Any, Callable, Dict, Iterable, List, Mapping, NamedTuple, Optional, Sequence, Tuple

import can
import canopen
from canopen.sdo import SdoClient
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from .. import cia402
from ..cia402 import State
from .budget import check_budget
from ..can_device import max_receive_lag
from ..config import ConfigError, DriverConfig
from ..limits import JointLimits, saturate
from ..objects import (ObjectKey, ObjectStringError, ObjectValueError, decode_value, encode_value,
                       find_variable, is_readable, is_writable, parse_object_key)
from ..result import Result, fail, ok
from ..units import object_variable_name
from .axis import (SWITCHING_STATE, Axis, AxisSnapshot, Binding, Converter, command_problem, env_for_check,
                   holding_controlword, initial_snapshot)
from .bus import HeartbeatProducer, ReceiveClock, SyncProducer, is_socketcan, open_bus, unread_frames
from .modes import (CONTROLWORD, HOMING, MODES_DISPLAY, MODES_OF_OPERATION, POSITION_ACTUAL, STATUSWORD,
                    TARGET_POSITION, TARGET_TORQUE, TARGET_VELOCITY, VELOCITY_ACTUAL, mode_of, supported_modes_text)
from .pdo import PdoLayoutError, RxPdo, TpdoReceiver, TxPdo, enabled_maps
from .plan import (DRIVER_OWNED, HEARTBEAT_CONSUMER_1, HOMING_METHOD, MODE_TARGETS, PRODUCER_HEARTBEAT, RPDO_COMM, RPDO_MAP, TPDO_COMM, TPDO_MAP,
                   NodePlan, plan_node)
from .sdo import GuardedSdoClient, no_answer

log = logging.getLogger("maxon_epos4_ros_canopen.driver")

NMT_START, NMT_STOP, NMT_ENTER_PRE_OPERATIONAL, NMT_RESET_NODE = 0x01, 0x02, 0x80, 0x81
_PDO_MISSING_CYCLES = 50
QUICK_STOP_DECELERATION = ObjectKey(0x6085)
_STANDSTILL = 2  # |0x606C| at or below this is standing still
# Shutdown goes through the cycle for a drive whose statusword TxPDO came
# within this many cycles, over SDO for the others.
_HEARD_CYCLES = 20
_SDO_ATTEMPTS = 3  # tries of a transfer whose answer did not come
_SDO_FOREIGN_ANSWERS = 7  # more tries when the answer was another client's
_KERNEL_FILTER_MAX = 512  # CAN_RAW_FILTER_MAX of Linux
_PDO_NOT_VALID, _RTR_NOT_ALLOWED = 0x80000000, 0x40000000
# What init's enabling writes before the cycle starts, so the first RxPDOs
# hold the drive where it is: the targets (position: where it stands), and
# the controlword enable operation.
_HOLD_TARGETS = (TARGET_POSITION, TARGET_VELOCITY, TARGET_TORQUE)
_SET_BY_ENABLE = frozenset(_HOLD_TARGETS + (CONTROLWORD,))
# Nodes init configures at once: each has its own SDO client and lock, the
# bus interleaves their transfers.
_INIT_WORKERS = 32
# Controlwords init may write on the way to Operation Enabled: fault reset
# (two), shutdown, switch on, enable operation, and one fault on the way.
_ENABLE_STEPS = 8
_COMMAND_NAMES = {cia402.CW_DISABLE_VOLTAGE: "disable voltage", cia402.CW_QUICK_STOP: "quick stop",
                  cia402.CW_SHUTDOWN: "shutdown", cia402.CW_SWITCH_ON: "switch on",
                  cia402.CW_ENABLE_OPERATION: "enable operation", cia402.CW_FAULT_RESET: "fault reset"}
CycleCallback = Callable[["Driver"], None]
_get_ident = threading.get_ident
_monotonic = time.monotonic
_tuple_new = tuple.__new__

# Objects set_object refuses, and why: the driver configures or sends them
# itself, or writing them would act on the drive's memory.
_REFUSED_RANGES = (
    (0x1400, 0x1BFF, "a PDO communication or mapping parameter: the driver configures its PDOs itself"),
    (0x1010, 0x1011, "store/restore parameters: the driver does not write the drive's memory"),
    (0x1005, 0x1005, "the SYNC COB-ID: the driver's SYNC depends on it"),
    (0x1200, 0x12FF, "an SDO server parameter: the driver talks over it"),
)


class _InitError(Exception):
    pass


class _Timeout(Exception):
    """A drive did not show what init waited for (the text: what it shows)."""


# Diagnostics keys of the axis counters: commands refused or saturated,
# EMCY lines not logged, and every other counter is a frame dropped as
# malformed or undefined (so a counter added later is never left out).
COMMAND_COUNTERS = frozenset({"refused_commands", "clipped_commands"})
EMCY_NOT_LOGGED = "emcy_not_logged"


def _listed(counters: Mapping[str, int], wanted: Callable[[str], bool]) -> str:
    return ", ".join("%s %d" % (n, v) for n, v in sorted(counters.items()) if v and wanted(n)) or "none"


# ----------------------------------------------------------------- messages
@dataclass(frozen=True)
class _Command:
    axis: str
    kind: str
    value: float


@dataclass(frozen=True)
class _StateRequest:
    axes: Tuple[str, ...]
    state: Optional[State]
    fault_reset: bool = False


@dataclass(frozen=True)
class _StopInPlace:
    axes: Tuple[str, ...]


@dataclass(frozen=True)
class _Hold:
    axis: str
    raw_position: int


@dataclass(frozen=True)
class _SetMode:
    axis: str
    mode: int
    raw_position: int


@dataclass(frozen=True)
class _ModeConfirmed:
    axis: str
    mode: int


@dataclass(frozen=True)
class _Homing:
    axis: str
    on: bool


@dataclass(frozen=True)
class _Ready:
    axes: Tuple[str, ...]
    ready: bool


@dataclass(frozen=True)
class _ClearError:
    axis: str
    raw_position: int
    statusword: int


@dataclass(frozen=True)
class _Together:
    """Requests one cycle must take together: a state request with the
    error clearing it depends on, so that no cycle sees one without the
    other (a cleared error and no target state yet would judge the drive's
    state against the one held before the error)."""
    messages: Tuple[Any, ...]


@dataclass(frozen=True)
class _Detach:
    axis: str


@dataclass(frozen=True)
class _Attach:
    axis: str
    binding: Binding


@dataclass(frozen=True)
class _SetOutput:
    axis: str
    key: ObjectKey
    value: int


@dataclass(frozen=True)
class _SetHeartbeat:
    axis: str
    ms: int


@dataclass(frozen=True)
class _SetLimits:
    axis: str
    limits: JointLimits


@dataclass(frozen=True)
class _Heartbeat:
    node_id: int
    data: bytes
    time: float


@dataclass(frozen=True)
class _Emcy:
    node_id: int
    data: bytes
    time: float


class _ReceiveErrors(can.Listener):
    """Handles the CAN notifier's receive errors: logged (at most once a
    second) and waited out, so its reader thread keeps running.

    The notifier keeps the error as its ``exception``, and canopen's Network
    raises that again on every later send (SDO requests included): cleared
    here, or an interface that was down once would fail every SDO for good."""

    def __init__(self, notifier: can.Notifier) -> None:
        self._notifier = notifier
        self._logged = 0.0

    def on_message_received(self, msg: can.Message) -> None:
        pass

    def on_error(self, exc: Exception) -> None:
        self._notifier.exception = None
        now = time.monotonic()
        if now - self._logged > 1.0:
            self._logged = now
            log.error("CAN receive error: %s", exc)
        time.sleep(0.1)  # a downed interface fails every read at once


class DriverSnapshot(NamedTuple):
    """Everything the other threads may know of the axes, as of one cycle."""
    cycle: int
    axes: Mapping[str, AxisSnapshot]
    bus_error: Optional[str]
    foreign_frames: int


class _Node(NamedTuple):
    """What the driver knows of a node before any frame: immutable."""
    cfg: Any
    od: Any
    plan: NodePlan
    converter: Converter   # commands to device units (immutable)


class Driver:
    """ros_canopen's canopen_motor_node driver, minus ROS.

    ``Driver(config)`` loads every node's DCF/EDS and plans what init will
    write (raising ConfigError on any problem); nothing touches the bus
    until ``init()``. Pass ``bus`` to use an already open python-can bus
    (it is then not shut down by the driver).
    """

    def __init__(self, config: DriverConfig, bus: Optional[can.BusABC] = None, *,
                 boot_timeout: float = 5.0, state_timeout: float = 5.0,
                 homing_timeout: float = 60.0, sdo_timeout: float = 1.0) -> None:
        self.config = config
        # An EPOS4 answers an SDO within a millisecond; the generous timeout
        # is for loaded hosts (and user-mode Linux), it only delays the
        # error about a node that is really gone.
        self.sdo_timeout = sdo_timeout
        self.boot_timeout = boot_timeout
        self.state_timeout = state_timeout
        self.homing_timeout = homing_timeout
        self._external_bus = bus
        self._nodes: "OrderedDict[str, _Node]" = OrderedDict()
        # Planning reads the DCF's values, which depend on the node-ID
        # ($NODEID). After it only the objects' types and sizes are used,
        # the same for every node of one file: those nodes share the first
        # one's dictionary (about 160 kB each for an EPOS4 DCF).
        shared_ods: Dict[str, canopen.ObjectDictionary] = {}
        for n in config.nodes:
            try:
                od = canopen.import_od(n.eds_file, n.node_id)
            except Exception as e:  # canopen raises many kinds on a bad file
                raise ConfigError(config.source, "nodes/%s/eds_file" % n.key,
                                  "cannot read %s: %s" % (n.eds_file, e)) from None
            plan = plan_node(n, od, config.sync, config.source, config.heartbeat)
            try:
                for m in enabled_maps(plan.rx):
                    RxPdo(od, m)
                for m in enabled_maps(plan.tx):
                    TxPdo(od, m)
            except PdoLayoutError as e:
                raise ConfigError(config.source, "nodes/%s/eds_file" % n.key, str(e)) from None
            od = shared_ods.setdefault(os.path.realpath(n.eds_file), od)
            self._nodes[n.name] = _Node(n, od, plan, Converter(n, od))
        self._by_key = {node.cfg.key: name for name, node in self._nodes.items()}
        self._limits: Mapping[str, JointLimits] = MappingProxyType({name: JointLimits() for name in self._nodes})
        self._period = config.sync.update_ms / 1000.0
        # TxPDOs come every SYNC (or event period): 50 of them missing, and
        # at least 1.5 s, is an error.
        self._pdo_timeout = max(1.5, _PDO_MISSING_CYCLES * max(config.sync.interval_ms, config.sync.update_ms) / 1000.0)
        self._snapshot = DriverSnapshot(0, MappingProxyType(
            {name: initial_snapshot(node.cfg, node.plan, JointLimits()) for name, node in self._nodes.items()}),
            None, 0)
        self._inbox: "queue.SimpleQueue[Any]" = queue.SimpleQueue()
        self._cond = threading.Condition()
        self._waiters = 0  # threads in _wait (under _cond): the cycle notifies only when there are some
        self._service = threading.Lock()
        self._sdo_locks = {name: threading.Lock() for name in self._nodes}
        self._cache: Dict[str, Dict[ObjectKey, Any]] = {name: {} for name in self._nodes}  # under the SDO lock
        self._callbacks: Tuple[CycleCallback, ...] = ()
        self._requested_modes: Dict[str, Optional[int]] = {name: None for name in self._nodes}
        self._initial_env: Dict[str, Mapping[str, float]] = {name: {} for name in self._nodes}
        self.initialized = False
        self.bus: Optional[can.BusABC] = None
        self.network: Optional[canopen.Network] = None
        self._sdo: Mapping[str, GuardedSdoClient] = MappingProxyType({})
        self._receiver: Optional[TpdoReceiver] = None
        self._boot: Dict[int, threading.Event] = {}
        self.sync: Optional[SyncProducer] = None
        self._sync_paced = False     # SYNC from the kernel, the cycle paced between SYNCs
        self._sync_in_cycle = False  # SYNC sent by the cycle
        self._heartbeat: Optional[HeartbeatProducer] = None
        self._thread: Optional[threading.Thread] = None
        self._cycle_ident: Optional[int] = None
        self._stop = threading.Event()
        self._abort = threading.Event()  # close(): cut service waits short
        # owned by the cycle thread while it runs
        self._axes: List[Axis] = []
        self._axis: Dict[str, Axis] = {}
        self._by_node_id: Dict[int, Axis] = {}
        self._cycle_no = 0
        self.overruns = 0
        self.bus_error: Optional[str] = None
        self._send_failures = 0
        self._out_frames: Dict[int, can.Message] = {}  # COB-ID -> the message _send reuses (cycle thread)
        self._foreign_frames = [0]  # written by the notifier thread only
        self._receive_clock = ReceiveClock()  # written by the notifier thread only

    # ============================================================ lookup
    @property
    def joints(self) -> Mapping[str, AxisSnapshot]:
        """name -> the latest immutable snapshot of each joint."""
        return self._snapshot.axes

    @property
    def cycles(self) -> int:
        return self._snapshot.cycle

    def snapshot(self) -> DriverSnapshot:
        return self._snapshot

    def _name(self, name: str) -> Optional[str]:
        if name in self._nodes:
            return name
        return self._by_key.get(name) if isinstance(name, str) else None

    def joint(self, name: str) -> Optional[AxisSnapshot]:
        """A joint's snapshot by its name (the node's ``name``) or its node key (``node1``)."""
        n = self._name(name)
        return None if n is None else self._snapshot.axes[n]

    def _unknown(self, name: Any) -> Result:
        return fail("unknown node %r (known: %s)" % (name, ", ".join(self._nodes)))

    def set_limits(self, name: str, limits: JointLimits) -> None:
        """Joint limits (ROS units) every command is saturated to."""
        n = self._name(name)
        if n is None:
            raise KeyError(name)
        new = dict(self._limits)
        new[n] = limits
        self._limits = MappingProxyType(new)
        self._post(_SetLimits(n, limits))

    def limits(self, name: str) -> JointLimits:
        return self._limits[self._name(name) or name]

    def add_cycle_callback(self, fn: CycleCallback) -> None:
        """fn(driver) runs every cycle in the cycle thread, after the readings
        are fresh (``driver.joints``) and before the RPDOs go out; its
        ``set_command`` calls take effect in the same cycle (CSP trajectories)."""
        self._callbacks = self._callbacks + (fn,)

    def remove_cycle_callback(self, fn: CycleCallback) -> None:
        self._callbacks = tuple(c for c in self._callbacks if c is not fn)

    # ========================================================== commands
    def set_command(self, name: str, kind: str, value: Any) -> Result:
        """A controller's command for a joint, in ROS units. Checked at once
        against the latest snapshot and again when the cycle applies it; the
        last command before a cycle wins. Saturated to the joint limits."""
        if _get_ident() == self._cycle_ident:
            # a cycle callback (the trajectory controller), every cycle for
            # every joint: the axis by its name first, the lookups after
            axis = self._axis.get(name)
            if axis is not None:
                return axis.apply_command(kind, value)
        n = self._name(name)
        if n is None:
            return self._unknown(name)
        if _get_ident() == self._cycle_ident:
            axis = self._axis.get(n)
            if axis is None:
                return fail("%s is not initialized: call init" % n)
            return axis.apply_command(kind, value)
        snap = self._snapshot.axes[n]
        problem = command_problem(snap, kind, value)
        if problem:
            return fail(problem)
        limits = self._limits[n]
        clipped_value, clipped = saturate(limits, kind, float(value))
        _, err = self._nodes[n].converter.convert(kind, clipped_value, env_for_check(snap, self._initial_env[n]))
        if err:
            return fail(err)
        self._inbox.put(_Command(n, kind, float(value)))
        if clipped:
            return ok("clipped to the joint limits (%s)" % limits.describe())
        return ok()

    # ============================================================ inbox
    def _post(self, *messages: Any) -> int:
        """Send messages to the cycle; returns the cycle number after which
        a snapshot shows their effect (see _wait)."""
        seq = self._cycle_no
        for m in messages:
            self._inbox.put(m)
        return seq

    def _drain(self) -> None:
        batch = []
        inbox = self._inbox
        while True:
            try:
                batch.append(inbox.get_nowait())
            except queue.Empty:
                break
        if not batch:
            return
        # The last command of a joint in this batch is the one that counts;
        # everything else is handled in the order it came.
        last_command: Dict[str, int] = {}
        for i, m in enumerate(batch):
            if type(m) is _Command:
                last_command[m.axis] = i
        for i, m in enumerate(batch):
            try:
                if type(m) is _Command:
                    if last_command[m.axis] == i:
                        axis = self._axis.get(m.axis)
                        if axis is not None:
                            axis.apply_command(m.kind, m.value)
                    continue
                self._handle(m)
            except Exception:
                log.exception("driver: handling %r failed", m)

    def _handle(self, m: Any) -> None:
        kind = type(m)
        if kind is _Heartbeat:
            axis = self._by_node_id.get(m.node_id)
            if axis is not None:
                axis.on_heartbeat(m.data, m.time)
        elif kind is _Emcy:
            axis = self._by_node_id.get(m.node_id)
            if axis is not None:
                axis.on_emcy(m.data, m.time)
        elif kind is _StateRequest:
            for name in m.axes:
                self._axis[name].request_state(m.state, m.fault_reset)
        elif kind is _StopInPlace:
            for name in m.axes:
                self._axis[name].stop_in_place()
        elif kind is _Hold:
            self._axis[m.axis].hold(m.raw_position)
        elif kind is _SetMode:
            self._axis[m.axis].set_mode(m.mode, m.raw_position)
        elif kind is _ModeConfirmed:
            self._axis[m.axis].mode_confirmed(m.mode)
        elif kind is _Homing:
            self._axis[m.axis].homing = m.on
        elif kind is _Ready:
            for name in m.axes:
                self._axis[name].ready = m.ready
        elif kind is _ClearError:
            axis = self._axis[m.axis]
            axis.clear_error(m.statusword)
            # the watchdogs start afresh: silence from before recover (a bus
            # that was down) is not news; silence after it trips them again
            axis.last_heartbeat = axis.status_seen = time.monotonic()
            axis.hold(m.raw_position)
        elif kind is _Together:
            for part in m.messages:
                self._handle(part)
        elif kind is _Detach:
            self._axis[m.axis].detach()
        elif kind is _Attach:
            self._axis[m.axis].attach(m.binding, self._cycle_no, time.monotonic())
        elif kind is _SetOutput:
            self._axis[m.axis].set_output(m.key, m.value)
        elif kind is _SetHeartbeat:
            axis = self._axis[m.axis]
            axis.heartbeat_ms = m.ms
            axis.last_heartbeat = time.monotonic()
        elif kind is _SetLimits:
            axis = self._axis.get(m.axis)
            if axis is not None:
                axis.limits = m.limits

    # ====================================================== bus plumbing
    def _open(self) -> None:
        if self._external_bus is not None:
            self.bus = self._external_bus
        else:
            try:
                self.bus = open_bus(self.config.bus)
            except Exception as e:  # OSError, CanError, ValueError from python-can
                raise _InitError("cannot open CAN device %r: %s" % (self.config.bus.device, e)) from None
        network = canopen.Network(self.bus)
        # first, so that every subscriber takes its frame's times from it
        self._receive_clock = clock = ReceiveClock(unread_frames(self.bus), max_receive_lag(self.bus))
        network.listeners.insert(0, clock)
        network.connect()
        # python-can's notifier ends its reader thread on the first receive
        # error (an interface going down) unless a listener handles it; this
        # one does, so reception resumes when the interface is up again.
        network.notifier.add_listener(_ReceiveErrors(network.notifier))
        self.network = network
        self._receiver = receiver = TpdoReceiver({m.cob_id: m.length for node in self._nodes.values()
                                                  for m in enabled_maps(node.plan.tx)}, clock.times)
        for cob in receiver.cob_ids:
            network.subscribe(cob, receiver.on_frame)
        if not self.config.bus.loopback:
            # With loopback off the driver never hears its own frames: one on
            # its RxPDO COB-IDs comes from another master. It is counted and
            # otherwise ignored.
            for node in self._nodes.values():
                for m in enabled_maps(node.plan.rx):
                    network.subscribe(m.cob_id, self._on_foreign_frame)
        sdo = {}
        inbox = self._inbox
        for name, node in self._nodes.items():
            nid = node.cfg.node_id
            client = GuardedSdoClient(0x600 + nid, 0x580 + nid, node.od, clock)
            client.network = network
            client.RESPONSE_TIMEOUT = self.sdo_timeout
            network.subscribe(0x580 + nid, client.on_response)
            sdo[name] = client
            boot = self._boot.setdefault(nid, threading.Event())

            def on_heartbeat(can_id: int, data: Any, _ts: float, boot: threading.Event = boot) -> None:
                payload = bytes(data)
                if payload == b"\x00":
                    boot.set()
                # stamped with when it arrived, not when this thread got to it
                inbox.put(_Heartbeat(can_id - 0x700, payload, clock.progress[1]))

            def on_emcy(can_id: int, data: Any, _ts: float) -> None:
                inbox.put(_Emcy(can_id - 0x80, bytes(data), time.monotonic()))
            network.subscribe(0x700 + nid, on_heartbeat)
            network.subscribe(0x80 + nid, on_emcy)
        self._sdo = MappingProxyType(sdo)
        self._filter_in_kernel(network)
        if self.config.heartbeat is not None:
            self._heartbeat = HeartbeatProducer(self.bus, self.config.heartbeat)
            self._heartbeat.start()

    def _filter_in_kernel(self, network: canopen.Network) -> None:
        """On a SocketCAN bus of its own, the driver has the kernel drop
        every frame nobody here subscribed to: a busy or hostile bus then
        costs the notifier thread (and through the GIL the cycle) nothing
        for frames the driver ignores anyway."""
        ids = sorted(network.subscribers)
        if self._external_bus is not None or not is_socketcan(self.bus) or len(ids) > _KERNEL_FILTER_MAX:
            return
        try:
            self.bus.set_filters([{"can_id": i, "can_mask": 0x7FF, "extended": False} for i in ids])
        except (OSError, can.CanError) as e:
            log.warning("CAN receive filters not set (%s): every frame reaches the driver", e)

    def _on_foreign_frame(self, _can_id: int, _data: Any, _ts: float) -> None:
        self._foreign_frames[0] += 1

    def _close(self) -> None:
        for what, fn in (("heartbeat producer", self._stop_heartbeat), ("CAN network", self._close_network)):
            try:
                fn()
            except Exception as e:  # closing must go on whatever a part says
                log.warning("closing the %s: %s", what, e)

    def _stop_heartbeat(self) -> None:
        if self._heartbeat is not None:
            heartbeat, self._heartbeat = self._heartbeat, None
            heartbeat.stop()

    def _close_network(self) -> None:
        network, self.network = self.network, None
        self._sdo = MappingProxyType({})
        if network is not None and network.notifier is not None:
            # the notifier's reader wakes every NOTIFIER_CYCLE: wait longer
            # than that, or shutting the bus below it pulls its socket away
            # mid-read ("Bad file descriptor")
            network.notifier.stop(network.NOTIFIER_CYCLE + 1.0)
        bus, self.bus = self.bus, None
        if bus is not None and self._external_bus is None:
            bus.shutdown()

    def _send(self, cob_id: int, data: bytes) -> None:
        """An RxPDO from the cycle thread (the only caller). One can.Message
        per COB-ID is reused, its bytes overwritten, as SyncProducer does:
        python-can's send turns the message into a frame before it returns
        (the virtual bus copies it), and building a Message per frame was a
        large part of the cycle."""
        msg = self._out_frames.get(cob_id)
        if msg is None or len(msg.data) != len(data):
            msg = self._out_frames[cob_id] = can.Message(arbitration_id=cob_id, data=data, is_extended_id=False)
        else:
            msg.data[:] = data
        try:
            self.bus.send(msg)
        except (can.CanError, OSError) as e:
            self._send_error = e

    def _nmt(self, command: int, node_id: int) -> None:
        # Raw NMT frames: canopen's NmtMaster looks its state up in a table
        # and raises on a state byte CiA 301 does not define.
        self.network.send_message(0, bytes([command, node_id]))

    # ============================================================= cycle
    def _start_cycle(self, axes: List[Axis]) -> None:
        sync = self.config.sync
        if sync.interval_ms > 0:
            # When SYNC and cycle share a period the cycle sends each SYNC
            # right after its RxPDOs, so every SYNC carries fresh targets.
            # With sync/kernel_timer the kernel's broadcast manager sends
            # SYNC (SocketCAN; no scheduling delay of this process moves a
            # SYNC) and the cycle is paced between two SYNCs (see _run): its
            # RxPDOs only have to land before the next one. Without a kernel
            # timer (python-can's virtual bus, no can-bcm) the cycle sends
            # SYNC itself: a second thread would only add its own jitter.
            self.sync = SyncProducer(self.bus, sync.overflow)
            self._start_sync()
        self._axes = axes
        self._axis = {a.name: a for a in axes}
        self._by_node_id = {a.node_id: a for a in axes}
        # What a previous session left in the inbox (a request its cycle
        # never took, heartbeats from the configuration) must not act on
        # this one; joint limits are the axes' already.
        while True:
            try:
                self._inbox.get_nowait()
            except queue.Empty:
                break
        for axis in axes:
            axis.limits = self._limits[axis.name]
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="epos4_driver_cycle", daemon=True)
        self._thread.start()

    def _start_sync(self) -> None:
        sync, producer = self.config.sync, self.sync
        same_period = sync.interval_ms == sync.update_ms
        if same_period and not sync.kernel_timer:
            producer.stop()
            self._sync_paced, self._sync_in_cycle = False, True
            return
        producer.start(sync.interval_ms / 1000.0)
        self._sync_paced = same_period and producer.kernel_timed
        self._sync_in_cycle = same_period and not producer.kernel_timed
        if self._sync_in_cycle:
            producer.stop()

    def _stop_cycle(self) -> None:
        self._stop.set()
        thread = self._thread
        if thread is not None:
            thread.join(timeout=5.0)
            if thread.is_alive():
                log.error("driver cycle thread did not stop within 5 s")
            self._thread = None
        self._cycle_ident = None
        if self.sync is not None:
            try:
                self.sync.stop()
            except Exception as e:
                log.warning("stopping SYNC: %s", e)
            self.sync = None
        self._sync_paced = self._sync_in_cycle = False
        with self._cond:
            self._cond.notify_all()

    def _run(self) -> None:
        self._cycle_ident = threading.get_ident()
        period = self._period
        next_t = time.monotonic()
        while not self._stop.is_set():
            self.cycle()
            now = time.monotonic()
            sync = self.sync
            if self._sync_paced and sync is not None and sync.period:
                # a quarter period after the next SYNC: the drives' TPDOs
                # answering it are in, and the RxPDOs have time to land
                due = sync.next_after(now) + 0.25 * sync.period
                if due - next_t > 1.5 * period:
                    self.overruns += int((due - next_t) / period - 0.5)
                next_t = due
            else:
                next_t += period
                if next_t < now:
                    self.overruns += 1
                    next_t = now
            self._stop.wait(max(0.0, next_t - time.monotonic()))

    def cycle(self) -> None:
        """One control cycle: inbox, readings, snapshot, callbacks, RPDOs and
        SYNC. Never raises: a failing part is logged and the rest runs."""
        self._cycle_no = cycle_no = self._cycle_no + 1
        now = _monotonic()
        self._send_error = None
        if not self._inbox.empty():  # the usual cycle has no message: no get/Empty round
            try:
                self._drain()
            except Exception:
                log.exception("driver inbox failed")
        receiver = self._receiver
        period, pdo_timeout = self._period, self._pdo_timeout
        reception = self._receive_clock.progress
        snaps = {}
        for axis in self._axes:
            try:
                if axis.attached:
                    axis.read(receiver, now, cycle_no)
                    axis.watch(now, cycle_no, period, pdo_timeout, _PDO_MISSING_CYCLES, reception)
            except Exception:
                log.exception("%s: reading failed", axis.name)
            snaps[axis.name] = axis.snapshot()
        self._snapshot = _tuple_new(DriverSnapshot, (cycle_no, MappingProxyType(snaps), self.bus_error,
                                                     self._foreign_frames[0]))
        for fn in self._callbacks:
            try:
                fn(self)
            except Exception:
                log.exception("cycle callback %r failed", fn)
        send = self._send
        for axis in self._axes:
            try:
                if axis.attached:
                    axis.write(send)
            except Exception:
                log.exception("%s: writing failed", axis.name)
        if self._sync_in_cycle and self.sync is not None:
            try:
                self.sync.send()
            except (can.CanError, OSError) as e:
                self._send_error = e
        if self._send_error is None:  # _watch_bus's usual answer, without the call
            self._send_failures = 0
        else:
            self._watch_bus()
        # _wait counts itself in before it looks at the snapshot, so a
        # waiter that is not counted yet will see this cycle's snapshot.
        if self._waiters:
            with self._cond:
                self._cond.notify_all()

    def _watch_bus(self) -> None:
        e = self._send_error
        if e is None:
            self._send_failures = 0
            return
        self._send_failures += 1
        if self._send_failures == 10:
            self.bus_error = str(e)
            log.error("CAN bus error in 10 cycles in a row: %s", e)
            for axis in self._axes:
                axis.set_error("bus error: %s" % e, sight_lost=True)

    # ============================================================= waits
    def _wait(self, pred: Callable[[DriverSnapshot], bool], timeout: float, after: int = -1) -> bool:
        """Wait until a snapshot newer than cycle ``after`` satisfies pred."""
        deadline = time.monotonic() + timeout

        def done() -> bool:
            snap = self._snapshot
            return snap.cycle > after and pred(snap)
        with self._cond:
            self._waiters += 1
            try:
                while not done():
                    remaining = deadline - time.monotonic()
                    if remaining <= 0 or self._thread is None or self._abort.is_set():
                        return done()
                    self._cond.wait(min(remaining, 0.5))
            finally:
                self._waiters -= 1
        return True

    def _wait_cycles(self, n: int) -> None:
        target = self._cycle_no + n
        self._wait(lambda s: s.cycle >= target, max(1.0, n * self.config.sync.update_ms / 100.0))

    def _go(self, names: Sequence[str], state: State, fault_reset: bool = False,
            timeout: Optional[float] = None, stop_on_error: bool = True,
            together: Sequence[Any] = (), unheard_cycles: Optional[int] = None) -> Optional[str]:
        """Drive joints to a CiA 402 state through the cycle; an error text or
        None. ``together``: requests the cycle takes in the same breath.
        ``unheard_cycles``: stop waiting for a drive whose statusword TxPDO
        has not come for that many cycles."""
        names = tuple(names)
        if not names:
            return None
        after = self._post(_Together(tuple(together) + (_StateRequest(names, state, fault_reset),)))

        def there(a: AxisSnapshot) -> bool:
            # on a statusword that came after the request, not a stale one
            return a.held_state == state and a.target_state is None and a.state == state and a.status_cycle > after

        def unheard(s: DriverSnapshot, a: AxisSnapshot) -> bool:
            return unheard_cycles is not None and s.cycle - max(a.status_cycle, after) > unheard_cycles

        def settled(s: DriverSnapshot) -> bool:
            return all(there(s.axes[n]) or (stop_on_error and s.axes[n].error) or unheard(s, s.axes[n])
                       for n in names)
        reached = self._wait(settled, timeout or self.state_timeout, after)
        snap = self._snapshot
        problems = []
        for n in names:
            a = snap.axes[n]
            if there(a):
                continue
            if a.error and stop_on_error:
                return "%s: %s" % (n, a.error)
            problems.append("%s did not reach %s (state %s, statusword 0x%04X%s)" % (
                n, state.value, a.state.value if a.state else "unknown", a.statusword,
                ", last EMCY " + a.last_emcy if a.last_emcy else ""))
        if problems:
            return "; ".join(problems)
        return None if reached else "timeout waiting for %s" % state.value

    # =============================================================== SDO
    def _upload(self, name: str, key: ObjectKey) -> Any:
        var = find_variable(self._nodes[name].od, key)
        return var.decode_raw(self._sdo_transfer(name, lambda sdo: sdo.upload(key.index, key.subindex)))

    def _download(self, name: str, index: int, sub: int, data: bytes) -> None:
        self._sdo_transfer(name, lambda sdo: sdo.download(index, sub, data))

    def _sdo_transfer(self, name: str, transfer: Callable[[SdoClient], Any]) -> Any:
        """One SDO transfer, tried again when its answer was not the one asked
        for (another client on the same SDO channel, a user's tool or a test
        probe, or a stray frame can take an answer) or did not come in time
        (a loaded host). Every transfer the driver makes may be repeated:
        reads, and writes of a value. An abort is final. Each attempt waits
        longer than the one before (1, 2, 3 × sdo_timeout): a drive whose
        answer came late once, on a host that stalled, gets the time, and
        the late answer to the same request still counts.
        An answer for another object means another client is busy on the
        same channel: the next try comes after a short random pause, so two
        clients polling the drive do not meet again at once."""
        with self._sdo_locks[name]:
            client = self._sdo[name]
            tally = client.tally()
            late = 0
            try:
                for attempt in range(_SDO_ATTEMPTS + _SDO_FOREIGN_ANSWERS):
                    client.RESPONSE_TIMEOUT = self.sdo_timeout * (late + 1)
                    try:
                        return transfer(client)
                    except (SdoCommunicationError, struct.error) as e:
                        # apart from a missing answer (sdo.no_answer), every
                        # communication error is an answer that was not this request's (another
                        # client's, "Node returned a value for ... instead",
                        # "Unexpected response"), whatever its wording, and
                        # so is an answer shorter than 8 bytes, which canopen
                        # fails to unpack (a forged or corrupt frame)
                        foreign = not no_answer(e)
                        late += 0 if foreign else 1
                        if late == _SDO_ATTEMPTS or attempt + 1 == _SDO_ATTEMPTS + _SDO_FOREIGN_ANSWERS:
                            if isinstance(e, struct.error):
                                raise SdoCommunicationError("malformed SDO answer (%s)" % e) from e
                            if foreign:
                                raise
                            # what came, and why it was no answer, tells the
                            # drive's silence from this host's trouble
                            raise SdoCommunicationError("%s; %s" % (e, client.since(tally))) from e
                        log.warning("%s: SDO transfer disturbed (%s%s): trying again",
                                    name, e, "" if foreign else "; " + client.since(tally))
                        if foreign:
                            time.sleep(random.uniform(0.005, 0.05))
            finally:
                client.RESPONSE_TIMEOUT = self.sdo_timeout

    def _write_u32(self, name: str, index: int, sub: int, value: int) -> None:
        self._download(name, index, sub, value.to_bytes(4, "little"))

    def _write_u8(self, name: str, index: int, sub: int, value: int) -> None:
        self._download(name, index, sub, bytes([value]))

    def _position(self, name: str) -> int:
        """0x6064 read over SDO: a position the driver can vouch for (an
        answer to its own request), unlike a TPDO anyone could have sent."""
        return int(self._upload(name, POSITION_ACTUAL))

    # ============================================================== init
    def _configure(self, name: str, reset: bool = True, hold: bool = True) -> Binding:
        """NMT reset (init) or enter pre-operational (recover: a reset would
        lose the drive's position counter), then everything the plan says,
        over SDO. ``hold``: see ``_read_initial`` (init's ``_enable`` sets
        what it leaves out)."""
        node = self._nodes[name]
        nid = node.cfg.node_id
        if reset:
            boot = self._boot[nid]
            boot.clear()
            self._nmt(NMT_RESET_NODE, nid)
            if not boot.wait(self.boot_timeout):
                raise _InitError("%s (node %d): no boot-up within %g s after NMT reset"
                                 % (name, nid, self.boot_timeout))
        else:
            self._nmt(NMT_ENTER_PRE_OPERATIONAL, nid)
        step = "configuration"
        try:
            for w in node.plan.writes:
                step = "writing " + w.text
                self._download(name, w.key.index, w.key.subindex, w.data)
            step = "writing the PDO mapping"
            self._write_pdos(name)
            step = "reading the initial values"
            return self._read_initial(name, hold)
        except SdoAbortedError as e:
            raise _InitError("%s (node %d): %s failed: %s" % (name, nid, step, e)) from None
        except SdoCommunicationError as e:
            raise _InitError("%s (node %d): no SDO answer during configuration (%s): %s"
                             % (name, nid, step, e)) from None

    def _write_pdos(self, name: str) -> None:
        """The plan's PDO configuration, in CiA 301's order: invalidate, clear
        the mapping, write it, count, transmission type, validate; a PDO the
        plan leaves off is only invalidated. (canopen's
        Map.save does the same but also subscribes the map to its COB-ID,
        which the driver must not do for RxPDOs.)"""
        plan = self._nodes[name].plan
        for maps, comm_base, map_base, rx in ((plan.rx, RPDO_COMM, RPDO_MAP, True),
                                              (plan.tx, TPDO_COMM, TPDO_MAP, False)):
            for mp in maps:
                comm, mapping = comm_base + mp.number - 1, map_base + mp.number - 1
                rtr = 0 if rx or mp.rtr_allowed else _RTR_NOT_ALLOWED
                self._write_u32(name, comm, 1, mp.cob_id | _PDO_NOT_VALID | rtr)
                if not (mp.enabled and mp.entries):
                    # a PDO left invalid is neither sent nor received: its
                    # mapping and timing would be transfers for nothing
                    continue
                self._write_u8(name, mapping, 0, 0)
                for sub, (key, bits) in enumerate(mp.entries, start=1):
                    self._write_u32(name, mapping, sub, key.index << 16 | key.subindex << 8 | bits)
                self._write_u8(name, mapping, 0, len(mp.entries))
                self._write_u8(name, comm, 2, mp.trans_type)
                if mp.event_timer is not None:
                    self._download(name, comm, 5, int(mp.event_timer).to_bytes(2, "little"))
                self._write_u32(name, comm, 1, mp.cob_id | rtr)

    def _known(self, name: str, key: ObjectKey) -> Any:
        """``key``'s value in the drive: what this configuration has just
        written to it (a drive holds a value it accepted: reading it back
        would be one more transfer on a bus all drives share), else read."""
        data = self._nodes[name].plan.written.get(key)
        if data is None:
            return self._upload(name, key)
        return find_variable(self._nodes[name].od, key).decode_raw(data)

    def _read_initial(self, name: str, hold: bool = True) -> Binding:
        """Codecs and first values: every RPDO value the drive has (known or
        read), so the first RPDOs repeat it (profile velocity...); the
        objects conversions read that no TPDO carries. With ``hold``, the
        controlword that holds the drive's state and its position too;
        without, the position and what ``_enable`` sets (_SET_BY_ENABLE)
        are left to it: it reads the position and writes the others."""
        node = self._nodes[name]
        rx = tuple(RxPdo(node.od, m) for m in enabled_maps(node.plan.rx))
        tx = tuple(TxPdo(node.od, m) for m in enabled_maps(node.plan.tx))
        initial_out: Dict[ObjectKey, int] = {}
        for rpdo in rx:
            for key in rpdo.keys:
                if not hold and key in _SET_BY_ENABLE:
                    continue
                if key == CONTROLWORD:
                    initial_out[key] = holding_controlword(int(self._upload(name, STATUSWORD)))
                else:
                    initial_out[key] = int(self._known(name, key))
        tx_keys = {k for t in tx for k in t.keys}
        env: Dict[str, float] = {}
        cfg = node.cfg
        for expr in (cfg.pos_from_device, cfg.vel_from_device, cfg.eff_from_device,
                     cfg.pos_to_device, cfg.vel_to_device, cfg.eff_to_device):
            for key in expr.objects:
                if key not in tx_keys:
                    env[object_variable_name(key)] = float(self._known(name, key))
        self._initial_env[name] = MappingProxyType(dict(env))
        heartbeat_ms = int(self._known(name, PRODUCER_HEARTBEAT)) if PRODUCER_HEARTBEAT.index in node.od else 0
        return Binding(rx, tx, MappingProxyType(initial_out), MappingProxyType(env),
                       self._position(name) if hold else 0, heartbeat_ms, time.monotonic())

    def init(self) -> Result:
        """ros_canopen's init: reset, configure, start, home, enable."""
        if not self._service.acquire(blocking=False):
            return fail("another driver service is running")
        try:
            if self.initialized:
                return ok("already initialized")
            try:
                return self._init()
            except _InitError as e:
                self._teardown()
                return fail(str(e))
            except Exception as e:  # never let a surprise kill the node
                log.exception("init failed")
                self._teardown()
                return fail("init failed: %s" % e)
        finally:
            self._service.release()

    def _init(self) -> Result:
        self.bus_error = None
        self._send_failures = 0
        self._abort.clear()
        warning = check_budget(self.config, [node.plan for node in self._nodes.values()])
        if warning:
            log.warning("%s", warning)
        self._open()
        names = list(self._nodes)
        # Everything init needs from a node is read while it is configured,
        # all nodes at once; none is enabled unless every one is configured.
        prepared = self._each_node(names, self._prepare)
        # A mode requested before init is set before enabling; a node that
        # homes first gets it after homing, through the cycle, as before.
        modes = {name: None if prepared[name][1] else self._requested_modes[name] for name in names}
        enabled = self._enable_all(names, {name: prepared[name][0] for name in names}, modes)
        try:
            axes = []
            now = time.monotonic()
            for name in names:
                node = self._nodes[name]
                binding, statusword = enabled[name]
                axis = Axis(node.cfg, node.od, node.plan, self._limits[name])
                axis.active_mode = modes[name]
                axis.attach(binding, self._cycle_no, now)
                axis.enabled_over_sdo(statusword)
                axis.ready = True
                axes.append(axis)
            for axis in axes:
                self._nmt(NMT_START, axis.node_id)
            now = time.monotonic()
            for axis in axes:
                axis.last_heartbeat = axis.status_seen = now
            # The axes are this thread's until the cycle starts: their first
            # snapshot shows them enabled and ready without waiting for it.
            self._cycle_no += 1
            self._snapshot = DriverSnapshot(self._cycle_no, MappingProxyType({a.name: a.snapshot() for a in axes}),
                                            self.bus_error, self._foreign_frames[0])
            self._start_cycle(axes)
        except BaseException:
            if self._thread is None:  # no cycle to disable them: do it over SDO
                problems = self._disable_all(names)
                if problems:
                    log.error("init: %s", "; ".join(problems))
            raise
        for name in names:
            method = prepared[name][1]
            if method:
                r = self._home(name, method)
                if not r:
                    raise _InitError(r.message)
                mode = self._requested_modes[name]
                if mode is not None:
                    r = self._switch(name, mode, force=True)
                    if not r:
                        raise _InitError(r.message)
        self.initialized = True
        text = ", ".join("%s (node %d, PDOs from %s)" % (n, self._nodes[n].cfg.node_id, self._nodes[n].plan.source)
                         for n in names)
        return ok("initialized " + text)

    def _each_node(self, names: Sequence[str], work: Callable[[str], Any]) -> Dict[str, Any]:
        """work(name) for every node at once; the results by name, or an
        _InitError naming every node that failed (each message names the
        node and the step)."""
        results, errors = self._each_node_collect(names, work)
        if errors:
            raise _InitError("; ".join(errors[n] for n in names if n in errors))
        return results

    def _each_node_collect(self, names: Sequence[str],
                           work: Callable[[str], Any]) -> Tuple[Dict[str, Any], Dict[str, str]]:
        results: Dict[str, Any] = {}
        errors: Dict[str, str] = {}

        def run(name: str) -> None:
            try:
                results[name] = work(name)
            except _InitError as e:
                errors[name] = str(e)
            except Exception as e:  # a bus going away, anything: the node is named all the same
                log.exception("init of %s", name)
                errors[name] = "%s (node %d): %s" % (name, self._nodes[name].cfg.node_id, e)
        if len(names) == 1:
            run(names[0])
        elif names:
            with ThreadPoolExecutor(max_workers=min(len(names), _INIT_WORKERS),
                                    thread_name_prefix="epos4_init") as pool:
                list(pool.map(run, names))
        return results, errors

    def _prepare(self, name: str) -> Tuple[Binding, int]:
        """One node's configuration (reset, parameters, PDOs, initial values)
        and its homing method."""
        binding = self._configure(name, hold=False)
        if HOMING_METHOD.index not in self._nodes[name].od:
            return binding, 0
        try:
            return binding, int(self._known(name, HOMING_METHOD))
        except (SdoAbortedError, SdoCommunicationError) as e:
            raise _InitError("%s (node %d): reading the homing method 0x6098 failed: %s"
                             % (name, self._nodes[name].cfg.node_id, e)) from None

    def _enable_all(self, names: Sequence[str], bindings: Mapping[str, Binding],
                    modes: Mapping[str, Optional[int]]) -> Dict[str, Tuple[Binding, int]]:
        """Every node to Operation Enabled over SDO, at once; when one fails,
        every node is disabled again before the error is raised."""
        results, errors = self._each_node_collect(names, lambda n: self._enable(n, bindings[n], modes[n]))
        if errors:
            problems = [errors[n] for n in names if n in errors]
            problems.extend(self._disable_all(names))
            raise _InitError("; ".join(problems))
        return results

    def _enable(self, name: str, binding: Binding, mode: Optional[int]) -> Tuple[Binding, int]:
        """Operation Enabled over SDO, before NMT start: the mode (if one was
        requested) written and confirmed, the targets set to what the cycle's
        first RxPDOs will carry (the position just read, velocity and torque
        0), then the CiA 402 walk, each controlword confirmed by reading the
        statusword. The binding returned starts the RxPDOs there, with
        controlword enable operation; and the statusword read last."""
        node = self._nodes[name]
        nid = node.cfg.node_id
        step = "reading the statusword 0x6041"
        try:
            statusword = int(self._upload(name, STATUSWORD))
            out = dict(binding.initial_out)
            if mode is not None:
                step = "writing modes of operation 0x6060 = %d" % mode
                self._download(name, MODES_OF_OPERATION.index, 0, mode.to_bytes(1, "little", signed=True))
                step = "confirming modes of operation display 0x6061 = %d" % mode
                self._await(name, MODES_DISPLAY, lambda v: v == mode,
                            "modes of operation display 0x6061 = %%d, not %d" % mode)
                out[MODES_OF_OPERATION] = mode
            step = "reading the position actual value 0x6064"
            position = self._position(name)
            for key, value in zip(_HOLD_TARGETS, (position, 0, 0)):
                step = "writing %s = %d (hold)" % (key, value)
                self._download(name, key.index, key.subindex, find_variable(node.od, key).encode_raw(value))
                out[key] = value
            for _ in range(_ENABLE_STEPS):
                state = cia402.state_or_none(statusword)
                if state == State.OPERATION_ENABLED:
                    break
                if state == State.FAULT:
                    # fault reset acts on the rising edge of bit 7
                    commands: Tuple[int, ...] = (cia402.CW_DISABLE_VOLTAGE, cia402.CW_FAULT_RESET)
                else:
                    cw = cia402.next_controlword(state, State.OPERATION_ENABLED) if state is not None else None
                    commands = (cw,) if cw is not None else ()  # none: the drive moves on by itself
                for cw in commands:
                    step = "writing controlword 0x6040 = 0x%04X (%s)" % (cw, _COMMAND_NAMES.get(cw, "?"))
                    self._download(name, CONTROLWORD.index, 0, cw.to_bytes(2, "little"))
                step = "waiting to leave %s%s" % (state.value if state else "0x%04X" % statusword,
                                                  " after " + step[8:] if commands else "")
                statusword = self._await(name, STATUSWORD, lambda v, s=state: cia402.state_or_none(v) != s,
                                         "statusword 0x6041 = 0x%04X")
            else:
                raise _InitError("%s (node %d): not operation enabled after %d steps (0x6041 = 0x%04X)"
                                 % (name, nid, _ENABLE_STEPS, statusword))
        except SdoAbortedError as e:
            raise _InitError("%s (node %d): enabling: %s failed: %s" % (name, nid, step, e)) from None
        except SdoCommunicationError as e:
            raise _InitError("%s (node %d): no SDO answer while enabling (%s): %s" % (name, nid, step, e)) from None
        except _Timeout as e:
            raise _InitError("%s (node %d): enabling: %s: still %s after %g s" % (name, nid, step, e,
                                                                                  self.state_timeout)) from None
        out[CONTROLWORD] = cia402.CW_ENABLE_OPERATION
        return replace(binding, initial_out=MappingProxyType(out), raw_position=position), statusword

    def _await(self, name: str, key: ObjectKey, done: Callable[[int], bool], shows: str) -> int:
        """Read ``key`` over SDO until ``done(value)``, for at most
        ``state_timeout``: the drive's own answers, no cycle involved. An
        EPOS4 changes state within a millisecond, so the first reads come
        at once and later ones less often."""
        deadline = time.monotonic() + self.state_timeout
        pause = 0.0005
        while True:
            value = int(self._upload(name, key))
            if done(value):
                return value
            if time.monotonic() > deadline or self._abort.is_set():
                raise _Timeout(shows % value)
            time.sleep(pause)
            pause = min(2 * pause, 0.02)

    def _disable_all(self, names: Sequence[str]) -> List[str]:
        """Disable every node over SDO (no cycle runs): the problems."""
        _, errors = self._each_node_collect(names, lambda name: self._stop_and_disable(
            name, "disabling after the failed init"))
        return [errors[n] for n in names if n in errors]

    def _home(self, name: str, method: int) -> Result:
        r = self._switch(name, HOMING.number, force=True)
        if not r:
            return fail("homing of %s: %s" % (name, r.message))
        after = self._post(_Homing(name, True))
        start = after + 3
        sw_done = cia402.SW_HOMING_ATTAINED | cia402.SW_TARGET_REACHED

        def finished(s: DriverSnapshot) -> bool:
            a = s.axes[name]
            if a.error:
                return True
            if s.cycle < start:
                return False
            return (a.statusword & sw_done) == sw_done or bool(a.statusword & cia402.SW_HOMING_ERROR)
        done = self._wait(finished, self.homing_timeout, after)
        position = self._position(name)
        self._wait(lambda s: True, 1.0, self._post(_Homing(name, False), _Hold(name, position)))
        a = self._snapshot.axes[name]
        if a.error:
            return fail("homing of %s (method %d): %s" % (name, method, a.error))
        if a.statusword & cia402.SW_HOMING_ERROR:
            return fail("homing of %s (method %d) failed: homing error bit set%s" % (
                name, method, ", last EMCY " + a.last_emcy if a.last_emcy else ""))
        if not done:
            return fail("homing of %s (method %d) not finished within %g s" % (name, method, self.homing_timeout))
        log.info("%s homed (method %d)", name, method)
        return ok()

    # ====================================================== mode switch
    def switch_mode(self, joint_names: Iterable[str], mode: Any) -> Result:
        """Put joints into a mode of operation through their switching_state;
        targets hold the position read over SDO first, so nothing jumps.
        Before init, the mode is remembered and applied by init."""
        if isinstance(mode, bool) or not isinstance(mode, int) or mode_of(mode) is None:
            return fail("mode %r is not supported (supported: %s)" % (mode, supported_modes_text()))
        names = []
        for name in joint_names:
            n = self._name(name)
            if n is None:
                return self._unknown(name)
            plan = self._nodes[n].plan
            if not plan.supports(mode):
                return fail("%s cannot run mode %d (%s): its %s PDO layout carries no %s (layout modes: %s)" % (
                    n, mode, cia402.mode_name(mode), plan.source,
                    ", ".join(str(k) for k in MODE_TARGETS[mode]) or "controlword",
                    ", ".join(cia402.mode_name(m) for m in plan.modes) or "all"))
            names.append(n)
        if not self.initialized:
            for n in names:
                self._requested_modes[n] = mode
            return ok("mode %d will be set at init" % mode)
        for n in names:
            self._requested_modes[n] = mode
            r = self._switch(n, mode)
            if not r:
                return r
        return ok()

    def _switch(self, name: str, mode: int, force: bool = False) -> Result:
        try:
            return self._switch_steps(name, mode, force)
        except (SdoAbortedError, SdoCommunicationError) as e:
            return fail("mode switch of %s: %s" % (name, e))

    def _switch_steps(self, name: str, mode: int, force: bool) -> Result:
        a = self._snapshot.axes[name]
        if a.error:
            return fail("%s is in error (%s): call recover" % (name, a.error))
        if not force and a.active_mode == mode and a.mode_display == mode and a.held_state == State.OPERATION_ENABLED:
            self._wait(lambda s: True, 1.0, self._post(_Hold(name, self._position(name))))
            return ok()
        position = self._position(name)
        self._post(_Hold(name, position))
        node = self._nodes[name]
        err = self._go([name], SWITCHING_STATE[node.cfg.switching_state])
        if err:
            return fail("mode switch of %s: %s" % (name, err))
        self._post(_SetMode(name, mode, position))
        if MODES_OF_OPERATION not in node.plan.rx_keys():
            self._download(name, MODES_OF_OPERATION.index, 0, mode.to_bytes(1, "little", signed=True))
        if MODES_DISPLAY in node.plan.tx_keys():
            confirmed = self._wait(lambda s: s.axes[name].mode_display == mode or bool(s.axes[name].error),
                                   self.state_timeout)
        else:
            confirmed = int(self._upload(name, MODES_DISPLAY)) == mode
            if confirmed:
                self._post(_ModeConfirmed(name, mode))
        a = self._snapshot.axes[name]
        if not confirmed or a.error:
            return fail("%s did not confirm mode %s (0x6061 = %d)" % (name, cia402.mode_name(mode), a.mode_display))
        self._post(_Hold(name, self._position(name)))
        err = self._go([name], State.OPERATION_ENABLED)
        if err:
            return fail("mode switch of %s: %s" % (name, err))
        log.info("%s in mode %s", name, cia402.mode_name(mode))
        return ok()

    # ================================================ halt/recover/shutdown
    def halt(self) -> Result:
        """Stop motion. Per node's ``halt_mode``: ``quick_stop`` (default, as
        ros_canopen) brings an enabled drive to Quick Stop Active, where it
        ramps down on its quick stop deceleration; ``halt_bit`` keeps it
        Operation Enabled and stops in place (halt bit in the profile modes,
        the last commanded target in CSP, zero in CSV/CST). Either way the
        joint takes no command until recover."""
        if not self.initialized:
            return fail("driver not initialized: call init")
        names = tuple(self._nodes)
        snap = self._snapshot.axes
        quick = tuple(n for n in names if self._nodes[n].cfg.halt_mode == "quick_stop"
                      and snap[n].held_state == State.OPERATION_ENABLED and not snap[n].error)
        after = self._post(_StopInPlace(names))
        if quick:
            after = self._post(_StateRequest(quick, State.QUICK_STOP_ACTIVE))

            def stopping(s: DriverSnapshot) -> bool:
                return all(s.axes[n].error or (s.axes[n].target_state is None and s.axes[n].held_state in (
                    State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED)) for n in quick)
            if not self._wait(stopping, self.state_timeout, after):
                return fail("halt: quick stop not confirmed by %s" % ", ".join(
                    n for n in quick if self._snapshot.axes[n].held_state != State.QUICK_STOP_ACTIVE))
        self._wait(lambda s: True, 1.0, after + 1)
        return ok("halted" + (" (quick stop)" if quick else ""))

    def recover(self) -> Result:
        """Fault reset and re-enable; targets hold the position read over SDO
        before enabling, so that nothing jumps to a stale target."""
        if not self._service.acquire(blocking=False):
            return fail("another driver service is running")
        try:
            if not self.initialized:
                return fail("driver not initialized: call init")
            return self._recover()
        except (SdoAbortedError, SdoCommunicationError) as e:
            return fail("recover: %s" % e)
        except Exception as e:
            log.exception("recover failed")
            return fail("recover failed: %s" % e)
        finally:
            self._service.release()

    def _recover(self) -> Result:
        names = list(self._nodes)
        # Restart the periodic senders: cheap, and afterwards they surely
        # run, whatever the bus did to them while it failed.
        if self._heartbeat is not None:
            self._heartbeat.stop()
            self._heartbeat.start()
            if self.bus_error is not None:
                # The drives heard no master heartbeat while the bus failed:
                # their consumers may trip any moment now. Two heartbeat
                # periods after the restart each has heard one or tripped,
                # so the fault reset below comes after the trip, not before.
                time.sleep(2 * self._heartbeat.period_s)
        if self.sync is not None:
            self._start_sync()
        self.bus_error = None
        notes = []
        rehome = []
        reconfigured: List[str] = []
        for name in names:
            a = self._snapshot.axes[name]
            if a.rebooted or a.nmt_state in ("STOPPED", "PRE-OPERATIONAL", "INITIALISING", "LOST"):
                # Configure the node again: one that rebooted lost its
                # configuration, and one that was silent or left OPERATIONAL
                # may have lost or been given another. Only a rebooted node
                # is reset: a reset restarts the position counter, and
                # pre-operational is enough to write the rest.
                self._wait(lambda s: not s.axes[name].attached, 2.0, self._post(_Detach(name)))
                try:
                    binding = self._configure(name, reset=a.rebooted)
                except _InitError as e:
                    return fail("recover: %s" % e)
                self._nmt(NMT_START, self._nodes[name].cfg.node_id)
                self._post(_Attach(name, binding))
                reconfigured.append(name)
                if a.rebooted:
                    # an incremental encoder restarts at 0: the position
                    # reference is gone, homing (if configured) finds it again
                    method = int(self._known(name, HOMING_METHOD)) if HOMING_METHOD.index in self._nodes[name].od else 0
                    if method:
                        rehome.append((name, method))
                    else:
                        notes.append("%s rebooted: its position reference is lost (no homing method configured)"
                                     % name)
        for name in names:
            if name not in reconfigured:
                # a drive whose 0x1017 is 0 says nothing of its NMT state: one
                # that left OPERATIONAL by itself (its communication error
                # behaviour, 0x1029) is started again; harmless otherwise
                self._nmt(NMT_START, self._nodes[name].cfg.node_id)
        # Each drive's state is read over SDO only once the controlword the
        # cycle holds it with (quick stop, for one it lost sight of) and a
        # SYNC after it went out since it was started: the drive answers in
        # the order frames came, so the answer shows that controlword's
        # effect, and no TxPDO the drive sent before it can come after the
        # request below and confirm a state the drive is about to leave.
        # The cycle that takes the attach sends it (in-cycle SYNC, or the
        # kernel's SYNC before the next cycle): two cycles on, it is out.
        if not self._wait(lambda s: True, self.state_timeout, self._post() + 2):
            return fail("recover: the control cycle did not run for %g s" % self.state_timeout)
        clear = []
        for name in names:
            try:
                clear.append(_ClearError(name, self._position(name), int(self._upload(name, STATUSWORD))))
            except (SdoAbortedError, SdoCommunicationError) as e:
                return fail("recover: %s (node %d): reading its position and statusword: %s"
                            % (name, self._nodes[name].cfg.node_id, e))
        err = self._go(names, State.OPERATION_ENABLED, fault_reset=True, together=clear)
        if err:
            return fail("recover: " + err)
        self._wait(lambda s: True, 1.0, self._post(_Ready(tuple(names), True)))
        for name, method in rehome:
            mode = self._snapshot.axes[name].active_mode
            r = self._home(name, method)
            if not r:
                return fail("recover: %s rebooted and lost its position reference; %s" % (name, r.message))
            notes.append("%s rebooted: homed again (method %d)" % (name, method))
            if mode is not None:
                r = self._switch(name, mode, force=True)
                if not r:
                    return fail("recover: " + r.message)
        for name in names:
            a = self._snapshot.axes[name]
            if a.active_mode is not None and a.mode_display != a.active_mode:
                r = self._switch(name, a.active_mode, force=True)
                if not r:
                    return fail("recover: " + r.message)
        self._wait_cycles(2)
        # a drive confirmed enabled above may have left it since (one still
        # finishing a quick stop it began by itself): not "recovered" then
        snap = self._snapshot
        again = ["%s: %s" % (n, snap.axes[n].error) for n in names if snap.axes[n].error]
        if again:
            return fail("recover: in error again before recover ended: " + "; ".join(again))
        return ok("recovered" + ("; " + "; ".join(notes) if notes else ""))

    def shutdown(self) -> Result:
        """Quick stop and disable every drive, stop SYNC, NMT stop."""
        with self._service:
            if not self.initialized and self.network is None:
                return ok("driver was not initialized")
            problems = self._teardown()
            if problems:
                return fail("shut down with problems: " + "; ".join(problems))
            return ok("shut down")

    def _teardown(self) -> List[str]:
        """Bring every drive the driver can reach to rest and disable it; a
        drive that does not answer does not keep the others running."""
        problems: List[str] = []
        names = list(self._nodes)
        if self._thread is not None:
            snap = self._snapshot.axes
            self._post(_StopInPlace(tuple(names)))
            attached = [n for n in names if snap[n].attached]
            # The drives the cycle hears are stopped and disabled through it,
            # all at once; those it does not hear (a drive that left
            # OPERATIONAL by itself takes no RxPDO and sends no TxPDO) and
            # those it could not bring there, one by one over SDO.
            # Heard means statusword TxPDOs coming: a heartbeat's NMT state
            # (anyone can forge one) does not decide the way.
            cycle = self._snapshot.cycle
            heard = [n for n in attached if cycle - snap[n].status_cycle <= _HEARD_CYCLES]
            done = self._stop_and_disable_by_pdo(heard)
            rest = [n for n in attached if n not in done]
            _, errors = self._each_node_collect(rest, self._stop_and_disable)
            if rest:
                # a drive still in OPERATIONAL then shows its last state on the bus too
                self._wait_cycles(2)
            problems.extend(errors[n] for n in rest if n in errors)
            self._release_heartbeat_consumers([n for n in attached if n not in errors])
        self._stop_cycle()
        # The cycle thread is gone: the axes are this thread's again.
        for axis in self._axes:
            axis.ready = False
            if axis.active_mode is not None:
                self._requested_modes[axis.name] = axis.active_mode
        if self.network is not None:
            for node in self._nodes.values():
                try:
                    self._nmt(NMT_STOP, node.cfg.node_id)
                except (can.CanError, OSError) as e:
                    problems.append("NMT stop of %s: %s" % (node.cfg.name, e))
                    continue
                axis = self._axis.get(node.cfg.name)
                if axis is not None:
                    axis.nmt_state = "STOPPED"
        if self._axes:
            # numbered as a cycle, so that a service waiting for a cycle
            # after its post is not answered by this snapshot
            self._cycle_no += 1
            self._snapshot = DriverSnapshot(self._cycle_no, MappingProxyType(
                {a.name: a.snapshot() for a in self._axes}), self.bus_error, self._foreign_frames[0])
        self._close()
        self.initialized = False
        return problems

    def _stop_and_disable_by_pdo(self, names: Sequence[str]) -> List[str]:
        """Quick stop, standstill and disable voltage through the cycle; the
        names now in Switch On Disabled or Fault. The power goes off only
        once a drive's standstill is read over SDO (a TxPDO anyone could
        have sent proves nothing); one not confirmed is left to SDO."""
        snap = self._snapshot.axes
        enabled = [n for n in names if snap[n].state == State.OPERATION_ENABLED]
        self._go(enabled, State.QUICK_STOP_ACTIVE, stop_on_error=False, unheard_cycles=_HEARD_CYCLES)
        snap = self._snapshot.axes
        # options 0-2 end the quick stop in Switch On Disabled by themselves
        stopping = [n for n in enabled if snap[n].state in (State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED)]
        at_rest = self._wait_standstill(stopping)
        live = [n for n in names if (n in at_rest or n not in enabled) and snap[n].state not in (State.FAULT, None)]
        self._go(live, State.SWITCH_ON_DISABLED, stop_on_error=False, unheard_cycles=_HEARD_CYCLES)
        snap = self._snapshot.axes
        return [n for n in names if snap[n].state in (State.SWITCH_ON_DISABLED, State.FAULT)
                and (n in at_rest or n not in enabled)]

    def _wait_standstill(self, names: Sequence[str]) -> List[str]:
        """Wait until each drive has stopped on its quick stop ramp (or left
        Quick Stop Active by itself at its end), at most the ramp's time
        from the velocity and 0x6085 (quick stop deceleration) plus a
        margin, all drives at once; the names confirmed at rest."""
        deadline = time.monotonic()
        for name in names:
            try:
                deadline = max(deadline, self._quick_stop_deadline(name))
            except (SdoAbortedError, SdoCommunicationError):
                deadline = max(deadline, time.monotonic() + self.state_timeout)
        at_rest: List[str] = []
        waiting = list(names)
        while waiting:
            for name in list(waiting):
                if self._snapshot.axes[name].state == State.SWITCH_ON_DISABLED:
                    at_rest.append(name)  # the end of the ramp (options 0-2)
                    waiting.remove(name)
                    continue
                try:
                    if abs(int(self._upload(name, VELOCITY_ACTUAL))) <= _STANDSTILL:
                        at_rest.append(name)
                        waiting.remove(name)
                except (SdoAbortedError, SdoCommunicationError):
                    pass  # not known yet: asked again until the deadline
            if not waiting or time.monotonic() > deadline:
                return at_rest
            time.sleep(0.02)
        return at_rest

    def _stop_and_disable(self, name: str, why: str = "shutting down") -> None:
        """Shutdown of one drive, judged by its own SDO answers: quick stop,
        standstill, disable voltage. A drive that left OPERATIONAL by
        itself (its heartbeat consumer tripped, 0x1029) takes no RxPDO and
        sends no TxPDO, and a TxPDO anyone could have sent proves nothing:
        SDO reaches and answers in OPERATIONAL and PRE-OPERATIONAL alike.
        Each controlword goes to the cycle first, so the RxPDO carries the
        same command and none still on its way can undo it (enable
        operation takes Quick Stop Active back to Operation Enabled,
        transition 16)."""
        nid = self._nodes[name].cfg.node_id
        step = "reading the statusword 0x6041"
        try:
            state = cia402.state_or_none(int(self._upload(name, STATUSWORD)))
            if state == State.OPERATION_ENABLED:
                step = "quick stop"
                self._command(name, State.QUICK_STOP_ACTIVE, cia402.CW_QUICK_STOP)
                step = "waiting for standstill"
                state = self._standstill(name)
            if state in (State.QUICK_STOP_ACTIVE, State.SWITCHED_ON, State.READY_TO_SWITCH_ON):
                step = "disable voltage"
                self._command(name, State.SWITCH_ON_DISABLED, cia402.CW_DISABLE_VOLTAGE)
                step = "confirming switch_on_disabled"
                self._await(name, STATUSWORD, lambda v: cia402.state_or_none(v) == State.SWITCH_ON_DISABLED,
                            "statusword 0x6041 = 0x%%04X after %g s" % self.state_timeout)
        except (SdoAbortedError, SdoCommunicationError, _Timeout) as e:
            raise _InitError("%s (node %d): %s: %s: %s" % (name, nid, why, step, e)) from None

    def _command(self, name: str, state: State, controlword: int) -> None:
        """``controlword`` to the drive over SDO, once the cycle's RxPDO (if
        a cycle runs) carries it too."""
        if self._thread is not None:
            after = self._post(_StateRequest((name,), state, False))
            self._wait(lambda s: True, 1.0, after)
        self._download(name, CONTROLWORD.index, 0, controlword.to_bytes(2, "little"))

    def _quick_stop_deadline(self, name: str) -> float:
        """When a drive's quick stop ramp must be done (monotonic): its time
        from 0x606C and 0x6085 read over SDO, plus a margin, at most the
        state timeout."""
        velocity = abs(int(self._upload(name, VELOCITY_ACTUAL)))
        deceleration = int(self._upload(name, QUICK_STOP_DECELERATION)) if \
            QUICK_STOP_DECELERATION.index in self._nodes[name].od else 0
        ramp = velocity / deceleration if deceleration > 0 else self.state_timeout
        return time.monotonic() + min(1.5 * ramp + 0.5, self.state_timeout)

    def _standstill(self, name: str) -> Optional[State]:
        """Wait until the drive has stopped on its quick stop ramp (or left
        Quick Stop Active by itself at its end), at most the ramp's time
        from the velocity and 0x6085 (quick stop deceleration) plus a
        margin; the state it is in then. Raises _Timeout when it still
        moves."""
        deadline = self._quick_stop_deadline(name)
        while True:
            state = cia402.state_or_none(int(self._upload(name, STATUSWORD)))
            if state != State.QUICK_STOP_ACTIVE:
                return state
            velocity = int(self._upload(name, VELOCITY_ACTUAL))
            if abs(velocity) <= _STANDSTILL:
                return state
            if time.monotonic() > deadline:
                raise _Timeout("still moving (0x606C = %d) when the quick stop time ran out" % velocity)
            time.sleep(0.02)

    def _release_heartbeat_consumers(self, names: Sequence[str]) -> None:
        """A drive disabled by shutdown need not watch the master any more:
        stop its heartbeat consumer so the master's heartbeat ending now is
        no fault (best effort)."""
        for name in names:
            plan = self._nodes[name].plan
            if any(w.key == HEARTBEAT_CONSUMER_1 for w in plan.writes):
                try:
                    self._download(name, HEARTBEAT_CONSUMER_1.index, HEARTBEAT_CONSUMER_1.subindex, bytes(4))
                except Exception as e:
                    log.warning("%s: heartbeat consumer left on: %s", name, e)

    def close(self) -> None:
        """Leave the drives safe and release the bus (node exit); never raises.
        A service still waiting (init homing...) is made to give up first."""
        try:
            self._abort.set()
            got = self._service.acquire(timeout=10.0)
            if got:
                self._service.release()
            self._abort.clear()  # shutdown's own waits (quick stop) must run
            if self.initialized or self.network is not None:
                r = self.shutdown()
                if not r:
                    log.error("close: %s", r.message)
        except Exception:
            log.exception("close failed")

    # ========================================================== objects
    def _object(self, node_name: Any, obj: Any) -> Tuple[Optional[str], Any, Optional[Result]]:
        n = self._name(node_name)
        if n is None:
            return None, None, self._unknown(node_name)
        try:
            key = parse_object_key(obj)
            var = find_variable(self._nodes[n].od, key)
        except ObjectStringError as e:
            return None, None, fail(str(e))
        if n not in self._sdo:
            return None, None, fail("driver not initialized: call init")
        return n, var, None

    def get_object(self, node_name: str, obj: str, cached: bool = False) -> Result:
        """ros_canopen's get_object; always answers."""
        try:
            return self._get_object(node_name, obj, cached)
        except Exception as e:  # a bus going away mid-request, anything
            return fail("reading %s from %s: %s" % (obj, node_name, e))

    def _get_object(self, node_name: str, obj: str, cached: bool) -> Result:
        n, var, err = self._object(node_name, obj)
        if err is not None:
            return err
        key = ObjectKey(var.index, var.subindex)
        if not is_readable(var):
            return fail("object %s is write-only" % key)
        readings = self._snapshot.axes[n].readings
        if cached and key in readings:
            return ok(value=decode_value(var, readings[key]))
        cache = self._cache[n]
        if cached and key in cache:
            return ok(value=decode_value(var, cache[key]))
        try:
            value = self._upload(n, key)
        except SdoAbortedError as e:
            return fail("reading %s from %s: %s" % (key, n, e))
        except SdoCommunicationError as e:
            return fail("reading %s from %s: no answer (%s)" % (key, n, e))
        cache[key] = value
        return ok(value=decode_value(var, value))

    def set_object(self, node_name: str, obj: str, value: str, cached: bool = False) -> Result:
        """ros_canopen's set_object; always answers. Objects the driver owns
        are refused with the reason."""
        try:
            return self._set_object(node_name, obj, value, cached)
        except Exception as e:
            return fail("writing %s to %s: %s" % (obj, node_name, e))

    def _set_object(self, node_name: str, obj: str, value: str, cached: bool) -> Result:
        n, var, err = self._object(node_name, obj)
        if err is not None:
            return err
        key = ObjectKey(var.index, var.subindex)
        if key in DRIVER_OWNED:
            return fail("object %s is written by the driver every cycle: use the controllers "
                        "and services instead" % key)
        for lo, hi, why in _REFUSED_RANGES:
            if lo <= key.index <= hi:
                return fail("object %s is refused: %s" % (key, why))
        if not is_writable(var):
            return fail("object %s is read-only" % key)
        try:
            py_value = encode_value(var, value)
            data = var.encode_raw(py_value)
        except ObjectValueError as e:
            return fail(str(e))
        cache = self._cache[n]
        if cached and cache.get(key) == py_value:
            return ok("unchanged")
        try:
            self._download(n, key.index, key.subindex, data)
        except SdoAbortedError as e:
            return fail("writing %s to %s: %s" % (key, n, e))
        except SdoCommunicationError as e:
            return fail("writing %s to %s: no answer (%s)" % (key, n, e))
        cache[key] = py_value
        if key in self._nodes[n].plan.rx_keys():
            # keep the RPDO from writing the old value back
            self._wait(lambda s: True, 1.0, self._post(_SetOutput(n, key, int(py_value))))
        if key == PRODUCER_HEARTBEAT:
            self._post(_SetHeartbeat(n, int(py_value)))
        return ok()

    # ==================================================== ROS layer/diag
    def published_types(self) -> Dict[str, int]:
        """topic -> CANopen data type of the ROS layer's published objects."""
        out = {}
        for node in self._nodes.values():
            for pub in node.cfg.publish:
                out[pub.topic] = find_variable(node.od, pub.key).data_type
        return out

    def read_published(self) -> Dict[str, Any]:
        """topic -> value of every ``publish`` object: from its TPDO when
        mapped, else the cache, read by SDO when forced (``!``) or never read.
        Objects that cannot be read are left out (and logged)."""
        out: Dict[str, Any] = {}
        if not self._sdo:
            return out
        snap = self._snapshot.axes
        for name, node in self._nodes.items():
            readings = snap[name].readings
            cache = self._cache[name]
            for pub in node.cfg.publish:
                if pub.key in readings and not pub.force:
                    out[pub.topic] = readings[pub.key]
                    continue
                if pub.force or pub.key not in cache:
                    try:
                        cache[pub.key] = self._upload(name, pub.key)
                    except Exception as e:  # SDO abort, timeout, network closed meanwhile
                        log.warning("publish %s: %s", pub.topic, e)
                        continue
                out[pub.topic] = cache[pub.key]
        return out

    def status(self) -> List[Dict[str, Any]]:
        """One dict per node for diagnostics."""
        snap = self._snapshot
        # how long the latest frame read had waited unread: a loaded host
        receive_lag_ms = int(round(max(0.0, self._receive_clock.lag()) * 1000))
        out = []
        for a in snap.axes.values():
            out.append({
                "name": a.name, "node_id": a.node_id, "nmt_state": a.nmt_state,
                "state": a.state.value if a.state else "unknown",
                "statusword": "0x%04X" % a.statusword,
                "mode": a.mode_name(), "mode_display": a.mode_display,
                "last_emcy": a.last_emcy, "error_register": "0x%02X" % a.error_register,
                "error": a.error or "", "halted": a.halted, "initialized": self.initialized,
                "pdo_mapping": a.plan.source, "limits": a.limits.describe(),
                "last_refused_command": a.last_refusal,
                "frames_ignored": _listed(a.counters, lambda n: n not in COMMAND_COUNTERS and n != EMCY_NOT_LOGGED),
                "commands_limited": _listed(a.counters, COMMAND_COUNTERS.__contains__),
                "emcy_not_logged": a.counters.get(EMCY_NOT_LOGGED, 0),
                "foreign_rpdo_frames": snap.foreign_frames,
                "receive_lag_ms": receive_lag_ms,
            })
        return out


