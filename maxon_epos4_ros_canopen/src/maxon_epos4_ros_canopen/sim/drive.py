"""One virtual EPOS4 node: NMT slave, heartbeat, SDO server, PDOs, EMCY,
the CiA 402 device control and the operation modes, driving a motor model.

The node never touches the bus itself: frames go out through the
``transport(cob_id, data, remote)`` callable and come in through
``on_frame``; ``tick(now)`` advances time.  That keeps it usable from one
runner thread for many nodes (see runner.py).
"""
from __future__ import annotations

import math
from typing import Any, Callable, Dict, List, Optional, Tuple

import canopen

from .. import cia402
from .. import epos4_errors
from ..cia402 import OperationMode, State
from . import injection, motor as mm
from .objects import (ABORT_STORE, ABORT_VALUE_RANGE, Key,
                      ObjectStore, SdoAbort)
from .emcy import ErrorReport
from .heartbeat import HeartbeatConsumer, report_lost
from .modes import WINDOW_OFF, Demand, Mode, StopRamp, make_mode, position_limits
from .nonvolatile import NonVolatileMemory
from .pdo import Pdo, PdoSet
from .sdo import SdoServer

Transport = Callable[[int, bytes, bool], None]
# the states with the power stage on, and those of them that ramp to a stop
_POWERED = frozenset((State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE))
_RAMPING = frozenset((State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE))

NMT_INITIALISING, NMT_STOPPED, NMT_OPERATIONAL, NMT_PRE_OPERATIONAL = 0x00, 0x04, 0x05, 0x7F
SUPPORTED_MODES = frozenset(int(m) for m in OperationMode)
SAVE_SIGNATURE = 0x65766173  # "save"
LOAD_SIGNATURE = 0x64616F6C  # "load"
MAX_STEP = 0.02  # s
# The drive's control cycle: the profile generators and the motor's loops
# run at this rate whatever the length of a tick.
CONTROL_PERIOD = 0.0025  # s

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


def check_value(key: Key, value: Any) -> None:
    """The drive's own range checks of a written value (raises SdoAbort)."""
    index, sub = key
    if index == 0x6060 and value not in SUPPORTED_MODES:
        raise SdoAbort(ABORT_VALUE_RANGE, "mode %d" % value)
    if index in OPTION_CODES and value not in OPTION_CODES[index]:
        raise SdoAbort(ABORT_VALUE_RANGE, "option code %d of 0x%04X" % (value, index))
    if index == 0x1003 and value != 0:
        raise SdoAbort(ABORT_VALUE_RANGE, "only 0 clears the error history")
    if index == 0x1010 and sub >= 1 and value != SAVE_SIGNATURE:
        raise SdoAbort(ABORT_STORE, "signature")
    if index == 0x1011 and sub >= 1 and value != LOAD_SIGNATURE:
        raise SdoAbort(ABORT_STORE, "signature")


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
        self.memory = NonVolatileMemory(self.store)  # 0x1010 store / 0x1011 restore
        self.pdos = PdoSet()
        self.sdo = SdoServer(self.store, self._send_sdo, sdo_timeout)
        self.errors = ErrorReport(self.store, node_id, self._send,
                                  lambda: self.nmt_state != NMT_STOPPED)
        self.consumer = HeartbeatConsumer()
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
        self.demand = Demand()
        self.sync_interval = 0.0  # s between the last two SYNCs (CSP's interpolation period)
        self.power_on(now)

    # ------------------------------------------------------------------ NMT
    def power_on(self, now: float) -> None:
        """Power-on (also NMT reset node and the ``reboot`` fault)."""
        self.store.power_on()
        self.rated_torque = self.motor.configure(self.store.get)
        self.offset = float(self.store.get(0x6064, 0, 0)) - self.motor.position
        self.state = State.NOT_READY_TO_SWITCH_ON
        self.last_cw = 0
        self.mode = 0
        self.referenced = False
        self.errors.code = 0
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
        self.consumer.load(self.store, self.node_id)

    def _supervision_time(self, now: float) -> float:
        return self.bus_time() if self.bus_time is not None else now

    def _check_consumers(self, now: float) -> None:
        supervised = self._supervision_time(now)
        for node_id, silent in self.consumer.expired(supervised):
            report_lost(self.node_id, node_id, silent, self.consumer.timeouts.get(node_id, 0.0), now - supervised)
            self._heartbeat_lost(node_id, now)

    def _heartbeat_lost(self, node_id: int, now: float) -> None:
        """Heartbeat consumer timeout: EMCY 0x8130, then the abort connection
        option code 0x6007 (the fault reaction where the DCF lacks 0x6007),
        then the NMT reaction of 0x1029 sub 1."""
        option = self.store.get(0x6007, 0, None)
        if option is None or option == ABORT_CONNECTION_FAULT:
            self.raise_fault(epos4_errors.CAN_HEARTBEAT, now)
        else:
            self.errors.record(epos4_errors.CAN_HEARTBEAT)
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
        ids += [0x700 + n for n in self.consumer.timeouts]
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
        if self.consumer.watches(cob_id - 0x700) and not remote:
            if data:  # a heartbeat (or boot-up) of a watched node arms/feeds its entry
                self.consumer.heard(cob_id - 0x700, self._supervision_time(now))
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
        if self.state == State.OPERATION_ENABLED:
            self.active.on_sync(now)

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
        if self.pdos.owns(key[0]):
            self.pdos.check_write(self.store, key, value)
        elif key[0] == 0x1016 and key[1] >= 1:
            self.consumer.check_entry(self.store, key[1], value)
        else:
            check_value(key, value)

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
        elif index == 0x1010:
            self.memory.save(key[1])
        elif index == 0x1011:
            self.memory.restore_defaults(key[1])
        elif index == 0x1003:
            self.errors.clear_history()
        elif index in (0x3001, 0x3000, 0x3010, 0x6080, 0x6076):
            self.rated_torque = self.motor.configure(self.store.get)

    # -------------------------------------------------------------- faults
    def raise_fault(self, code: int, now: float) -> None:
        """An error occurs: EMCY, 0x1001, 0x1003, 0x603F, fault reaction."""
        self.errors.record(code)
        self.stopping = None
        if self.state not in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            self.state = State.FAULT_REACTION_ACTIVE  # transition 13
            self.demand.follow(self.position, self.motor.velocity)
        self._publish(now)

    # ----------------------------------------------------- device control
    def _on_controlword(self, cw: int, now: float) -> None:
        previous, self.last_cw = self.last_cw, cw
        reset_edge = cw & cia402.CW_FAULT_RESET_BIT and not previous & cia402.CW_FAULT_RESET_BIT
        if reset_edge and self.errors.code and self.state != State.FAULT:
            self.errors.clear()  # an error that needed no FAULT state (e.g. 0x6007 quick stop)
        self._device_command(cw, now, previous)
        if self.state == State.OPERATION_ENABLED and self.stopping is None:
            self.active.control(cw, previous, now)
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
            self.errors.clear()
        if old == State.OPERATION_ENABLED and new in (State.READY_TO_SWITCH_ON, State.SWITCHED_ON):
            # Shutdown (0x605B) / disable operation (0x605C) option 1: slow
            # down with the profile deceleration, then leave operation enabled.
            option = self.store.get(0x605B if new == State.READY_TO_SWITCH_ON else 0x605C, 0, 0)
            if option == 1:
                self.stopping = new
                self.demand.follow(self.position, self.motor.velocity)
                return
        self.state = new
        if new == State.OPERATION_ENABLED:
            self._reset_motion()
        elif new == State.QUICK_STOP_ACTIVE:
            self.demand.follow(self.position, self.motor.velocity)
            self.quick_stop_done = False  # set once a quick stop of option 5/6 is done
            if self.store.get(0x605A, 0, 2) == 0:
                self.state = State.SWITCH_ON_DISABLED  # option 0: disable drive at once

    def _set_mode(self, value: int) -> None:
        if value not in SUPPORTED_MODES or value == self.mode:
            return
        self.mode = value
        self._reset_motion()

    def _reset_motion(self) -> None:
        """Demand = actual and a fresh mode object: a new mode or enable
        starts without a jump and with nothing left of a previous move."""
        self.demand.follow(self.position if hasattr(self, "offset") else 0.0, self.motor.velocity)
        self.following_error = False
        self.quick_stop_done = False
        self.active: Mode = make_mode(self.mode, self)

    @property
    def position(self) -> float:
        return self.motor.position + self.offset

    def set_home(self, home: float) -> None:
        """Homing found its reference: the actual position becomes ``home``."""
        self.offset += home - self.position
        self.demand.follow(home, 0.0)
        self.referenced = True

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
        if self.consumer.seen:
            # a silent drive (cut off the bus) hears no heartbeat either: its
            # consumer trips and the drive reacts; only the EMCY is not heard
            self._check_consumers(now)
        if now >= self.next_heartbeat:
            if not self.heartbeat_stopped and not self.is_silent(now):
                self._send(0x700 + self.node_id, bytes([self.nmt_state]))
            self.next_heartbeat += self.heartbeat_period
            if self.next_heartbeat < now:
                self.next_heartbeat = now + self.heartbeat_period
        cycles = max(1, int(math.ceil(dt / CONTROL_PERIOD - 1e-9)))
        h = dt / cycles
        if self.state not in _POWERED and abs(self.motor.velocity) < mm.STANDSTILL_RPM:
            # Power stage off, rotor at rest: every control cycle would
            # compute the same (nothing moves, no state changes), so one
            # stands for all of them.
            cycles = 1
        self._cycles(cycles, h, now)
        self._publish(now)
        if self.nmt_state == NMT_OPERATIONAL and not self.is_silent(now):
            self._event_tpdos(now)

    def _cycles(self, cycles: int, h: float, now: float) -> None:
        """``cycles`` control cycles of ``h`` s up to ``now``. Each: the
        demand of the mode or of a stop ramp, the motor's loops, then the
        supervision (following error, software limits) while operation is
        enabled. Written as one loop, as calls and look-ups cost more than
        the arithmetic; within a tick only the drive runs, so what only
        the master writes (the controlword, the supervision objects) is
        read once."""
        m = self.motor
        demand = self.demand
        store = self.store
        halt = bool(self.last_cw & cia402.CW_HALT)
        window = store.get(0x6065, 0, WINDOW_OFF)
        lo, hi = position_limits(store)
        for i in range(cycles):
            t = now - (cycles - 1 - i) * h
            state = self.state
            ramp: Optional[StopRamp] = None
            if state == State.OPERATION_ENABLED and self.stopping is None:
                loop = self.active.step(h, t, halt)
            elif state in _RAMPING or state == State.OPERATION_ENABLED:  # stopping
                stopping = state == State.OPERATION_ENABLED
                ramp = StopRamp.for_state(state, stopping, store)
                loop = ramp.step(h, demand, store, m.inc_per_s_per_rpm)
            else:
                loop = mm.OFF
            m.cycle(h, loop, demand.position - self.offset, demand.velocity, demand.current,
                    demand.acceleration if loop == mm.POSITION else 0.0)
            demand.acceleration = 0.0
            if ramp is not None and ramp.done(demand, m):
                self._ramp_done(state, ramp)
            if loop == mm.OFF:
                demand.position, demand.velocity = m.position + self.offset, 0.0
            elif loop != mm.POSITION:
                demand.position = m.position + self.offset
            if state == State.OPERATION_ENABLED:  # _supervise
                active = self.active
                if active.position_controlled:
                    error = abs(demand.position - (m.position + self.offset))
                    self.following_error = window != WINDOW_OFF and error > window
                    if self.following_error:
                        self.raise_fault(epos4_errors.FOLLOWING_ERROR, t)
                        continue
                if not lo <= demand.position <= hi and active.software_limits:
                    self.raise_fault(epos4_errors.SOFTWARE_POSITION_LIMIT, t)

    def _ramp_done(self, state: State, ramp: StopRamp) -> None:
        """A stop ramp that began in ``state`` has ended with the rotor at rest."""
        if state == State.OPERATION_ENABLED:
            self.state, self.stopping = self.stopping, None  # transition 8 / 5 completes
        elif state == State.FAULT_REACTION_ACTIVE:
            self.state = State.FAULT  # transition 14
        elif not ramp.stays_in_quick_stop:
            self.state = State.SWITCH_ON_DISABLED  # transition 12 (automatic)
        else:
            self.quick_stop_done = True

    # ------------------------------------------------------------ publish
    def _publish(self, now: float) -> None:
        # Written unconditionally: a key of an object the DCF lacks is never
        # served (the SDO server and PDO mapping look at the OD, not here).
        values = self.store.values
        m = self.motor
        # round() of a float or an int is an int already
        position = round(m.position + self.offset)
        velocity = round(m.velocity)
        current = round(m.current * 1000.0)
        torque = round(m.current * m.torque_constant / self.rated_torque * 1000.0)
        demand = round(self.demand.position)
        values[(0x6064, 0)] = position
        values[(0x6062, 0)] = demand
        values[(0x60F4, 0)] = demand - position
        values[(0x606C, 0)] = values[(0x30D3, 1)] = velocity
        values[(0x606B, 0)] = round(self.demand.velocity)
        values[(0x30D1, 1)] = values[(0x30D1, 2)] = values[(0x30D0, 0)] = current
        values[(0x6077, 0)] = values[(0x30D2, 1)] = torque
        values[(0x6061, 0)] = self.mode
        values[(0x6041, 0)] = self.statusword()

    def statusword(self) -> int:
        state = self.state
        sw = cia402.statusword_state_bits(state) | cia402.SW_VOLTAGE_ENABLED | cia402.SW_REMOTE
        if self.referenced:
            sw |= cia402.SW_POSITION_REFERENCED
        if state == State.QUICK_STOP_ACTIVE and self.quick_stop_done:
            sw |= cia402.SW_TARGET_REACHED
        if state != State.OPERATION_ENABLED:
            return sw
        active = self.active
        if active.internal_limit:
            sw |= cia402.SW_INTERNAL_LIMIT_ACTIVE
        if active.reports_following_error and self.following_error:
            sw |= cia402.SW_FOLLOWING_ERROR
        return sw | active.status(self.last_cw)

    # ----------------------------------------------------- fault injection
    def inject(self, fault: str, now: float, error_code: int = 0, duration: float = 0.0) -> str:
        """Apply a test fault (injection.py); returns a description.  Raises ValueError."""
        return injection.inject(self, fault, now, error_code, duration)
