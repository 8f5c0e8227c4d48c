"""The CANopen master: ros_canopen's driver services on canopen + python-can.

Threads: the service calls (init, halt, recover, shutdown, get/set_object,
switch_mode) run in the caller's thread, one at a time; the cycle runs in
its own thread every ``sync/update_ms`` and is the only one that sends
PDOs and SYNC; canopen's notifier thread delivers TPDOs, heartbeats and
EMCYs. Services ask the cycle for a state and wait for it (on a condition
the cycle signals), they never write the controlword themselves.
"""
from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from typing import Any, Callable, Dict, Iterable, List, Optional, Sequence, Tuple

import can
import canopen
from canopen.emcy import EmcyError
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from .. import cia402
from ..cia402 import State
from ..config import SUPPORTED_DRIVE_MODES, ConfigError, DriverConfig
from ..objects import (ObjectKey, ObjectStringError, ObjectValueError, decode_value, encode_value,
                       find_variable, is_readable, is_writable, parse_object_key)
from .bus import HeartbeatProducer, SyncProducer, open_bus
from .joint import CYCLIC_MODES, HM, Joint, JointLimits
from .plan import DRIVER_OWNED, HOMING_METHOD, POSITION_ACTUAL, PRODUCER_HEARTBEAT, plan_node
from .result import Result, fail, ok

try:  # written by the simulator engineer; the driver still works without names
    from ..epos4_errors import describe as describe_error
except ImportError:  # pragma: no cover
    def describe_error(code: int) -> str:
        return "0x%04X" % code

log = logging.getLogger("maxon_epos4_ros_canopen.driver")

NMT_NAMES = {0: "INITIALISING", 4: "STOPPED", 5: "OPERATIONAL", 0x7F: "PRE-OPERATIONAL"}
NMT_START, NMT_STOP, NMT_RESET_NODE = 0x01, 0x02, 0x81
CycleCallback = Callable[["Driver"], None]
_PDO_MISSING_CYCLES = 50


class _InitError(Exception):
    pass


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
        self.joints: "OrderedDict[str, Joint]" = OrderedDict()
        for n in config.nodes:
            try:
                od = canopen.import_od(n.eds_file, n.node_id)
            except Exception as e:  # canopen raises many kinds on a bad file
                raise ConfigError(config.source, "nodes/%s/eds_file" % n.key,
                                  "cannot read %s: %s" % (n.eds_file, e)) from None
            self.joints[n.name] = Joint(n, od, plan_node(n, od, config.sync, config.source))
        self._by_key = {j.cfg.key: j for j in self.joints.values()}
        self._joint_list = list(self.joints.values())
        self._period = config.sync.update_ms / 1000.0
        # TxPDOs come every SYNC (or event period): 50 of them missing, and
        # at least 1.5 s, is an error.
        self._pdo_timeout = max(1.5, _PDO_MISSING_CYCLES * max(config.sync.interval_ms, config.sync.update_ms) / 1000.0)
        self._lock = threading.RLock()
        self._cond = threading.Condition()
        self._service = threading.Lock()
        self._callbacks: List[CycleCallback] = []
        self.initialized = False
        self.bus: Optional[can.BusABC] = None
        self.network: Optional[canopen.Network] = None
        self.sync: Optional[SyncProducer] = None
        self._sync_in_cycle = False
        self._heartbeat: Optional[HeartbeatProducer] = None
        self._thread: Optional[threading.Thread] = None
        self._stop = threading.Event()
        self._abort = threading.Event()  # close(): cut service waits short
        self.cycles = 0
        self.overruns = 0
        self.bus_error: Optional[str] = None
        self._send_failures = 0
        self._boot: Dict[int, threading.Event] = {}

    # ============================================================ lookup
    def joint(self, name: str) -> Optional[Joint]:
        """A joint by its name (the node's ``name``) or its node key (``node1``)."""
        return self.joints.get(name) or self._by_key.get(name)

    def _unknown(self, name: str) -> Result:
        return fail("unknown node %r (known: %s)" % (name, ", ".join(self.joints)))

    def set_limits(self, name: str, limits: JointLimits) -> None:
        j = self.joint(name)
        if j is None:
            raise KeyError(name)
        j.limits = limits

    def add_cycle_callback(self, fn: CycleCallback) -> None:
        """fn(driver) runs every cycle, under the driver lock, after the
        readings are fresh and before the RPDOs go out (CSP trajectories)."""
        self._callbacks.append(fn)

    def remove_cycle_callback(self, fn: CycleCallback) -> None:
        if fn in self._callbacks:
            self._callbacks.remove(fn)

    def set_command(self, name: str, kind: str, value: float) -> Result:
        j = self.joint(name)
        if j is None:
            return self._unknown(name)
        with self._lock:
            return j.set_command(kind, value)

    # ====================================================== bus plumbing
    def _open(self) -> None:
        if self._external_bus is not None:
            self.bus = self._external_bus
        else:
            try:
                self.bus = open_bus(self.config.bus)
            except Exception as e:  # OSError, CanError, ValueError from python-can
                raise _InitError("cannot open CAN device %r: %s" % (self.config.bus.device, e)) from None
        self.network = canopen.Network(self.bus)
        self.network.connect()
        for j in self.joints.values():
            node = canopen.RemoteNode(j.node_id, j.od)
            node.sdo.RESPONSE_TIMEOUT = self.sdo_timeout
            self.network.add_node(node)
            event = self._boot.setdefault(j.node_id, threading.Event())
            node.nmt.add_heartbeat_callback(self._heartbeat_callback(j, event))
            node.emcy.add_callback(self._emcy_callback(j))
            j.node = node
        if self.config.heartbeat is not None:
            self._heartbeat = HeartbeatProducer(self.bus, self.config.heartbeat)
            self._heartbeat.start()

    def _close(self) -> None:
        if self._heartbeat is not None:
            self._heartbeat.stop()
            self._heartbeat = None
        if self.network is not None:
            if self.network.notifier is not None:
                self.network.notifier.stop(1.0)
            self.network = None
        if self.bus is not None and self._external_bus is None:
            self.bus.shutdown()
        self.bus = None

    def _heartbeat_callback(self, j: Joint, boot: threading.Event) -> Callable[[int], None]:
        def on_heartbeat(state: int) -> None:
            j.last_heartbeat = time.time()
            j.nmt_state = NMT_NAMES.get(state, "0x%02X" % state)
            if state == 0:
                boot.set()
                if j.ready:
                    j.rebooted = True
        return on_heartbeat

    def _emcy_callback(self, j: Joint) -> Callable[[EmcyError], None]:
        def on_emcy(emcy: EmcyError) -> None:
            j.error_register = emcy.register
            if emcy.code == 0:
                log.info("%s (node %d): EMCY error reset", j.name, j.node_id)
                return
            text = "%s (error register 0x%02X)" % (describe_error(emcy.code), emcy.register)
            j.last_emcy = text
            log.error("%s (node %d): EMCY %s", j.name, j.node_id, text)
        return on_emcy

    def _send(self, cob_id: int, data: bytes) -> None:
        self.bus.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))

    # ============================================================= cycle
    def _start_cycle(self) -> None:
        sync = self.config.sync
        if sync.interval_ms > 0:
            self.sync = SyncProducer(self.bus, sync.overflow)
            self._sync_in_cycle = sync.interval_ms == sync.update_ms
            if not self._sync_in_cycle:
                self.sync.start(sync.interval_ms / 1000.0)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="epos4_driver_cycle", daemon=True)
        self._thread.start()

    def _stop_cycle(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        if self.sync is not None:
            self.sync.stop()
            self.sync = None
        self._sync_in_cycle = False

    def _run(self) -> None:
        period = self.config.sync.update_ms / 1000.0
        next_t = time.monotonic()
        while not self._stop.is_set():
            self.cycle()
            next_t += period
            delay = next_t - time.monotonic()
            if delay < 0:
                self.overruns += 1
                next_t = time.monotonic()
            else:
                self._stop.wait(delay)

    def cycle(self) -> None:
        """One control cycle: readings in, callbacks, RPDOs and SYNC out.
        Never raises: a failing cycle is logged and the next one runs."""
        try:
            with self._lock:
                now = time.time()
                joints = self._joint_list
                for j in joints:
                    if not j.configuring:  # init/recover owns it meanwhile
                        j.read()
                        self._watch(j, now)
                for fn in self._callbacks:
                    try:
                        fn(self)
                    except Exception:
                        log.exception("cycle callback %r failed", fn)
                for j in joints:
                    if not j.configuring:
                        j.write(self._send)
                if self._sync_in_cycle:
                    self.sync.send()
                self.cycles += 1
            self._send_failures = 0
        except (can.CanError, OSError) as e:
            self._send_failures += 1
            if self._send_failures == 10:
                self.bus_error = str(e)
                log.error("CAN bus error in 10 cycles in a row: %s", e)
                for j in self.joints.values():
                    j.set_error("bus error: %s" % e)
        except Exception:
            log.exception("driver cycle failed")
        with self._cond:
            self._cond.notify_all()

    def _watch(self, j: Joint, now: float) -> None:
        """Heartbeat consumer, NMT state, boot-up and TxPDO watchdog, for
        enabled joints. The TxPDO watchdog covers drives whose 0x1017 is 0
        (no heartbeat): their statusword PDO comes every SYNC or event."""
        if not j.ready or j.error:
            return
        if j.rebooted:
            j.set_error("node rebooted (boot-up message received)")
        elif j.heartbeat_ms > 0 and j.last_heartbeat and \
                now - j.last_heartbeat > 1.5 * j.heartbeat_ms / 1000.0 + 2 * self._period:
            j.nmt_state = "LOST"
            j.set_error("heartbeat lost: nothing for %.0f ms (0x1017 = %d ms)"
                        % ((now - j.last_heartbeat) * 1000, j.heartbeat_ms))
        elif j.nmt_state in ("STOPPED", "PRE-OPERATIONAL"):
            j.set_error("node left OPERATIONAL (heartbeat says %s)" % j.nmt_state)
        else:
            ts = j.status_pdo_time()
            if ts != j.pdo_seen_ts:
                j.pdo_seen_ts, j.pdo_seen_cycle, j.pdo_seen_time = ts, self.cycles, now
            elif self.cycles - j.pdo_seen_cycle >= _PDO_MISSING_CYCLES and \
                    now - j.pdo_seen_time > self._pdo_timeout:
                # Counted in our own cycles too, so that a stall of this
                # process (no SYNC sent) is not taken for a silent drive.
                j.nmt_state = "LOST"
                j.set_error("no statusword TxPDO in %d cycles (%.0f ms)" % (
                    self.cycles - j.pdo_seen_cycle, (now - j.pdo_seen_time) * 1000))

    def _wait(self, pred: Callable[[], bool], timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        with self._cond:
            while not pred():
                remaining = deadline - time.monotonic()
                if remaining <= 0 or self._thread is None or self._abort.is_set():
                    return pred()
                self._cond.wait(remaining)
        return True

    def _wait_cycles(self, n: int) -> None:
        target = self.cycles + n
        self._wait(lambda: self.cycles >= target, max(1.0, n * self.config.sync.update_ms / 100.0))

    def _go(self, joints: Sequence[Joint], state: State, fault_reset: bool = False,
            timeout: Optional[float] = None) -> Optional[str]:
        """Drive joints to a 402 state through the cycle; an error text or None."""
        with self._lock:
            for j in joints:
                j.request_state(state, fault_reset)
        reached = self._wait(lambda: all(j.state == state or j.error for j in joints),
                             timeout or self.state_timeout)
        for j in joints:
            if j.error:
                return "%s: %s" % (j.name, j.error)
            if j.state != state:
                return "%s did not reach %s (state %s, statusword 0x%04X%s)" % (
                    j.name, state.value, j.state.value if j.state else "unknown", j.statusword,
                    ", last EMCY " + j.last_emcy if j.last_emcy else "")
        return None if reached else "timeout waiting for %s" % state.value

    # ============================================================== init
    def _configure(self, j: Joint) -> None:
        """NMT reset, then everything the plan says, over SDO (pre-operational)."""
        with self._lock:
            j.configuring = True  # the cycle leaves this joint alone meanwhile
        try:
            self._configure_node(j)
        finally:
            j.configuring = False

    def _configure_node(self, j: Joint) -> None:
        node = j.node
        boot = self._boot[j.node_id]
        boot.clear()
        node.nmt.send_command(NMT_RESET_NODE)
        if not boot.wait(self.boot_timeout):
            raise _InitError("%s (node %d): no boot-up within %g s after NMT reset"
                             % (j.name, j.node_id, self.boot_timeout))
        j.rebooted = False
        step = "configuration"
        with j.sdo_lock:
            try:
                for w in j.plan.writes:
                    step = "writing " + w.text
                    node.sdo.download(w.key.index, w.key.subindex, w.data)
                step = "writing the PDO mapping"
                self._write_pdos(j)
                j.bind(node)
                step = "reading the initial values"
                self._read_initial(j)
            except SdoAbortedError as e:
                raise _InitError("%s (node %d): %s failed: %s" % (j.name, j.node_id, step, e)) from None
            except SdoCommunicationError as e:
                raise _InitError("%s (node %d): no SDO answer during configuration: %s"
                                 % (j.name, j.node_id, e)) from None

    def _write_pdos(self, j: Joint) -> None:
        for plans, maps in ((j.plan.rx, j.node.rpdo.map), (j.plan.tx, j.node.tpdo.map)):
            for mp in plans:
                m = maps[mp.number]
                m.clear()
                for key, bits in mp.entries:
                    m.add_variable(key.index, key.subindex, bits)
                m.cob_id = mp.cob_id
                m.enabled = mp.enabled
                m.trans_type = mp.trans_type
                m.event_timer = mp.event_timer
                m.inhibit_time = None
                m.sync_start_value = None
                m.rtr_allowed = mp.rtr_allowed
                m.save()

    def _upload(self, j: Joint, key: ObjectKey) -> Any:
        var = find_variable(j.od, key)
        return var.decode_raw(j.node.sdo.upload(key.index, key.subindex))

    def _read_initial(self, j: Joint) -> None:
        """Seed every PDO value from the drive, so the first RPDOs repeat what
        the drive has (profile velocity...), targets hold the actual position
        and readings are valid before the first TPDO."""
        for node_map in (j.node.tpdo.map, j.node.rpdo.map):
            for m in node_map.values():
                if m.enabled:
                    for var in m.map:
                        var.raw = self._upload(j, ObjectKey(var.index, var.subindex))
        j.raw_position = self._upload(j, POSITION_ACTUAL)
        j.rx_var(ObjectKey(0x6040)).raw = 0
        if j.active_mode is not None:
            j.rx_var(ObjectKey(0x6060)).raw = j.active_mode
        for expr in (j.cfg.pos_from_device, j.cfg.vel_from_device, j.cfg.eff_from_device,
                     j.cfg.pos_to_device, j.cfg.vel_to_device, j.cfg.eff_to_device):
            for key in expr.objects:
                if j.tx_var(key) is None:
                    j.set_env(key, self._upload(j, key))
        j.heartbeat_ms = self._upload(j, PRODUCER_HEARTBEAT) if PRODUCER_HEARTBEAT.index in j.od else 0
        j.read()
        j.reset_targets()
        j.resend_all()

    def _start_node(self, j: Joint) -> None:
        j.node.nmt.send_command(NMT_START)
        j.nmt_state = "OPERATIONAL"
        j.last_heartbeat = j.pdo_seen_time = time.time()
        j.pdo_seen_cycle = self.cycles
        j.pdo_seen_ts = j.status_pdo_time()

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
        self._abort.clear()
        self._open()
        joints = list(self.joints.values())
        for j in joints:
            j.error = None
            j.halted = False
            j.homing = False
            j.last_emcy = ""
            self._configure(j)
        for j in joints:
            self._start_node(j)
        self._start_cycle()
        self._wait_cycles(2)
        err = self._go(joints, State.OPERATION_ENABLED, fault_reset=True)
        if err:
            raise _InitError("enable failed: " + err)
        wanted = {j.name: j.requested_mode if j.requested_mode is not None else j.active_mode for j in joints}
        for j in joints:
            j.ready = True
        for j in joints:
            with j.sdo_lock:
                method = self._upload(j, HOMING_METHOD)
            if method:
                r = self._home(j, method)
                if not r:
                    raise _InitError(r.message)
        for j in joints:
            mode = wanted[j.name]
            if mode is not None:
                j.active_mode = None  # force the switch
                r = self._switch(j, mode)
                if not r:
                    raise _InitError(r.message)
        self.initialized = True
        names = ", ".join("%s (node %d, PDOs from %s)" % (j.name, j.node_id, j.plan.source) for j in joints)
        return ok("initialized " + names)

    def _home(self, j: Joint, method: int) -> Result:
        r = self._switch(j, HM)
        if not r:
            return fail("homing of %s: %s" % (j.name, r.message))
        start = self.cycles
        with self._lock:
            j.homing = True
        sw_done = cia402.SW_HOMING_ATTAINED | cia402.SW_TARGET_REACHED

        def finished() -> bool:
            if j.error or self.cycles < start + 3:
                return bool(j.error)
            return (j.statusword & sw_done) == sw_done or bool(j.statusword & cia402.SW_HOMING_ERROR)
        done = self._wait(finished, self.homing_timeout)
        with self._lock:
            j.homing = False
            j.reset_targets()
        if j.error:
            return fail("homing of %s (method %d): %s" % (j.name, method, j.error))
        if j.statusword & cia402.SW_HOMING_ERROR:
            return fail("homing of %s (method %d) failed: homing error bit set%s" % (
                j.name, method, ", last EMCY " + j.last_emcy if j.last_emcy else ""))
        if not done:
            return fail("homing of %s (method %d) not finished within %g s" % (j.name, method, self.homing_timeout))
        log.info("%s homed (method %d)", j.name, method)
        return ok()

    # ====================================================== mode switch
    def switch_mode(self, joint_names: Iterable[str], mode: int) -> Result:
        """Put joints into a mode of operation through their switching_state;
        targets are reset to the actual position first, so nothing jumps.
        Before init, the mode is remembered and applied by init."""
        if isinstance(mode, bool) or not isinstance(mode, int) or mode not in SUPPORTED_DRIVE_MODES:
            return fail("mode %r is not supported (supported: %s)" % (
                mode, ", ".join("%d %s" % kv for kv in sorted(SUPPORTED_DRIVE_MODES.items()))))
        joints = []
        for name in joint_names:
            j = self.joint(name)
            if j is None:
                return self._unknown(name)
            joints.append(j)
        if not self.initialized:
            for j in joints:
                j.requested_mode = mode
            return ok("mode %d will be set at init" % mode)
        for j in joints:
            j.requested_mode = mode
            r = self._switch(j, mode)
            if not r:
                return r
        return ok()

    def _switch(self, j: Joint, mode: int) -> Result:
        if j.error:
            return fail("%s is in error (%s): call recover" % (j.name, j.error))
        if j.active_mode == mode and j.mode_display == mode and j.state == State.OPERATION_ENABLED:
            with self._lock:
                j.reset_targets()
            return ok()
        with self._lock:
            j.reset_targets()
        err = self._go([j], j.switching_state)
        if err:
            return fail("mode switch of %s: %s" % (j.name, err))
        with self._lock:
            j.active_mode = mode
        if not self._wait(lambda: j.mode_display == mode or bool(j.error), self.state_timeout) or j.error:
            return fail("%s did not confirm mode %s (0x6061 = %d)" % (j.name, cia402.mode_name(mode), j.mode_display))
        with self._lock:
            j.reset_targets()
        err = self._go([j], State.OPERATION_ENABLED)
        if err:
            return fail("mode switch of %s: %s" % (j.name, err))
        log.info("%s in mode %s", j.name, cia402.mode_name(mode))
        return ok()

    # ================================================ halt/recover/shutdown
    def halt(self) -> Result:
        """Stop motion, keep the drives powered (controlword halt bit; in
        cyclic modes the targets also hold the actual position)."""
        if not self.initialized:
            return fail("driver not initialized: call init")
        with self._lock:
            for j in self.joints.values():
                j.halted = True
                if j.mode_display in CYCLIC_MODES:
                    j.reset_targets()
        self._wait_cycles(2)
        return ok("halted")

    def recover(self) -> Result:
        """Fault reset and re-enable; targets are set to the actual position
        before enabling so that nothing jumps to a stale target."""
        if not self._service.acquire(blocking=False):
            return fail("another driver service is running")
        try:
            if not self.initialized:
                return fail("driver not initialized: call init")
            joints = list(self.joints.values())
            # python-can's threaded periodic senders end on a send error
            # (bus down): restart them, they are cheap to restart.
            if self._heartbeat is not None:
                self._heartbeat.stop()
                self._heartbeat.start()
            if self.sync is not None and not self._sync_in_cycle:
                self.sync.start(self.config.sync.interval_ms / 1000.0)
            for j in joints:
                if j.rebooted or j.nmt_state in ("STOPPED", "PRE-OPERATIONAL", "INITIALISING", "LOST"):
                    # A node that rebooted lost its configuration: redo it.
                    try:
                        self._configure(j)
                    except _InitError as e:
                        return fail("recover: %s" % e)
                    self._start_node(j)
            self._wait_cycles(2)
            with self._lock:
                for j in joints:
                    j.error = None
                    j.rebooted = False
                    j.reset_targets()
                    j.halted = False
            err = self._go(joints, State.OPERATION_ENABLED, fault_reset=True)
            if err:
                return fail("recover: " + err)
            self._wait_cycles(2)  # the cleared halt bit and held targets are out
            for j in joints:
                if j.active_mode is not None and j.mode_display != j.active_mode:
                    mode, j.active_mode = j.active_mode, None
                    r = self._switch(j, mode)
                    if not r:
                        return fail("recover: " + r.message)
            return ok("recovered")
        except Exception as e:
            log.exception("recover failed")
            return fail("recover failed: %s" % e)
        finally:
            self._service.release()

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
        problems = []
        joints = list(self.joints.values())
        if self._thread is not None:
            with self._lock:
                for j in joints:
                    j.halted = True
                    j.reset_targets()
            moving = [j for j in joints if j.state == State.OPERATION_ENABLED and not j.error]
            if moving:  # quick stop ramps down before the power stage goes off
                with self._lock:
                    for j in moving:
                        j.request_state(State.QUICK_STOP_ACTIVE)
                self._wait(lambda: all(j.state in (State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED)
                                       for j in moving), self.state_timeout)
            err = self._go([j for j in joints if j.state not in (State.FAULT, None)], State.SWITCH_ON_DISABLED)
            if err:
                problems.append(err)
        self._stop_cycle()
        if self.network is not None:
            for j in joints:
                try:
                    j.node.nmt.send_command(NMT_STOP)
                    j.nmt_state = "STOPPED"
                except (can.CanError, OSError) as e:
                    problems.append("NMT stop of %s: %s" % (j.name, e))
        for j in joints:
            j.ready = False
            j.target_state = None
            if j.active_mode is not None:
                j.requested_mode = j.active_mode
        self._close()
        self.initialized = False
        return problems

    def close(self) -> None:
        """Leave the drives safe and release the bus (node exit). A service
        still waiting (init homing...) is made to give up first."""
        self._abort.set()
        if self._service.acquire(timeout=10.0):
            self._service.release()
        self._abort.clear()  # shutdown's own waits (quick stop) must run
        if self.initialized or self.network is not None:
            self.shutdown()

    # ========================================================== objects
    def _object(self, node_name: str, obj: str) -> Tuple[Optional[Joint], Any, Optional[Result]]:
        j = self.joint(node_name)
        if j is None:
            return None, None, self._unknown(node_name)
        try:
            key = parse_object_key(obj)
            var = find_variable(j.od, key)
        except ObjectStringError as e:
            return None, None, fail(str(e))
        if self.network is None:
            return None, None, fail("driver not initialized: call init")
        return j, var, None

    def get_object(self, node_name: str, obj: str, cached: bool = False) -> Result:
        j, var, err = self._object(node_name, obj)
        if err is not None:
            return err
        key = ObjectKey(var.index, var.subindex)
        if not is_readable(var):
            return fail("object %s is write-only" % key)
        pdo_var = j.tx_var(key)
        if cached and pdo_var is not None:
            return ok(value=decode_value(var, pdo_var.raw))
        if cached and key in j.cache:
            return ok(value=decode_value(var, j.cache[key]))
        try:
            with j.sdo_lock:
                value = self._upload(j, key)
        except SdoAbortedError as e:
            return fail("reading %s from %s: %s" % (key, j.name, e))
        except SdoCommunicationError as e:
            return fail("reading %s from %s: no answer (%s)" % (key, j.name, e))
        j.cache[key] = value
        return ok(value=decode_value(var, value))

    def set_object(self, node_name: str, obj: str, value: str, cached: bool = False) -> Result:
        j, var, err = self._object(node_name, obj)
        if err is not None:
            return err
        key = ObjectKey(var.index, var.subindex)
        if key in DRIVER_OWNED:
            return fail("object %s is written by the driver every cycle: use the controllers "
                        "and services instead" % key)
        if not is_writable(var):
            return fail("object %s is read-only" % key)
        try:
            py_value = encode_value(var, value)
            data = var.encode_raw(py_value)
        except ObjectValueError as e:
            return fail(str(e))
        if cached and j.cache.get(key) == py_value:
            return ok("unchanged")
        try:
            with j.sdo_lock, self._lock:
                j.node.sdo.download(key.index, key.subindex, data)
                rx = j.rx_var(key)
                if rx is not None:  # keep the RPDO from writing the old value back
                    rx.raw = py_value
        except SdoAbortedError as e:
            return fail("writing %s to %s: %s" % (key, j.name, e))
        except SdoCommunicationError as e:
            return fail("writing %s to %s: no answer (%s)" % (key, j.name, e))
        j.cache[key] = py_value
        return ok()

    # ==================================================== ROS layer/diag
    def published_types(self) -> Dict[str, int]:
        """topic -> CANopen data type of the ROS layer's published objects."""
        out = {}
        for j in self.joints.values():
            for pub in j.cfg.publish:
                out[pub.topic] = find_variable(j.od, pub.key).data_type
        return out

    def read_published(self) -> Dict[str, Any]:
        """topic -> value of every ``publish`` object: from its TPDO when
        mapped, else the cache, read by SDO when forced (``!``) or never read.
        Objects that cannot be read are left out (and logged once)."""
        out: Dict[str, Any] = {}
        if self.network is None:
            return out
        for j in self.joints.values():
            for pub in j.cfg.publish:
                pdo_var = j.tx_var(pub.key)
                if pdo_var is not None and not pub.force:
                    out[pub.topic] = pdo_var.raw
                    continue
                if pub.force or pub.key not in j.cache:
                    try:
                        with j.sdo_lock:
                            j.cache[pub.key] = self._upload(j, pub.key)
                    except (SdoAbortedError, SdoCommunicationError) as e:
                        log.warning("publish %s: %s", pub.topic, e)
                        continue
                out[pub.topic] = j.cache[pub.key]
        return out

    def status(self) -> List[Dict[str, Any]]:
        """One dict per node for diagnostics."""
        out = []
        for j in self.joints.values():
            out.append({
                "name": j.name, "node_id": j.node_id, "nmt_state": j.nmt_state,
                "state": j.state.value if j.state else "unknown",
                "statusword": "0x%04X" % j.statusword,
                "mode": j.mode_name(), "mode_display": j.mode_display,
                "last_emcy": j.last_emcy, "error_register": "0x%02X" % j.error_register,
                "error": j.error or "", "halted": j.halted, "initialized": self.initialized,
                "pdo_mapping": j.plan.source,
            })
        return out

