"""One virtual EPOS4 node: NMT slave, heartbeat, SDO server, PDOs, EMCY,
the CiA 402 device control and the operation modes, driving a motor model.

The node never touches the bus itself: frames go out through the
``transport(cob_id, data, remote)`` callable and come in through
``on_frame``; ``tick(now)`` advances time.  That keeps it usable from one
runner thread for many nodes (see runner.py).
"""
from __future__ import annotations

import math
import struct
from typing import Any, Callable, Dict, List, Optional, Tuple

import canopen

from .. import cia402
from .. import epos4_errors
from ..cia402 import OperationMode, State
from . import motor as mm
from .objects import (ABORT_PARAMETER_INCOMPATIBLE, ABORT_STORE, ABORT_VALUE_RANGE, Key,
                      ObjectStore, SdoAbort)
from .pdo import COB_INVALID, Pdo, PdoSet
from .sdo import SdoServer

Transport = Callable[[int, bytes, bool], None]

NMT_INITIALISING, NMT_STOPPED, NMT_OPERATIONAL, NMT_PRE_OPERATIONAL = 0x00, 0x04, 0x05, 0x7F
SUPPORTED_MODES = frozenset(int(m) for m in OperationMode)
SAVE_SIGNATURE = 0x65766173  # "save"
LOAD_SIGNATURE = 0x64616F6C  # "load"
WINDOW_OFF = 0xFFFFFFFF
MAX_STEP = 0.02  # s
_EMCY = struct.Struct("<HB5s")

# Option codes the simulated EPOS4 accepts: CiA 402's values that the EPOS4
# implements (for 0x605A not 3/4/7/8, "slow down on current or voltage
# limit"); docs/virtual_epos4.md says which ranges are confirmed where.
OPTION_CODES: Dict[int, Tuple[int, ...]] = {
    0x6007: (0, 1, 2, 3),  # abort connection: none, fault, disable voltage, quick stop
    0x605A: (0, 1, 2, 5, 6),  # quick stop
    0x605B: (0, 1),  # shutdown: disable at once / slow down with 0x6084 first
    0x605C: (0, 1),  # disable operation: same choices
    0x605E: (0, 1, 2),  # fault reaction: coast / 0x6084 / 0x6085
}
ABORT_CONNECTION_NONE, ABORT_CONNECTION_FAULT, ABORT_CONNECTION_DISABLE_VOLTAGE, \
    ABORT_CONNECTION_QUICK_STOP = 0, 1, 2, 3
# 0x1029 sub 1, reaction of the NMT state to a communication error (CiA 301).
COMM_ERROR_PRE_OPERATIONAL, COMM_ERROR_NO_CHANGE, COMM_ERROR_STOPPED = 0, 1, 2


def consumer_entry(value: int) -> Tuple[int, float]:
    """0x1016 sub-index value -> (watched node id, timeout in s); (0, 0) = unused."""
    node_id, ms = (value >> 16) & 0xFF, value & 0xFFFF
    if not 1 <= node_id <= 127 or ms == 0:
        return 0, 0.0
    return node_id, ms / 1000.0


def _sign(x: float) -> float:
    return 1.0 if x > 0 else -1.0 if x < 0 else 0.0


def _ramp(v: float, target: float, accel: float, decel: float, dt: float) -> float:
    """Move ``v`` toward ``target``: ``accel`` when speeding up, ``decel`` when slowing."""
    if v == target:
        return v
    speeding_up = abs(target) > abs(v) and v * target >= 0
    step = (accel if speeding_up else decel) * dt
    if abs(target - v) <= step:
        return target
    return v + step * _sign(target - v)


class VirtualEpos4:
    """A simulated EPOS4 on node ``node_id`` with dictionary ``od``."""

    def __init__(self, node_id: int, od: canopen.ObjectDictionary, transport: Transport,
                 now: float, hard_stop: Optional[Tuple[float, float]] = None,
                 sdo_timeout: float = 1.0, on_routes_changed: Optional[Callable[[], None]] = None,
                 initial: Optional[Dict[Tuple[int, int], Any]] = None,
                 bus_time: Optional[Callable[[], float]] = None):
        self.on_routes_changed = on_routes_changed
        # The heartbeat consumer's clock: when the frame being handled
        # reached the host, or the time now once no frame waits (see
        # Simulator.bus_time). A real drive never falls behind the bus; this
        # process can, and must not take a backlog of its own for a silent
        # master. Without it, the time the frame is handled.
        self.bus_time = bus_time
        self.node_id = node_id
        self.transport = transport
        self.store = ObjectStore(od, initial)
        self.store.write_hook = self._check_write
        self.store.after_write = self._after_write
        self.pdos = PdoSet()
        self.sdo = SdoServer(self.store, self._send_sdo, sdo_timeout)
        self.motor = mm.MotorModel()
        if hard_stop is not None:
            self.motor.hard_stop_min, self.motor.hard_stop_max = hard_stop
        # fault injection
        self.silent_until: Optional[float] = None  # inf = until cleared
        self.heartbeat_stopped = False
        self.sdo_delay = 0.0
        self.corrupt_next = False
        self._delayed: List[Tuple[float, int, bytes]] = []
        self.sync_cob = 0x80
        self.t = now
        self.power_on(now)

    # ------------------------------------------------------------------ NMT
    def power_on(self, now: float) -> None:
        """Power-on (also NMT reset node and the ``reboot`` fault)."""
        self.store.power_on()
        self._apply_motor_data()
        self.offset = float(self.store.get(0x6064, 0, 0)) - self.motor.position
        self.state = State.NOT_READY_TO_SWITCH_ON
        self.last_cw = 0
        self.mode = 0
        self.referenced = False
        self.fault_code = 0
        self.stopping: Optional[State] = None  # target of a shutdown/disable operation slow-down
        self._reset_motion()
        self.state = State.SWITCH_ON_DISABLED  # transitions 0 and 1: self-test done
        self._set_mode(self.store.get(0x6060, 0, 0))
        self._reset_communication(now)
        self._publish(now)

    def _reset_communication(self, now: float) -> None:
        self.store.power_on(0x1000, 0x1FFF)
        self.pdos.load(self.store)
        self.sync_cob = self.store.get(0x1005, 0, 0x80) & 0x7FF
        self.nmt_state = NMT_PRE_OPERATIONAL
        self.guard_toggle = 0
        self._load_consumers()
        self._routes_changed()
        self._send(0x700 + self.node_id, b"\x00")  # boot-up
        self._schedule_heartbeat(now)

    def _schedule_heartbeat(self, now: float) -> None:
        period = self.store.get(0x1017, 0, 0) / 1000.0
        self.heartbeat_period = period
        self.next_heartbeat = now + period if period > 0 else math.inf

    def on_nmt(self, command: int, now: float) -> None:
        if self.is_silent(now):
            return
        if command == 0x01:
            entering = self.nmt_state != NMT_OPERATIONAL
            self.nmt_state = NMT_OPERATIONAL
            if entering:
                for tpdo in self.pdos.tpdos:
                    tpdo.last_data = None  # event PDOs send their first value
                for rpdo in self.pdos.rpdos:
                    rpdo.sampled = None  # one buffered before the drive left OPERATIONAL is stale
        elif command == 0x02:
            self.nmt_state = NMT_STOPPED
        elif command == 0x80:
            self.nmt_state = NMT_PRE_OPERATIONAL
        elif command == 0x81:
            self.power_on(now)
        elif command == 0x82:
            self._reset_communication(now)

    # ---------------------------------------------------- heartbeat consumer
    def _load_consumers(self) -> None:
        """(Re)read 0x1016: every entry starts unarmed (CiA 301: supervision
        begins with the first heartbeat received from the watched node)."""
        self.consumers: Dict[int, float] = {}  # watched node id -> timeout (s)
        self.heartbeat_seen: Dict[int, float] = {}  # armed entries: node id -> last heartbeat (bus time)
        for sub in range(1, 128):
            if (0x1016, sub) not in self.store:
                break
            node_id, timeout = consumer_entry(self.store.get(0x1016, sub, 0))
            if node_id and node_id != self.node_id:
                self.consumers[node_id] = timeout

    def _supervision_time(self, now: float) -> float:
        return self.bus_time() if self.bus_time is not None else now

    def _check_consumers(self, now: float) -> None:
        bus_now = self._supervision_time(now)
        for node_id, last in list(self.heartbeat_seen.items()):
            if bus_now - last > self.consumers[node_id]:
                del self.heartbeat_seen[node_id]  # unarmed until the next heartbeat
                self._heartbeat_lost(node_id, now)

    def _heartbeat_lost(self, node_id: int, now: float) -> None:
        """Heartbeat consumer timeout: EMCY 0x8130, then the abort connection
        option code 0x6007 (the fault reaction where the DCF lacks 0x6007),
        then the NMT reaction of 0x1029 sub 1."""
        option = self.store.get(0x6007, 0, None)
        if option is None or option == ABORT_CONNECTION_FAULT:
            self.raise_fault(epos4_errors.CAN_HEARTBEAT, now)
        else:
            self._record_error(epos4_errors.CAN_HEARTBEAT)
            if option == ABORT_CONNECTION_DISABLE_VOLTAGE:
                self._device_command(cia402.CW_DISABLE_VOLTAGE, now)
            elif option == ABORT_CONNECTION_QUICK_STOP:
                self._device_command(cia402.CW_QUICK_STOP, now)
        behaviour = self.store.get(0x1029, 1, COMM_ERROR_PRE_OPERATIONAL)
        if behaviour == COMM_ERROR_PRE_OPERATIONAL and self.nmt_state == NMT_OPERATIONAL:
            self.nmt_state = NMT_PRE_OPERATIONAL
        elif behaviour == COMM_ERROR_STOPPED:
            self.nmt_state = NMT_STOPPED
        self._publish(now)

    # -------------------------------------------------------------- routing
    def _routes_changed(self) -> None:
        if self.on_routes_changed is not None:
            self.on_routes_changed()

    def cob_ids(self) -> List[int]:
        """COB-IDs this node listens to besides NMT and SYNC."""
        ids = [0x600 + self.node_id, 0x700 + self.node_id]
        ids += [0x700 + n for n in self.consumers]
        ids += [p.cob_id for p in self.pdos.rpdos + self.pdos.tpdos if p.valid]
        return ids

    def is_silent(self, now: float) -> bool:
        if self.silent_until is None:
            return False
        if now >= self.silent_until:
            self.silent_until = None
            return False
        return True

    def on_frame(self, cob_id: int, data: bytes, remote: bool, now: float) -> None:
        if self.is_silent(now):
            return
        if cob_id == 0x600 + self.node_id:
            if self.nmt_state != NMT_STOPPED and not remote:
                self.sdo.on_request(data, now)
            return
        if cob_id - 0x700 in self.consumers and not remote:
            if data:  # a heartbeat (or boot-up) of a watched node arms/feeds its entry
                self.heartbeat_seen[cob_id - 0x700] = self._supervision_time(now)
            return
        if cob_id == 0x700 + self.node_id:
            if remote:  # node guarding
                self._send(cob_id, bytes([self.nmt_state | self.guard_toggle]))
                self.guard_toggle ^= 0x80
            return
        if self.nmt_state != NMT_OPERATIONAL:
            return
        for rpdo in self.pdos.rpdos:
            if rpdo.valid and rpdo.cob_id == cob_id and not remote:
                self._on_rpdo(rpdo, data, now)
                return
        if remote:
            for tpdo in self.pdos.tpdos:
                if tpdo.valid and tpdo.cob_id == cob_id and tpdo.rtr_allowed:
                    self.tick(now)
                    data_out = tpdo.sampled if tpdo.transmission_type == 252 and tpdo.sampled else \
                        tpdo.pack(self.store.values)
                    self._send(cob_id, data_out)
                    return

    # ------------------------------------------------------------------ PDO
    def _on_rpdo(self, rpdo: Pdo, data: bytes, now: float) -> None:
        if len(data) < rpdo.codec.size:
            self.raise_fault(epos4_errors.CAN_PDO_LENGTH, now)
            return
        if rpdo.synchronous:
            rpdo.sampled = bytes(data)  # CiA 301: takes effect at the next SYNC
        else:
            self._apply_rpdo(rpdo, data, now)

    def _apply_rpdo(self, rpdo: Pdo, data: bytes, now: float) -> None:
        values = self.store.values
        for key, value in rpdo.unpack(data):
            if key == (0x6060, 0) and value not in SUPPORTED_MODES:
                continue  # the EPOS4 keeps the mode it has
            values[key] = value
            if key[0] in (0x6040, 0x6060):
                self._after_write(key, value)

    def on_sync(self, now: float) -> None:
        if self.is_silent(now) or self.nmt_state != NMT_OPERATIONAL:
            return
        self.tick(now)
        if self.nmt_state != NMT_OPERATIONAL:
            # This advance found the master lost (0x1029 left OPERATIONAL):
            # a pre-operational drive applies none of the RxPDOs buffered for
            # this SYNC, and no TxPDO goes out.
            for rpdo in self.pdos.rpdos:
                rpdo.sampled = None
            return
        for tpdo in self.pdos.tpdos:  # sampled at SYNC reception
            if not tpdo.valid:
                continue
            ttype = tpdo.transmission_type
            if ttype == 0:
                data = tpdo.pack(self.store.values)
                if data != tpdo.last_data:
                    self._send_pdo(tpdo, data, now)
            elif ttype <= 240:
                tpdo.sync_counter += 1
                if tpdo.sync_counter >= ttype:
                    tpdo.sync_counter = 0
                    self._send_pdo(tpdo, tpdo.pack(self.store.values), now)
            elif ttype == 252:
                tpdo.sampled = tpdo.pack(self.store.values)
        for rpdo in self.pdos.rpdos:
            if rpdo.valid and rpdo.sampled is not None:
                data, rpdo.sampled = rpdo.sampled, None
                self._apply_rpdo(rpdo, data, now)
        if self.state == State.OPERATION_ENABLED and self.mode == OperationMode.CYCLIC_SYNC_POSITION:
            self._csp_new_target(now)

    def _send_pdo(self, tpdo: Pdo, data: bytes, now: float) -> None:
        tpdo.last_data = data
        tpdo.last_time = now
        self._send(tpdo.cob_id, data)

    def _event_tpdos(self, now: float) -> None:
        for tpdo in self.pdos.tpdos:
            if tpdo.valid and tpdo.transmission_type >= 254:
                data = tpdo.pack(self.store.values)
                if data != tpdo.last_data and now - tpdo.last_time >= tpdo.inhibit:
                    self._send_pdo(tpdo, data, now)

    # ------------------------------------------------------------- sending
    def _send(self, cob_id: int, data: bytes, remote: bool = False) -> None:
        if self.silent_until is not None:
            return
        if self.corrupt_next and data:
            self.corrupt_next = False
            data = bytes(b ^ 0xFF for b in data)
        self.transport(cob_id, data, remote)

    def _send_sdo(self, data: bytes) -> None:
        if self.sdo_delay > 0:
            self._delayed.append((self.t + self.sdo_delay, 0x580 + self.node_id, data))
        else:
            self._send(0x580 + self.node_id, data)

    # ------------------------------------------------------------ OD writes
    def _check_write(self, key: Key, value: Any) -> None:
        index, sub = key
        if self.pdos.owns(index):
            self.pdos.check_write(self.store, key, value)
        elif index == 0x6060 and value not in SUPPORTED_MODES:
            raise SdoAbort(ABORT_VALUE_RANGE, "mode %d" % value)
        elif index in OPTION_CODES and value not in OPTION_CODES[index]:
            raise SdoAbort(ABORT_VALUE_RANGE, "option code %d of 0x%04X" % (value, index))
        elif index == 0x1016 and sub >= 1:
            self._check_consumer_entry(sub, value)
        elif index == 0x1003 and value != 0:
            raise SdoAbort(ABORT_VALUE_RANGE, "only 0 clears the error history")
        elif index == 0x1010 and sub >= 1 and value != SAVE_SIGNATURE:
            raise SdoAbort(ABORT_STORE, "signature")
        elif index == 0x1011 and sub >= 1 and value != LOAD_SIGNATURE:
            raise SdoAbort(ABORT_STORE, "signature")

    def _check_consumer_entry(self, sub: int, value: int) -> None:
        node_id, _ = consumer_entry(value)
        if not node_id:
            return
        for other in range(1, 128):
            if (0x1016, other) not in self.store:
                break
            if other != sub and consumer_entry(self.store.get(0x1016, other, 0))[0] == node_id:
                # CiA 301: one node may be watched by one entry only
                raise SdoAbort(ABORT_PARAMETER_INCOMPATIBLE, "node %d already watched" % node_id)

    def _after_write(self, key: Key, value: Any) -> None:
        index = key[0]
        if index == 0x6040:
            self._on_controlword(value, self.t)
        elif index == 0x6060:
            self._set_mode(value)
            self._publish(self.t)
        elif self.pdos.owns(index):
            self.pdos.load_one(self.store, index)
            self._routes_changed()
        elif index == 0x1017:
            self._schedule_heartbeat(self.t)
        elif index == 0x1016:
            self._load_consumers()
            self._routes_changed()
        elif index == 0x1005:
            self.sync_cob = value & 0x7FF
            self._routes_changed()
        elif index == 0x1003:
            for sub in range(1, 256):
                if (0x1003, sub) not in self.store:
                    break
                self.store.set(0x1003, sub, 0)
        elif index in (0x3001, 0x3000, 0x3010, 0x6080, 0x6076):
            self._apply_motor_data()

    def _apply_motor_data(self) -> None:
        get = self.store.get
        m = self.motor
        resolution = get(0x3000, 5, 0) or 4 * get(0x3010, 1, 0) or 2000
        m.increments_per_turn = float(resolution)
        kt = get(0x3001, 5, 0) * 1e-6
        m.torque_constant = kt if kt > 0 else 0.1
        limit = get(0x3001, 2, 0) / 1000.0
        m.current_limit = limit if limit > 0 else 10.0
        m.max_speed = float(get(0x6080, 0, 0) or 5000)
        rated = get(0x6076, 0, 0) * 1e-6
        nominal = get(0x3001, 1, 0) / 1000.0
        self.rated_torque = rated if rated > 0 else m.torque_constant * (nominal or 1.0)

    # -------------------------------------------------------------- faults
    def raise_fault(self, code: int, now: float) -> None:
        """An error occurs: EMCY, 0x1001, 0x1003, 0x603F, fault reaction."""
        self._record_error(code)
        self.stopping = None
        if self.state not in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            self.state = State.FAULT_REACTION_ACTIVE  # transition 13
            self.v_dem = self.motor.velocity
            self.p_dem = self.position
        self._publish(now)

    def _record_error(self, code: int) -> None:
        """EMCY, 0x1001, 0x1003, 0x603F; no change of the power state."""
        register = epos4_errors.error_register(code)
        self.fault_code = code
        self.store.set(0x603F, 0, code)
        self.store.set(0x1001, 0, register)
        self._push_history(code)
        self._emcy(code, register)

    def _clear_error(self) -> None:
        self.fault_code = 0
        self.store.set(0x603F, 0, 0)
        self.store.set(0x1001, 0, 0)
        self._emcy(0x0000, 0)

    def _push_history(self, code: int) -> None:
        subs = [s for s in range(1, 256) if (0x1003, s) in self.store]
        if not subs:
            return
        for sub in reversed(subs[1:]):
            self.store.set(0x1003, sub, self.store.get(0x1003, sub - 1))
        self.store.set(0x1003, 1, code)
        self.store.set(0x1003, 0, min(len(subs), self.store.get(0x1003, 0) + 1))

    def _emcy(self, code: int, register: int) -> None:
        cob = self.store.get(0x1014, 0, 0x80 + self.node_id)
        if cob & COB_INVALID or self.nmt_state == NMT_STOPPED:
            return
        self._send(cob & 0x7FF, _EMCY.pack(code, register, bytes(5)))

    # ----------------------------------------------------- device control
    def _on_controlword(self, cw: int, now: float) -> None:
        previous, self.last_cw = self.last_cw, cw
        reset_edge = cw & cia402.CW_FAULT_RESET_BIT and not previous & cia402.CW_FAULT_RESET_BIT
        if reset_edge and self.fault_code and self.state != State.FAULT:
            self._clear_error()  # an error that needed no FAULT state (e.g. 0x6007 quick stop)
        self._device_command(cw, now, previous)
        if self.state == State.OPERATION_ENABLED and self.stopping is None:
            self._mode_control(cw, previous, now)
        self._publish(now)

    def _device_command(self, cw: int, now: float, previous: Optional[int] = None) -> None:
        """The power-state part of a controlword (also the drive's own
        commands, e.g. the abort connection option code)."""
        if previous is None:
            previous = self.last_cw
        old = self.state
        new = cia402.apply_controlword(old, cw, previous, self.store.get(0x605A, 0, 2))
        if old == State.OPERATION_ENABLED and self.stopping is not None:
            if new == State.OPERATION_ENABLED:  # enable operation again: the slow-down is cancelled
                self.stopping = None
                self._reset_motion()
                return
            if new == self.stopping:
                return  # the same command again: the slow-down goes on
        if new == old:
            return
        self.stopping = None
        if old == State.FAULT:  # fault reset: the errors are gone
            self._clear_error()
        if old == State.OPERATION_ENABLED and new in (State.READY_TO_SWITCH_ON, State.SWITCHED_ON):
            # Shutdown (0x605B) / disable operation (0x605C) option 1: slow
            # down with the profile deceleration, then leave operation enabled.
            option = self.store.get(0x605B if new == State.READY_TO_SWITCH_ON else 0x605C, 0, 0)
            if option == 1:
                self.stopping = new
                self.v_dem = self.motor.velocity
                self.p_dem = self.position
                return
        self.state = new
        if new == State.OPERATION_ENABLED:
            self._reset_motion()
        elif new == State.QUICK_STOP_ACTIVE:
            self.v_dem = self.motor.velocity
            self.p_dem = self.position
            self.target_reached = False  # set again once the quick stop is done
            if self.store.get(0x605A, 0, 2) == 0:
                self.state = State.SWITCH_ON_DISABLED  # option 0: disable drive at once

    def _set_mode(self, value: int) -> None:
        if value not in SUPPORTED_MODES or value == self.mode:
            return
        self.mode = value
        self._reset_motion()

    def _reset_motion(self) -> None:
        """Demand = actual: a new mode or enable starts without a jump."""
        self.p_dem = self.position if hasattr(self, "offset") else 0.0
        self.v_dem = self.motor.velocity
        self.i_dem = 0.0
        self.ppm_target: Optional[float] = None
        self.ppm_pending: Optional[float] = None
        self.ack = False
        self.target_reached = False
        self.in_window_since: Optional[float] = None
        self.internal_limit = False
        self.following_error = False
        self.homing: Optional[str] = None  # None, search, back, done, error
        self.homing_stop = 0.0
        self.csp_start = self.csp_goal = self.p_dem
        self.csp_t0 = self.t
        self.last_sync = None

    @property
    def position(self) -> float:
        return self.motor.position + self.offset

    def _limits(self) -> Tuple[float, float]:
        lo, hi = self.store.get(0x607D, 1, -2 ** 31), self.store.get(0x607D, 2, 2 ** 31 - 1)
        if lo >= hi:  # 0/0 in EPOS Studio exports: limits not in use
            return -math.inf, math.inf
        return float(lo), float(hi)

    def _clamp_target(self, target: float) -> float:
        lo, hi = self._limits()
        clamped = min(hi, max(lo, target))
        self.internal_limit = clamped != target
        return clamped

    def _mode_control(self, cw: int, previous: int, now: float) -> None:
        rising = cw & cia402.CW_NEW_SET_POINT and not previous & cia402.CW_NEW_SET_POINT
        falling = previous & cia402.CW_NEW_SET_POINT and not cw & cia402.CW_NEW_SET_POINT
        if self.mode == OperationMode.PROFILE_POSITION:
            if rising:
                self._ppm_new_set_point(cw)
            elif falling:
                self.ack = False
        elif self.mode == OperationMode.HOMING:
            if rising:
                self._homing_start(now)
            elif falling and self.homing in ("search", "back"):
                self.homing = None  # 1 -> 0 interrupts homing
                self.v_dem = self.motor.velocity

    def _ppm_new_set_point(self, cw: int) -> None:
        raw = float(self.store.get(0x607A, 0, 0))
        moving = self.ppm_target is not None and not self.target_reached
        if cw & cia402.CW_RELATIVE:
            base = self.ppm_pending if self.ppm_pending is not None else \
                self.ppm_target if self.ppm_target is not None else self.p_dem
            raw += base
        target = self._clamp_target(raw)
        if not moving or cw & cia402.CW_CHANGE_SET_IMMEDIATELY:
            self.ppm_target, self.ppm_pending = target, None
        elif self.ppm_pending is None:
            self.ppm_pending = target  # buffered: starts when the current one ends
        else:
            return  # buffer full: no acknowledge
        self.ack = True
        self.target_reached = False
        self.in_window_since = None

    def _homing_start(self, now: float) -> None:
        method = self.store.get(0x6098, 0, 0)
        self.target_reached = False
        self.referenced = False
        if method in (35, 37):
            self._set_home()
        elif method in (-3, -4):
            self.homing = "search"
            self.homing_direction = 1.0 if method == -3 else -1.0
            self.v_dem = 0.0
        else:
            self.homing = "error"  # methods with switches/index: not simulated

    def _set_home(self) -> None:
        home = float(self.store.get(0x30B0, 0, 0))
        self.offset += home - self.position
        self.p_dem = home
        self.v_dem = 0.0
        self.homing = "done"
        self.referenced = True
        self.target_reached = True

    def _csp_new_target(self, now: float) -> None:
        goal = float(self.store.get(0x607A, 0, 0))
        self.csp_start = self.p_dem
        self.csp_goal = self._clamp_target(goal)
        if self.last_sync is not None:
            self.sync_interval = now - self.last_sync
        self.last_sync = now
        self.csp_t0 = now

    def _interpolation_period(self) -> float:
        value = self.store.get(0x60C2, 1, 0)
        if value:
            return value * 10.0 ** self.store.get(0x60C2, 2, -3)
        return getattr(self, "sync_interval", 0.01) or 0.01

    # ---------------------------------------------------------------- time
    def tick(self, now: float) -> None:
        dt = now - self.t
        if dt <= 0:
            return
        self.t = now
        # A starved loop must not integrate one huge step (the position loop
        # would overshoot): the simulated time then runs slower than the clock.
        dt = min(dt, MAX_STEP)
        if self._delayed:
            due = [d for d in self._delayed if d[0] <= now]
            self._delayed = [d for d in self._delayed if d[0] > now]
            for _, cob, data in due:
                self._send(cob, data)
        self.sdo.check_timeout(now)
        if self.heartbeat_seen:
            # a silent drive (cut off the bus) hears no heartbeat either: its
            # consumer trips and the drive reacts; only the EMCY is not heard
            self._check_consumers(now)
        if now >= self.next_heartbeat:
            if not self.heartbeat_stopped and not self.is_silent(now):
                self._send(0x700 + self.node_id, bytes([self.nmt_state]))
            self.next_heartbeat += self.heartbeat_period
            if self.next_heartbeat < now:
                self.next_heartbeat = now + self.heartbeat_period
        self._motion(dt, now)
        self._publish(now)
        if self.nmt_state == NMT_OPERATIONAL and not self.is_silent(now):
            self._event_tpdos(now)

    def _motion(self, dt: float, now: float) -> None:
        state = self.state
        m = self.motor
        k = m.inc_per_s_per_rpm
        stopping = state == State.OPERATION_ENABLED and self.stopping is not None
        ramp_option = None  # the option code of a stop ramp in progress
        if state == State.OPERATION_ENABLED and not stopping:
            mode, pref, vref, iref = self._mode_step(dt, now)
        elif stopping or state in (State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE):
            if stopping:
                ramp_option = 1  # slow down with the profile deceleration
            else:
                ramp_option = self.store.get(0x605A if state == State.QUICK_STOP_ACTIVE else 0x605E, 0, 2)
            decel = self.store.get(0x6084 if ramp_option in (1, 5) else 0x6085, 0, 10000)
            if ramp_option == 0:
                self.v_dem = 0.0
                mode, pref, vref, iref = mm.OFF, 0.0, 0.0, 0.0
            else:
                v_before = self.v_dem
                self.v_dem = _ramp(self.v_dem, 0.0, decel, decel, dt)
                # the distance the ramp covers in this step (trapezoid): a
                # coarse step of a starved loop must not leave the demand
                # short of the rotor, which the position loop would then
                # pull back
                self.p_dem += 0.5 * (v_before + self.v_dem) * k * dt
                mode, pref, vref, iref = mm.POSITION, self.p_dem - self.offset, self.v_dem, 0.0
        else:
            mode, pref, vref, iref = mm.OFF, 0.0, 0.0, 0.0
        m.step(dt, mode, pref, vref, iref)
        # The ramp ends, and a power stage goes off, only with the rotor at
        # rest after this step.
        if ramp_option is not None and self.v_dem == 0.0 and abs(m.velocity) < mm.STANDSTILL_RPM:
            if stopping:
                self.state, self.stopping = self.stopping, None  # transition 8 / 5 completes
            elif state == State.FAULT_REACTION_ACTIVE:
                self.state = State.FAULT  # transition 14
            elif ramp_option in (0, 1, 2):
                self.state = State.SWITCH_ON_DISABLED  # transition 12 (automatic)
            else:
                self.target_reached = True
        if mode == mm.OFF:
            self.p_dem, self.v_dem = self.position, 0.0
        elif mode != mm.POSITION:
            self.p_dem = self.position  # velocity/torque control: demand follows actual
        if state == State.OPERATION_ENABLED:
            self._supervise(now)

    def _mode_step(self, dt: float, now: float) -> Tuple[int, float, float, float]:
        """Demand generator of the active mode -> motor loop references."""
        get = self.store.get
        k = self.motor.inc_per_s_per_rpm
        halt = self.last_cw & cia402.CW_HALT
        mode = self.mode
        if mode == OperationMode.PROFILE_POSITION:
            self._ppm_step(dt, now, halt)
        elif mode == OperationMode.PROFILE_VELOCITY:
            target = 0.0 if halt else float(get(0x60FF, 0, 0))
            vmax = float(get(0x607F, 0, 50000))
            self.internal_limit = abs(target) > vmax
            target = max(-vmax, min(vmax, target))
            self.v_dem = _ramp(self.v_dem, target, get(0x6083, 0, 10000), get(0x6084, 0, 10000), dt)
            self.target_reached = abs(self.motor.velocity - target) <= 10.0
            return mm.VELOCITY, 0.0, self.v_dem, 0.0
        elif mode == OperationMode.HOMING:
            return self._homing_step(dt, halt)
        elif mode == OperationMode.CYCLIC_SYNC_POSITION:
            period = self._interpolation_period()
            frac = min(1.0, (now - self.csp_t0) / period)
            self.p_dem = self.csp_start + (self.csp_goal - self.csp_start) * frac
            self.v_dem = (self.csp_goal - self.csp_start) / period / k if frac < 1.0 else 0.0
            self.v_dem += get(0x60B1, 0, 0)
        elif mode == OperationMode.CYCLIC_SYNC_VELOCITY:
            vmax = float(get(0x6080, 0, 50000))
            self.v_dem = max(-vmax, min(vmax, float(get(0x60FF, 0, 0) + get(0x60B1, 0, 0))))
            return mm.VELOCITY, 0.0, self.v_dem, 0.0
        elif mode == OperationMode.CYCLIC_SYNC_TORQUE:
            torque = (get(0x6071, 0, 0) + get(0x60B2, 0, 0)) / 1000.0 * self.rated_torque
            self.i_dem = torque / self.motor.torque_constant
            return mm.CURRENT, 0.0, 0.0, self.i_dem
        return mm.POSITION, self.p_dem - self.offset, self.v_dem, 0.0

    def _ppm_step(self, dt: float, now: float, halt: int) -> None:
        get = self.store.get
        k = self.motor.inc_per_s_per_rpm
        accel = get(0x6083, 0, 10000) * k
        decel = get(0x6084, 0, 10000) * k
        v = self.v_dem * k  # inc/s
        if halt or self.ppm_target is None:
            v = _ramp(v, 0.0, accel, decel, dt)
            self.p_dem += v * dt
            if halt and v == 0.0:
                self.target_reached = True
            self.v_dem = v / k
            return
        vmax = min(get(0x6081, 0, 1000), get(0x607F, 0, 50000)) * k
        if get(0x6081, 0, 1000) > get(0x607F, 0, 50000):
            self.internal_limit = True
        d = self.ppm_target - self.p_dem
        if d != 0.0:
            self.target_reached = False  # e.g. resuming after halt
        direction = _sign(d)
        if v * direction < 0:  # moving away after a change: brake first
            v = _ramp(v, 0.0, accel, decel, dt)
            self.p_dem += v * dt
        else:
            allowed = math.sqrt(2.0 * decel * abs(d))
            speed = min(abs(v) + accel * dt, vmax, allowed)
            if speed * dt >= abs(d):
                self.p_dem, v = self.ppm_target, 0.0
            else:
                v = speed * direction
                self.p_dem += v * dt
        self.v_dem = v / k
        if self.p_dem == self.ppm_target and v == 0.0:
            if self.ppm_pending is not None:
                self.ppm_target, self.ppm_pending = self.ppm_pending, None
                return
            window = get(0x6067, 0, WINDOW_OFF)
            inside = window == WINDOW_OFF or abs(self.position - self.ppm_target) <= window
            if not inside:
                self.in_window_since = None
            elif self.in_window_since is None:
                self.in_window_since = now
            if inside and now - self.in_window_since >= get(0x6068, 0, 0) / 1000.0:
                self.target_reached = True

    def _homing_step(self, dt: float, halt: int) -> Tuple[int, float, float, float]:
        get = self.store.get
        accel = get(0x609A, 0, 1000)
        if self.homing == "search" and not halt:
            target = self.homing_direction * get(0x6099, 1, 100)
            self.v_dem = _ramp(self.v_dem, target, accel, accel, dt)
            if abs(self.motor.current) * 1000.0 >= get(0x30B2, 0, 500) and self.motor.blocked:
                self.homing = "back"
                self.homing_stop = self.position
                self.v_dem = 0.0
            return mm.VELOCITY, 0.0, self.v_dem, 0.0
        if self.homing == "back" and not halt:
            k = self.motor.inc_per_s_per_rpm
            goal = self.homing_stop - self.homing_direction * get(0x30B1, 0, 0)
            d = goal - self.p_dem
            speed = min(abs(self.v_dem) * k + accel * k * dt, get(0x6099, 2, 10) * k,
                        math.sqrt(2.0 * accel * k * abs(d)))
            if self.p_dem == goal or speed * dt >= abs(d):
                self.p_dem, self.v_dem = goal, 0.0
                settled = abs(self.position - goal) < 1.0 and abs(self.motor.velocity) < 1.0
                if settled:  # the EPOS4 sets the home position once at rest
                    self._set_home()
            else:
                self.v_dem = speed * _sign(d) / k
                self.p_dem += self.v_dem * k * dt
            return mm.POSITION, self.p_dem - self.offset, self.v_dem, 0.0
        # halted, idle, done or error: hold position
        self.v_dem = _ramp(self.v_dem, 0.0, accel, accel, dt)
        self.p_dem += self.v_dem * self.motor.inc_per_s_per_rpm * dt
        return mm.POSITION, self.p_dem - self.offset, self.v_dem, 0.0

    def _supervise(self, now: float) -> None:
        position_mode = self.mode in (OperationMode.PROFILE_POSITION, OperationMode.CYCLIC_SYNC_POSITION,
                                      OperationMode.HOMING)
        if position_mode:
            window = self.store.get(0x6065, 0, WINDOW_OFF)
            error = abs(self.p_dem - self.position)
            self.following_error = window != WINDOW_OFF and error > window
            if self.following_error:
                self.raise_fault(epos4_errors.FOLLOWING_ERROR, now)
                return
        lo, hi = self._limits()
        if not lo <= self.p_dem <= hi and self.mode != OperationMode.HOMING:
            self.raise_fault(epos4_errors.SOFTWARE_POSITION_LIMIT, now)

    # ------------------------------------------------------------ publish
    def _publish(self, now: float) -> None:
        # Written unconditionally: a key of an object the DCF lacks is never
        # served (the SDO server and PDO mapping look at the OD, not here).
        values = self.store.values
        m = self.motor
        position = int(round(self.position))
        velocity = int(round(m.velocity))
        current = int(round(m.current * 1000.0))
        torque = int(round(m.current * m.torque_constant / self.rated_torque * 1000.0))
        demand = int(round(self.p_dem))
        values[(0x6064, 0)] = position
        values[(0x6062, 0)] = demand
        values[(0x60F4, 0)] = demand - position
        values[(0x606C, 0)] = values[(0x30D3, 1)] = velocity
        values[(0x606B, 0)] = int(round(self.v_dem))
        values[(0x30D1, 1)] = values[(0x30D1, 2)] = values[(0x30D0, 0)] = current
        values[(0x6077, 0)] = values[(0x30D2, 1)] = torque
        values[(0x6061, 0)] = self.mode
        values[(0x6041, 0)] = self.statusword()

    def statusword(self) -> int:
        state = self.state
        sw = cia402.statusword_state_bits(state) | cia402.SW_VOLTAGE_ENABLED | cia402.SW_REMOTE
        if self.referenced:
            sw |= cia402.SW_POSITION_REFERENCED
        if state == State.QUICK_STOP_ACTIVE and self.target_reached:
            sw |= cia402.SW_TARGET_REACHED
        if state != State.OPERATION_ENABLED:
            return sw
        if self.internal_limit:
            sw |= cia402.SW_INTERNAL_LIMIT_ACTIVE
        mode = self.mode
        if mode == OperationMode.PROFILE_POSITION:
            if self.target_reached or self.ppm_target is None and self.v_dem == 0.0:
                sw |= cia402.SW_TARGET_REACHED
            if self.ack:
                sw |= cia402.SW_SET_POINT_ACKNOWLEDGE
            if self.following_error:
                sw |= cia402.SW_FOLLOWING_ERROR
        elif mode == OperationMode.PROFILE_VELOCITY:
            if self.target_reached:
                sw |= cia402.SW_TARGET_REACHED
            if abs(self.motor.velocity) <= 10.0:
                sw |= cia402.SW_SPEED
        elif mode == OperationMode.HOMING:
            if self.homing == "done":
                sw |= cia402.SW_HOMING_ATTAINED | cia402.SW_TARGET_REACHED
            elif self.homing == "error":
                sw |= cia402.SW_HOMING_ERROR | cia402.SW_TARGET_REACHED
            elif self.homing is None or self.last_cw & cia402.CW_HALT:
                if self.v_dem == 0.0:
                    sw |= cia402.SW_TARGET_REACHED
        else:
            sw |= cia402.SW_DRIVE_FOLLOWS_COMMAND
            if self.following_error:
                sw |= cia402.SW_FOLLOWING_ERROR
        return sw

    # ----------------------------------------------------- fault injection
    def inject(self, fault: str, now: float, error_code: int = 0, duration: float = 0.0) -> str:
        """Apply a test fault; returns a description.  Raises ValueError."""
        if fault == "emcy":
            if not 0 < error_code <= 0xFFFF:
                raise ValueError("emcy needs an error_code between 0x0001 and 0xFFFF")
            self.raise_fault(error_code, now)
            return "raised %s" % epos4_errors.describe(error_code)
        if fault == "silent":
            if duration < 0:
                raise ValueError("silent needs duration >= 0 (0 = until clear)")
            self.silent_until = now + duration if duration > 0 else math.inf
            return "silent for %s" % ("ever (until clear)" if duration <= 0 else "%.3f s" % duration)
        if fault == "heartbeat_stop":
            self.heartbeat_stopped = True
            return "heartbeat stopped"
        if fault == "reboot":
            self.silent_until = None
            self.power_on(now)
            return "rebooted"
        if fault == "sdo_delay":
            if duration < 0:
                raise ValueError("sdo_delay needs duration >= 0")
            self.sdo_delay = duration
            return "SDO answers delayed by %.3f s" % duration
        if fault == "corrupt_frame":
            self.corrupt_next = True
            return "next frame corrupted"
        if fault == "clear":
            self.silent_until = None
            self.heartbeat_stopped = False
            self.sdo_delay = 0.0
            self.corrupt_next = False
            return "injected faults cleared"
        raise ValueError("unknown fault %r (emcy, silent, heartbeat_stop, reboot, sdo_delay, "
                         "corrupt_frame, clear)" % fault)
