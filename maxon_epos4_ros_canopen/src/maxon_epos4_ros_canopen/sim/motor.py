"""Motor, load and cascaded controllers of the virtual EPOS4.

A rigid inertia driven by torque = torque constant x current, with viscous
friction, the output current limit and optional mechanical hard stops.  The
EPOS4's current, velocity and position loops are reduced to an ideal current
loop, a first-order velocity loop and a proportional position loop with
velocity feed-forward: enough for actual values that lag the demand, saturate
at the limits and stall against a hard stop.
"""
from __future__ import annotations

import math
from typing import Any, Callable, Optional

RPM_TO_RAD_S = 2.0 * math.pi / 60.0

OFF, POSITION, VELOCITY, CURRENT = 0, 1, 2, 3
# Slower than this the rotor counts as at rest: a drive ends a stop ramp
# here, and static friction holds an unpowered rotor this slow.
STANDSTILL_RPM = 1.0
# An unpowered rotor slows by its bearings' and gearhead's dry friction too,
# not by viscous friction alone (which would let it creep on for many
# seconds): a coasting motor with its gearhead stops within about a second.
COAST_DECELERATION_RPM_S = 1000.0


class MotorModel:
    """State in drive units: position in increments, velocity in rpm, current in A."""

    def __init__(self, increments_per_turn: float = 3200.0, inertia: float = 3.1e-4,
                 torque_constant: float = 0.108, current_limit: float = 9.52,
                 max_speed: float = 5000.0, friction: float = 2e-4,
                 velocity_time_constant: float = 0.005, position_gain: float = 40.0,
                 hard_stop_min: Optional[float] = None, hard_stop_max: Optional[float] = None):
        self.increments_per_turn = increments_per_turn
        self.inertia = inertia  # kg m^2 at the motor shaft
        self.torque_constant = torque_constant  # Nm/A
        self.current_limit = current_limit  # A
        self.max_speed = max_speed  # rpm
        self.friction = friction  # Nm per rad/s (viscous)
        self.velocity_time_constant = velocity_time_constant  # s
        self.position_gain = position_gain  # 1/s
        self.hard_stop_min = hard_stop_min  # increments, physical
        self.hard_stop_max = hard_stop_max
        self.position = 0.0
        self.velocity = 0.0
        self.current = 0.0
        self.blocked = False

    def configure(self, get: Callable[[int, int, Any], Any]) -> float:
        """Motor data from the drive's objects (``get(index, sub, default)``):
        encoder resolution, torque constant, current and speed limits.
        Returns the rated torque (Nm), 0x6076, else from the nominal current."""
        resolution = get(0x3000, 5, 0) or 4 * get(0x3010, 1, 0) or 2000
        self.increments_per_turn = float(resolution)
        kt = get(0x3001, 5, 0) * 1e-6
        self.torque_constant = kt if kt > 0 else 0.1
        limit = get(0x3001, 2, 0) / 1000.0
        self.current_limit = limit if limit > 0 else 10.0
        self.max_speed = float(get(0x6080, 0, 0) or 5000)
        rated = get(0x6076, 0, 0) * 1e-6
        nominal = get(0x3001, 1, 0) / 1000.0
        return rated if rated > 0 else self.torque_constant * (nominal or 1.0)

    @property
    def inc_per_s_per_rpm(self) -> float:
        return self.increments_per_turn / 60.0

    def step(self, dt: float, mode: int, position_ref: float = 0.0, velocity_ref: float = 0.0,
             current_ref: float = 0.0, acceleration_ref: float = 0.0) -> None:
        """Advance ``dt`` seconds in sub-steps short enough to stay stable.

        ``position_ref``, ``velocity_ref`` are the demand at the end of
        ``dt``; ``acceleration_ref`` (rpm/s) is the demand's acceleration
        over it: the position loop walks the demand's curve back from its
        end, and the velocity loop takes the acceleration as feed-forward
        (the EPOS4's acceleration feed-forward), so that a ramp is followed
        without the lag of the velocity loop."""
        if mode == OFF and abs(self.velocity) < STANDSTILL_RPM:
            self.velocity = self.current = 0.0
            return
        steps = max(1, int(math.ceil(dt / 0.0025)))
        h = dt / steps
        k = self.inc_per_s_per_rpm
        for i in range(steps):
            if mode == POSITION:
                # the demand at this sub-step's end, on the curve through the step's end
                back = dt - (i + 1) * h
                reference = position_ref - (velocity_ref - 0.5 * acceleration_ref * back) * back * k
                velocity = velocity_ref - acceleration_ref * back
                velocity_cmd = velocity + self.position_gain * (reference - self.position) / k
                self._velocity_loop(velocity_cmd, acceleration_ref)
            elif mode == VELOCITY:
                self._velocity_loop(velocity_ref)
            elif mode == CURRENT:
                current = max(-self.current_limit, min(self.current_limit, current_ref))
                if abs(self.velocity) >= self.max_speed and current * self.velocity > 0:
                    current = self.friction * self.velocity * RPM_TO_RAD_S / self.torque_constant
                self.current = current
            else:
                self.current = 0.0
            self._integrate(h)
        if mode == OFF and abs(self.velocity) < STANDSTILL_RPM:
            self.velocity = 0.0  # static friction holds a slow coasting rotor

    def cycle(self, dt: float, mode: int, position_ref: float = 0.0, velocity_ref: float = 0.0,
              current_ref: float = 0.0, acceleration_ref: float = 0.0) -> None:
        """``step`` over one control cycle (the drive calls it every 2.5 ms
        or less): the same arithmetic in the same order, with the loops
        written out in one function, because the calls and attribute
        look-ups cost more than the arithmetic. A longer ``dt`` goes to
        ``step``."""
        if dt / 0.0025 > 1.0:  # step would take more than one sub-step
            self.step(dt, mode, position_ref, velocity_ref, current_ref, acceleration_ref)
            return
        velocity = self.velocity
        if mode == OFF and abs(velocity) < STANDSTILL_RPM:
            self.velocity = self.current = 0.0
            return
        h = dt  # step's one sub-step (steps = 1); back = dt - 1 * h below, as there
        k = self.increments_per_turn / 60.0
        if mode == POSITION:
            back = dt - 1 * h
            reference = position_ref - (velocity_ref - 0.5 * acceleration_ref * back) * back * k
            velocity_cmd = velocity_ref - acceleration_ref * back + \
                self.position_gain * (reference - self.position) / k
            current = self._loop_current(velocity_cmd, acceleration_ref, velocity)
        elif mode == VELOCITY:
            current = self._loop_current(velocity_ref, 0.0, velocity)
        elif mode == CURRENT:
            limit = self.current_limit
            current = current_ref if current_ref < limit else limit  # min(limit, current_ref)
            current = current if current > -limit else -limit  # max(-limit, ...)
            if abs(velocity) >= self.max_speed and current * velocity > 0:
                current = self.friction * velocity * RPM_TO_RAD_S / self.torque_constant
        else:
            current = 0.0
        self.current = current
        # _integrate(h)
        torque = self.torque_constant * current - self.friction * velocity * RPM_TO_RAD_S
        new_velocity = velocity + torque / self.inertia * h / RPM_TO_RAD_S
        if current == 0.0:
            new_velocity -= math.copysign(min(abs(new_velocity), COAST_DECELERATION_RPM_S * h), new_velocity)
            if new_velocity * velocity <= 0.0:
                new_velocity = 0.0
        position = self.position + 0.5 * (velocity + new_velocity) * h * k
        self.blocked = False
        if self.hard_stop_max is not None and position >= self.hard_stop_max:
            position, self.blocked = self.hard_stop_max, True
            new_velocity = min(new_velocity, 0.0)
        if self.hard_stop_min is not None and position <= self.hard_stop_min:
            position, self.blocked = self.hard_stop_min, True
            new_velocity = max(new_velocity, 0.0)
        if mode == OFF and abs(new_velocity) < STANDSTILL_RPM:
            new_velocity = 0.0  # static friction holds a slow coasting rotor
        self.position, self.velocity = position, new_velocity

    def _loop_current(self, velocity_cmd: float, acceleration_ff: float, velocity: float) -> float:
        """_velocity_loop's current for the rotor at ``velocity`` (not stored)."""
        limit = self.max_speed
        velocity_cmd = velocity_cmd if velocity_cmd < limit else limit  # min(limit, cmd)
        velocity_cmd = velocity_cmd if velocity_cmd > -limit else -limit  # max(-limit, ...)
        accel = ((velocity_cmd - velocity) / self.velocity_time_constant + acceleration_ff) * RPM_TO_RAD_S
        torque = self.inertia * accel + self.friction * velocity * RPM_TO_RAD_S
        current = torque / self.torque_constant
        limit = self.current_limit
        current = current if current < limit else limit
        return current if current > -limit else -limit

    def _velocity_loop(self, velocity_cmd: float, acceleration_ff: float = 0.0) -> None:
        velocity_cmd = max(-self.max_speed, min(self.max_speed, velocity_cmd))
        accel = ((velocity_cmd - self.velocity) / self.velocity_time_constant + acceleration_ff) * RPM_TO_RAD_S
        torque = self.inertia * accel + self.friction * self.velocity * RPM_TO_RAD_S
        current = torque / self.torque_constant
        self.current = max(-self.current_limit, min(self.current_limit, current))

    def _integrate(self, h: float) -> None:
        torque = self.torque_constant * self.current - self.friction * self.velocity * RPM_TO_RAD_S
        new_velocity = self.velocity + torque / self.inertia * h / RPM_TO_RAD_S
        if self.current == 0.0:
            # coasting: dry friction as well, and friction stops, never reverses
            new_velocity -= math.copysign(min(abs(new_velocity), COAST_DECELERATION_RPM_S * h), new_velocity)
            if new_velocity * self.velocity <= 0.0:
                new_velocity = 0.0
        self.position += 0.5 * (self.velocity + new_velocity) * h * self.inc_per_s_per_rpm
        self.velocity = new_velocity
        self.blocked = False
        if self.hard_stop_max is not None and self.position >= self.hard_stop_max:
            self.position, self.blocked = self.hard_stop_max, True
            self.velocity = min(self.velocity, 0.0)
        if self.hard_stop_min is not None and self.position <= self.hard_stop_min:
            self.position, self.blocked = self.hard_stop_min, True
            self.velocity = max(self.velocity, 0.0)
