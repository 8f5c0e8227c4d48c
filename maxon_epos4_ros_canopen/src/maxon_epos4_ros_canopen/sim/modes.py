"""The operation modes of the virtual EPOS4 and its stop ramps, one object each.

A mode knows its target object, how it follows its set-point (its profile
generator, run once per control cycle), how it holds when halted, which
controlword bits it answers (the PPM new set-point handshake, the homing
start) and which statusword bits it reports. The drive asks its mode; a new
mode or an enable operation makes a new mode object, so that nothing of a
previous move survives.

All of them write the drive's demand (``Demand``): the values the EPOS4
publishes as 0x6062/0x606B and hands to its position, velocity or current
loop.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Dict, Optional, Tuple, Type

from .. import cia402
from ..cia402 import OperationMode, State
from . import motor as mm
from .profile import PointToPoint, ramp

if TYPE_CHECKING:  # pragma: no cover
    from .drive import VirtualEpos4

Key = Tuple[int, int]
WINDOW_OFF = 0xFFFFFFFF
# Stop option codes (0x605A quick stop, 0x605E fault reaction) and what they do.
STOP_COAST = 0  # disable the power stage at once
STOP_PROFILE = (1, 5)  # slow down with 0x6084 profile deceleration
STOP_QUICK = (2, 6)  # slow down with 0x6085 quick stop deceleration


class Demand:
    """The drive's demand: position (drive units), velocity (rpm),
    acceleration (rpm/s, the feed-forward of one control cycle), current (A)."""

    __slots__ = ("position", "velocity", "acceleration", "current")

    def __init__(self, position: float = 0.0, velocity: float = 0.0):
        self.position, self.velocity = position, velocity
        self.acceleration = self.current = 0.0

    def follow(self, position: float, velocity: float) -> None:
        """Demand = actual: what a stop ramp or a new mode starts from, without a jump."""
        self.position, self.velocity = position, velocity
        self.acceleration = self.current = 0.0

    def ramp(self, target: float, accel: float, decel: float, dt: float, k: float) -> None:
        """Velocity toward ``target`` (rpm) with ``accel``/``decel`` (rpm/s);
        the position on with the ramp's exact distance (``k`` inc/s per rpm)."""
        self.velocity, distance, self.acceleration = ramp(self.velocity, target, accel, decel, dt)
        self.position += distance * k


def position_limits(store) -> Tuple[float, float]:
    """0x607D software position limits; 0/0 (EPOS Studio exports) = not in use."""
    lo, hi = store.get(0x607D, 1, -2 ** 31), store.get(0x607D, 2, 2 ** 31 - 1)
    if lo >= hi:
        return -math.inf, math.inf
    return float(lo), float(hi)


class Mode:
    """An operation mode: what the drive does with its set-point while
    operation is enabled."""

    number = 0
    target_object: Optional[Key] = None  # where the master writes the set-point
    position_controlled = False  # the following error is supervised
    software_limits = True  # the demand must stay inside 0x607D
    reports_following_error = False  # statusword bit 13 shows it

    def __init__(self, drive: "VirtualEpos4"):
        self.drive = drive
        self.store = drive.store
        self.demand = drive.demand
        self.internal_limit = False

    @property
    def k(self) -> float:
        """inc/s per rpm of the encoder as configured now (0x3000 may change it)."""
        return self.drive.motor.inc_per_s_per_rpm

    def set_point(self) -> float:
        return float(self.store.get(self.target_object[0], self.target_object[1], 0))

    def clamp(self, target: float) -> float:
        """``target`` inside the software position limits (internal limit while clamped)."""
        lo, hi = position_limits(self.store)
        clamped = min(hi, max(lo, target))
        self.internal_limit = clamped != target
        return clamped

    def control(self, cw: int, previous: int, now: float) -> None:
        """The operation-mode-specific controlword bits (4-6, 9)."""

    def on_sync(self, now: float) -> None:
        """A SYNC while operation is enabled."""

    def step(self, dt: float, now: float, halt: bool) -> int:
        """One control cycle: update the demand; return the motor loop to close."""
        return self.hold(dt, now) if halt else self.follow(dt, now)

    def follow(self, dt: float, now: float) -> int:
        """Follow the set-point."""
        raise NotImplementedError

    def hold(self, dt: float, now: float) -> int:
        """Halt (controlword bit 8). The cyclic modes go on following their
        set-point: their master holds them by repeating it."""
        return self.follow(dt, now)

    def status(self, cw: int) -> int:
        """The mode's statusword bits (10, 12, 13) while operation is enabled."""
        return 0


class ProfilePosition(Mode):
    """PPM: point-to-point moves to 0x607A, planned by the profile generator."""

    number = OperationMode.PROFILE_POSITION
    target_object = (0x607A, 0)
    position_controlled = True
    reports_following_error = True

    def __init__(self, drive: "VirtualEpos4"):
        super().__init__(drive)
        self.target: Optional[float] = None
        self.pending: Optional[float] = None  # buffered set-point (single set-point off)
        self.ack = False
        self.target_reached = False
        self.in_window_since: Optional[float] = None
        # (target and profile parameters, the plan, its time so far) of the move in progress
        self.plan: Optional[Tuple[Tuple[float, float, float, float], PointToPoint, float]] = None

    def control(self, cw: int, previous: int, now: float) -> None:
        if cw & cia402.CW_NEW_SET_POINT and not previous & cia402.CW_NEW_SET_POINT:
            self._new_set_point(cw)
        elif previous & cia402.CW_NEW_SET_POINT and not cw & cia402.CW_NEW_SET_POINT:
            self.ack = False

    def _new_set_point(self, cw: int) -> None:
        raw = self.set_point()
        moving = self.target is not None and not self.target_reached
        if cw & cia402.CW_RELATIVE:
            base = self.pending if self.pending is not None else \
                self.target if self.target is not None else self.demand.position
            raw += base
        target = self.clamp(raw)
        if not moving or cw & cia402.CW_CHANGE_SET_IMMEDIATELY:
            self.target, self.pending = target, None
        elif self.pending is None:
            self.pending = target  # buffered: starts when the current one ends
        else:
            return  # buffer full: no acknowledge
        self.ack = True
        self.target_reached = False
        self.in_window_since = None

    def _accelerations(self) -> Tuple[float, float]:
        get = self.store.get
        return get(0x6083, 0, 10000) * self.k, get(0x6084, 0, 10000) * self.k

    def step(self, dt: float, now: float, halt: bool) -> int:
        if halt or self.target is None:
            return self.hold(dt, now)
        return self.follow(dt, now)

    def hold(self, dt: float, now: float) -> int:
        """Halted, or no set-point yet: slow down with 0x6084 and stay."""
        self.plan = None  # a release plans again from where the halt left the demand
        accel, decel = self._accelerations()
        self.demand.ramp(0.0, accel / self.k, decel / self.k, dt, self.k)
        if self.drive.last_cw & cia402.CW_HALT and self.demand.velocity == 0.0:
            self.target_reached = True
        return mm.POSITION

    def follow(self, dt: float, now: float) -> int:
        get, k, demand = self.store.get, self.k, self.demand
        accel, decel = self._accelerations()
        vmax = min(get(0x6081, 0, 1000), get(0x607F, 0, 50000)) * k
        if get(0x6081, 0, 1000) > get(0x607F, 0, 50000):
            self.internal_limit = True
        params = (self.target, vmax, accel, decel)
        if self.plan is None or self.plan[0] != params:
            if demand.position != self.target:
                self.target_reached = False  # e.g. resuming after halt
            # the profile parameters as they are now: a change reaches a move in progress
            self.plan = (params, PointToPoint(demand.position, demand.velocity * k, self.target,
                                              vmax, accel, decel), 0.0)
        _, plan, elapsed = self.plan
        elapsed += dt
        self.plan = (params, plan, elapsed)
        sample = plan.sample(elapsed)
        demand.position, demand.velocity, demand.acceleration = \
            sample.position, sample.velocity / k, sample.acceleration / k
        if elapsed >= plan.duration:
            if self.pending is not None:
                self.target, self.pending = self.pending, None
            else:
                self._check_window(now)
        return mm.POSITION

    def _check_window(self, now: float) -> None:
        """At the end of the profile: target reached once the rotor stayed
        in the position window (0x6067) for the window time (0x6068)."""
        get = self.store.get
        window = get(0x6067, 0, WINDOW_OFF)
        inside = window == WINDOW_OFF or abs(self.drive.position - self.target) <= window
        if not inside:
            self.in_window_since = None
        elif self.in_window_since is None:
            self.in_window_since = now
        if inside and now - self.in_window_since >= get(0x6068, 0, 0) / 1000.0:
            self.target_reached = True

    def status(self, cw: int) -> int:
        sw = 0
        if self.target_reached or self.target is None and self.demand.velocity == 0.0:
            sw |= cia402.SW_TARGET_REACHED
        if self.ack:
            sw |= cia402.SW_SET_POINT_ACKNOWLEDGE
        return sw


class ProfileVelocity(Mode):
    """PVM: ramps to 0x60FF with 0x6083/0x6084, limited by 0x607F."""

    number = OperationMode.PROFILE_VELOCITY
    target_object = (0x60FF, 0)

    def __init__(self, drive: "VirtualEpos4"):
        super().__init__(drive)
        self.target_reached = False

    def step(self, dt: float, now: float, halt: bool) -> int:
        return self._ramp_to(0.0 if halt else self.set_point(), dt)

    def follow(self, dt: float, now: float) -> int:
        return self._ramp_to(self.set_point(), dt)

    def hold(self, dt: float, now: float) -> int:
        return self._ramp_to(0.0, dt)

    def _ramp_to(self, target: float, dt: float) -> int:
        get = self.store.get
        vmax = float(get(0x607F, 0, 50000))
        self.internal_limit = abs(target) > vmax
        target = max(-vmax, min(vmax, target))
        self.demand.ramp(target, get(0x6083, 0, 10000), get(0x6084, 0, 10000), dt, self.k)
        self.target_reached = abs(self.drive.motor.velocity - target) <= 10.0
        return mm.VELOCITY

    def status(self, cw: int) -> int:
        sw = cia402.SW_TARGET_REACHED if self.target_reached else 0
        if abs(self.drive.motor.velocity) <= 10.0:
            sw |= cia402.SW_SPEED
        return sw


class Homing(Mode):
    """HMM: methods 35/37 (here is home) and -3/-4 (current threshold
    against a hard stop, then back off 0x30B1); others end in a homing error."""

    number = OperationMode.HOMING
    position_controlled = True
    software_limits = False

    def __init__(self, drive: "VirtualEpos4"):
        super().__init__(drive)
        self.phase: Optional[str] = None  # None, search, back, done, error
        self.direction = 1.0
        self.back: Optional[PointToPoint] = None
        self.back_elapsed = 0.0

    def control(self, cw: int, previous: int, now: float) -> None:
        if cw & cia402.CW_HOMING_START and not previous & cia402.CW_HOMING_START:
            self._start()
        elif previous & cia402.CW_HOMING_START and not cw & cia402.CW_HOMING_START \
                and self.phase in ("search", "back"):
            self.phase = None  # 1 -> 0 interrupts homing
            self.demand.velocity = self.drive.motor.velocity

    def _start(self) -> None:
        method = self.store.get(0x6098, 0, 0)
        self.drive.referenced = False
        if method in (35, 37):
            self._set_home()
        elif method in (-3, -4):
            self.phase = "search"
            self.direction = 1.0 if method == -3 else -1.0
            self.demand.velocity = 0.0
        else:
            self.phase = "error"  # methods with switches/index: not simulated

    def _set_home(self) -> None:
        self.drive.set_home(float(self.store.get(0x30B0, 0, 0)))
        self.phase = "done"

    def step(self, dt: float, now: float, halt: bool) -> int:
        if halt or self.phase not in ("search", "back"):
            return self.hold(dt, now)
        return self.follow(dt, now)

    def follow(self, dt: float, now: float) -> int:
        get, demand, motor = self.store.get, self.demand, self.drive.motor
        if self.phase == "search":
            accel = get(0x609A, 0, 1000)
            demand.ramp(self.direction * get(0x6099, 1, 100), accel, accel, dt, self.k)
            if abs(motor.current) * 1000.0 >= get(0x30B2, 0, 500) and motor.blocked:
                self.phase = "back"
                self.back = None
                self.stop_position = self.drive.position
                demand.velocity = 0.0
            return mm.VELOCITY
        if self.back is None:
            accel = get(0x609A, 0, 1000) * self.k
            goal = self.stop_position - self.direction * get(0x30B1, 0, 0)
            self.back = PointToPoint(demand.position, demand.velocity * self.k, goal,
                                     get(0x6099, 2, 10) * self.k, accel, accel)
            self.back_elapsed = 0.0
        self.back_elapsed += dt
        sample = self.back.sample(self.back_elapsed)
        demand.position, demand.velocity, demand.acceleration = \
            sample.position, sample.velocity / self.k, sample.acceleration / self.k
        if self.back_elapsed >= self.back.duration:
            goal = self.back.target
            if abs(self.drive.position - goal) < 1.0 and abs(motor.velocity) < 1.0:
                self._set_home()  # the EPOS4 sets the home position once at rest
        return mm.POSITION

    def hold(self, dt: float, now: float) -> int:
        """Halted, idle, done or error: hold position (a halt during the
        back-off move plans it again from here on release)."""
        self.back = None
        accel = self.store.get(0x609A, 0, 1000)
        self.demand.ramp(0.0, accel, accel, dt, self.k)
        return mm.POSITION

    def status(self, cw: int) -> int:
        if self.phase == "done":
            return cia402.SW_HOMING_ATTAINED | cia402.SW_TARGET_REACHED
        if self.phase == "error":
            return cia402.SW_HOMING_ERROR | cia402.SW_TARGET_REACHED
        if (self.phase is None or cw & cia402.CW_HALT) and self.demand.velocity == 0.0:
            return cia402.SW_TARGET_REACHED
        return 0


class CyclicMode(Mode):
    """The cyclic synchronous modes: the drive follows the command value
    (statusword bit 12) and reports a following error (bit 13)."""

    reports_following_error = True

    def step(self, dt: float, now: float, halt: bool) -> int:
        return self.follow(dt, now)  # halted or not: hold() is follow() (one call less a cycle)

    def status(self, cw: int) -> int:
        return cia402.SW_DRIVE_FOLLOWS_COMMAND


class CyclicSyncPosition(CyclicMode):
    """CSP: 0x607A taken at each SYNC, interpolated linearly over the
    interpolation period (0x60C2, else the measured SYNC interval), plus the
    velocity offset 0x60B1."""

    number = OperationMode.CYCLIC_SYNC_POSITION
    target_object = (0x607A, 0)
    position_controlled = True

    def __init__(self, drive: "VirtualEpos4"):
        super().__init__(drive)
        self.start = self.goal = self.demand.position
        self.t0 = drive.t
        self.last_sync: Optional[float] = None

    def on_sync(self, now: float) -> None:
        self.start = self.demand.position
        self.goal = self.clamp(self.set_point())
        if self.last_sync is not None:
            self.drive.sync_interval = now - self.last_sync
        self.last_sync = now
        self.t0 = now

    def follow(self, dt: float, now: float) -> int:
        # runs every control cycle: the store's dictionary read directly
        values = self.store.values
        value = values.get((0x60C2, 1), 0)
        # the interpolation period
        period = value * 10.0 ** values.get((0x60C2, 2), -3) if value else self.drive.sync_interval or 0.01
        frac = min(1.0, (now - self.t0) / period)
        demand = self.demand
        start, goal = self.start, self.goal
        demand.position = start + (goal - start) * frac
        demand.velocity = (goal - start) / period / self.k if frac < 1.0 else 0.0
        demand.velocity += values.get((0x60B1, 0), 0)
        return mm.POSITION


class CyclicSyncVelocity(CyclicMode):
    """CSV: 0x60FF + 0x60B1, limited by 0x6080, straight to the velocity loop."""

    number = OperationMode.CYCLIC_SYNC_VELOCITY
    target_object = (0x60FF, 0)

    def follow(self, dt: float, now: float) -> int:
        vmax = float(self.store.get(0x6080, 0, 50000))
        velocity = self.set_point() + self.store.get(0x60B1, 0, 0)
        self.demand.velocity = max(-vmax, min(vmax, velocity))
        return mm.VELOCITY


class CyclicSyncTorque(CyclicMode):
    """CST: 0x6071 + 0x60B2 in thousandths of the rated torque, as current."""

    number = OperationMode.CYCLIC_SYNC_TORQUE
    target_object = (0x6071, 0)

    def follow(self, dt: float, now: float) -> int:
        torque = (self.set_point() + self.store.get(0x60B2, 0, 0)) / 1000.0 * self.drive.rated_torque
        self.demand.current = torque / self.drive.motor.torque_constant
        return mm.CURRENT


MODES: Dict[int, Type[Mode]] = {cls.number: cls for cls in (
    ProfilePosition, ProfileVelocity, Homing, CyclicSyncPosition, CyclicSyncVelocity, CyclicSyncTorque)}


def make_mode(number: int, drive: "VirtualEpos4") -> Mode:
    """A fresh mode object for the value of 0x6060 (an idle one for 0 or an unknown value)."""
    cls = MODES.get(number)
    return cls(drive) if cls is not None else Idle(drive)


class Idle(CyclicMode):
    """No mode selected (0x6060 = 0): the demand stays where it is; the
    statusword's mode bits read as in the cyclic modes."""

    def follow(self, dt: float, now: float) -> int:
        return mm.POSITION


class StopRamp:
    """How the drive stops: a quick stop (0x605A), a fault reaction (0x605E)
    or the slow-down of shutdown / disable operation option 1.

    Option 0 switches the power stage off at once (the rotor coasts); the
    others ramp the velocity demand to 0 under position control, with 0x6084
    (options 1, 5) or 0x6085 (2, 6). The ramp is done once the demand is 0
    and the rotor at rest."""

    def __init__(self, option: int):
        self.option = option

    @classmethod
    def for_state(cls, state: State, slowing_down: bool, store) -> "StopRamp":
        if slowing_down:
            return cls(1)
        return cls(store.get(0x605A if state == State.QUICK_STOP_ACTIVE else 0x605E, 0, 2))

    def step(self, dt: float, demand: Demand, store, k: float) -> int:
        if self.option == STOP_COAST:
            demand.velocity = 0.0
            return mm.OFF
        decel = store.get(0x6084 if self.option in STOP_PROFILE else 0x6085, 0, 10000)
        demand.ramp(0.0, decel, decel, dt, k)
        return mm.POSITION

    def done(self, demand: Demand, motor: mm.MotorModel) -> bool:
        return demand.velocity == 0.0 and abs(motor.velocity) < mm.STANDSTILL_RPM

    @property
    def stays_in_quick_stop(self) -> bool:
        """Options 5 and 6 end in quick stop active (target reached); 0-2 disable the drive."""
        return self.option not in (0, 1, 2)
