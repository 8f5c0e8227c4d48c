"""The virtual EPOS4's motion as the simulator computed it before its
per-tick loop (VirtualEpos4._cycles, MotorModel.cycle, the one cycle for a
drive at rest with its power stage off): one call per 2.5 ms control
cycle, the supervision in a call of its own, the motor's loops in
MotorModel.step's sub-steps, the cyclic modes through Mode.step and the
store's get, the actual values published through int(round()); and the
simulator's loop pass as it was (ReferenceSimulator). Frozen here, not
imported by the simulator: the reference test_sim_differential.py holds
the simulator to."""
import math
import time
from typing import Optional

import can

from maxon_epos4_ros_canopen import cia402, epos4_errors
from maxon_epos4_ros_canopen.cia402 import State
from maxon_epos4_ros_canopen.sim import Simulator
from maxon_epos4_ros_canopen.sim import motor as mm
from maxon_epos4_ros_canopen.sim.drive import CONTROL_PERIOD, MAX_STEP, NMT_OPERATIONAL, VirtualEpos4
from maxon_epos4_ros_canopen.sim.modes import (WINDOW_OFF, CyclicSyncPosition, CyclicSyncTorque,
                                               CyclicSyncVelocity, Idle, Mode, StopRamp, position_limits)
from maxon_epos4_ros_canopen.sim.motor import COAST_DECELERATION_RPM_S, RPM_TO_RAD_S, STANDSTILL_RPM


def motor_step(m: mm.MotorModel, dt: float, mode: int, position_ref: float = 0.0, velocity_ref: float = 0.0,
               current_ref: float = 0.0, acceleration_ref: float = 0.0) -> None:
    """MotorModel.step as it was, on ``m``."""
    if mode == mm.OFF and abs(m.velocity) < STANDSTILL_RPM:
        m.velocity = m.current = 0.0
        return
    steps = max(1, int(math.ceil(dt / 0.0025)))
    h = dt / steps
    k = m.inc_per_s_per_rpm
    for i in range(steps):
        if mode == mm.POSITION:
            back = dt - (i + 1) * h
            reference = position_ref - (velocity_ref - 0.5 * acceleration_ref * back) * back * k
            velocity = velocity_ref - acceleration_ref * back
            velocity_cmd = velocity + m.position_gain * (reference - m.position) / k
            _velocity_loop(m, velocity_cmd, acceleration_ref)
        elif mode == mm.VELOCITY:
            _velocity_loop(m, velocity_ref)
        elif mode == mm.CURRENT:
            current = max(-m.current_limit, min(m.current_limit, current_ref))
            if abs(m.velocity) >= m.max_speed and current * m.velocity > 0:
                current = m.friction * m.velocity * RPM_TO_RAD_S / m.torque_constant
            m.current = current
        else:
            m.current = 0.0
        _integrate(m, h)
    if mode == mm.OFF and abs(m.velocity) < STANDSTILL_RPM:
        m.velocity = 0.0


def _velocity_loop(m: mm.MotorModel, velocity_cmd: float, acceleration_ff: float = 0.0) -> None:
    velocity_cmd = max(-m.max_speed, min(m.max_speed, velocity_cmd))
    accel = ((velocity_cmd - m.velocity) / m.velocity_time_constant + acceleration_ff) * RPM_TO_RAD_S
    torque = m.inertia * accel + m.friction * m.velocity * RPM_TO_RAD_S
    current = torque / m.torque_constant
    m.current = max(-m.current_limit, min(m.current_limit, current))


def _integrate(m: mm.MotorModel, h: float) -> None:
    torque = m.torque_constant * m.current - m.friction * m.velocity * RPM_TO_RAD_S
    new_velocity = m.velocity + torque / m.inertia * h / RPM_TO_RAD_S
    if m.current == 0.0:
        new_velocity -= math.copysign(min(abs(new_velocity), COAST_DECELERATION_RPM_S * h), new_velocity)
        if new_velocity * m.velocity <= 0.0:
            new_velocity = 0.0
    m.position += 0.5 * (m.velocity + new_velocity) * h * m.inc_per_s_per_rpm
    m.velocity = new_velocity
    m.blocked = False
    if m.hard_stop_max is not None and m.position >= m.hard_stop_max:
        m.position, m.blocked = m.hard_stop_max, True
        m.velocity = min(m.velocity, 0.0)
    if m.hard_stop_min is not None and m.position <= m.hard_stop_min:
        m.position, m.blocked = m.hard_stop_min, True
        m.velocity = max(m.velocity, 0.0)


class _ReferenceCsp(CyclicSyncPosition):
    step = Mode.step

    def _interpolation_period(self) -> float:
        value = self.store.get(0x60C2, 1, 0)
        if value:
            return value * 10.0 ** self.store.get(0x60C2, 2, -3)
        return self.drive.sync_interval or 0.01

    def follow(self, dt: float, now: float) -> int:
        period = self._interpolation_period()
        frac = min(1.0, (now - self.t0) / period)
        demand = self.demand
        demand.position = self.start + (self.goal - self.start) * frac
        demand.velocity = (self.goal - self.start) / period / self.k if frac < 1.0 else 0.0
        demand.velocity += self.store.get(0x60B1, 0, 0)
        return mm.POSITION


class _ReferenceCsv(CyclicSyncVelocity):
    step = Mode.step


class _ReferenceCst(CyclicSyncTorque):
    step = Mode.step


class _ReferenceIdle(Idle):
    step = Mode.step


REFERENCE_MODES = {CyclicSyncPosition: _ReferenceCsp, CyclicSyncVelocity: _ReferenceCsv,
                   CyclicSyncTorque: _ReferenceCst, Idle: _ReferenceIdle}


class ReferenceEpos4(VirtualEpos4):
    """A VirtualEpos4 whose time advances as it did: every control cycle of
    a tick computed, one by one."""

    def tick(self, now: float) -> None:
        dt = now - self.t
        if dt <= 0:
            return
        self.t = now
        dt = min(dt, MAX_STEP)
        if self._delayed:
            due = [d for d in self._delayed if d[0] <= now]
            self._delayed = [d for d in self._delayed if d[0] > now]
            for _, cob, data in due:
                self._send(cob, data)
        self.sdo.check_timeout(now)
        if self.consumer.seen:
            self._check_consumers(now)
        if now >= self.next_heartbeat:
            if not self.heartbeat_stopped and not self.is_silent(now):
                self._send(0x700 + self.node_id, bytes([self.nmt_state]))
            self.next_heartbeat += self.heartbeat_period
            if self.next_heartbeat < now:
                self.next_heartbeat = now + self.heartbeat_period
        cycles = max(1, int(math.ceil(dt / CONTROL_PERIOD - 1e-9)))
        h = dt / cycles
        for i in range(cycles):
            self._motion(h, now - (cycles - 1 - i) * h)
        self._publish(now)
        if self.nmt_state == NMT_OPERATIONAL and not self.is_silent(now):
            self._event_tpdos(now)

    def _reset_motion(self) -> None:
        super()._reset_motion()
        reference = REFERENCE_MODES.get(type(self.active))
        if reference is not None:
            self.active = reference(self)

    def _publish(self, now: float) -> None:
        values = self.store.values
        m = self.motor
        position = int(round(self.position))
        velocity = int(round(m.velocity))
        current = int(round(m.current * 1000.0))
        torque = int(round(m.current * m.torque_constant / self.rated_torque * 1000.0))
        demand = int(round(self.demand.position))
        values[(0x6064, 0)] = position
        values[(0x6062, 0)] = demand
        values[(0x60F4, 0)] = demand - position
        values[(0x606C, 0)] = values[(0x30D3, 1)] = velocity
        values[(0x606B, 0)] = int(round(self.demand.velocity))
        values[(0x30D1, 1)] = values[(0x30D1, 2)] = values[(0x30D0, 0)] = current
        values[(0x6077, 0)] = values[(0x30D2, 1)] = torque
        values[(0x6061, 0)] = self.mode
        values[(0x6041, 0)] = self.statusword()

    def _motion(self, dt: float, now: float) -> None:
        state = self.state
        m = self.motor
        demand = self.demand
        stopping = state == State.OPERATION_ENABLED and self.stopping is not None
        ramp: Optional[StopRamp] = None
        if state == State.OPERATION_ENABLED and not stopping:
            loop = self.active.step(dt, now, bool(self.last_cw & cia402.CW_HALT))
        elif stopping or state in (State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE):
            ramp = StopRamp.for_state(state, stopping, self.store)
            loop = ramp.step(dt, demand, self.store, m.inc_per_s_per_rpm)
        else:
            loop = mm.OFF
        motor_step(m, dt, loop, demand.position - self.offset, demand.velocity, demand.current,
                   demand.acceleration if loop == mm.POSITION else 0.0)
        demand.acceleration = 0.0
        if ramp is not None and ramp.done(demand, m):
            if stopping:
                self.state, self.stopping = self.stopping, None
            elif state == State.FAULT_REACTION_ACTIVE:
                self.state = State.FAULT
            elif not ramp.stays_in_quick_stop:
                self.state = State.SWITCH_ON_DISABLED
            else:
                self.quick_stop_done = True
        if loop == mm.OFF:
            demand.position, demand.velocity = self.position, 0.0
        elif loop != mm.POSITION:
            demand.position = self.position
        if state == State.OPERATION_ENABLED:
            self._supervise(now)

    def _supervise(self, now: float) -> None:
        active = self.active
        if active.position_controlled:
            window = self.store.get(0x6065, 0, WINDOW_OFF)
            error = abs(self.demand.position - self.position)
            self.following_error = window != WINDOW_OFF and error > window
            if self.following_error:
                self.raise_fault(epos4_errors.FOLLOWING_ERROR, now)
                return
        lo, hi = position_limits(self.store)
        if not lo <= self.demand.position <= hi and active.software_limits:
            self.raise_fault(epos4_errors.SOFTWARE_POSITION_LIMIT, now)


class ReferenceSimulator(Simulator):
    """A Simulator whose loop passes run as they did: python-can's Message
    for each frame through handle(), the clock read at the start of each
    pass and of each wait, after each frame and at the end of every pass."""

    def _receive_message(self, timeout: float) -> Optional[can.Message]:
        try:
            msg = self.bus.recv(timeout=timeout)
        except can.CanError as exc:
            self.bus_error = str(exc)
            time.sleep(min(timeout, self.tick_period))
            return None
        self.bus_error = None
        return msg

    def step(self, timeout: float) -> None:
        entered = self.clock()
        due = entered + max(0.0, timeout)
        msg = self._receive_message(max(0.0, timeout))
        start = time.perf_counter()
        now = self.clock()
        stalled = self._stood_still(entered - self._clock_read) | self._stood_still(now - due)
        if self._routes_dirty:
            self._rebuild_routes()
        burst = 0
        empty_at = now
        while msg is not None:
            arrival = self._arrival.arrival(msg.timestamp, now)
            self._delivery.frame(arrival, self._empty_at, now)
            self.bus_time = max(self.bus_time, arrival)
            self.handle(msg, now)
            burst += 1
            msg = self._receive_message(0.0) if burst < 256 else None
            handled = empty_at = self.clock()
            stalled = self._stood_still(handled - now) or stalled
            if msg is not None:
                now = handled
        if burst < 256:
            self._empty_at = empty_at
            if not stalled:
                self.bus_time = max(self.bus_time, empty_at - self._delivery.delay(empty_at))
        while not self._calls.empty():
            fn, box = self._calls.get_nowait()
            try:
                box["result"] = fn()
            except Exception as exc:
                box["error"] = exc
            box["done"].set()
        if now >= self._next_tick:
            self._tick(now)
            self._next_tick = max(self._next_tick + self.tick_period, now)
        self.busy_time += time.perf_counter() - start
        self.cpu_seconds = time.thread_time() - self._cpu0
        self._clock_read = self.clock()

    def run(self, passes: Optional[int] = None) -> None:
        if self._next_tick is None:
            self._next_tick = self._clock_read = self.clock()
            self._cpu0 = time.thread_time()
            self._rebuild_routes()
        done = 0
        while not self._stop.is_set() and (passes is None or done < passes):
            done += 1
            self.step(self._next_tick - self.clock())
