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
from typing import Optional

RPM_TO_RAD_S = 2.0 * math.pi / 60.0

OFF, POSITION, VELOCITY, CURRENT = 0, 1, 2, 3
# Slower than this the rotor counts as at rest: a drive ends a stop ramp
# here, and static friction holds an unpowered rotor this slow.
STANDSTILL_RPM = 1.0


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

    @property
    def inc_per_s_per_rpm(self) -> float:
        return self.increments_per_turn / 60.0

    def step(self, dt: float, mode: int, position_ref: float = 0.0, velocity_ref: float = 0.0,
             current_ref: float = 0.0) -> None:
        """Advance ``dt`` seconds in sub-steps short enough to stay stable."""
        if mode == OFF and abs(self.velocity) < STANDSTILL_RPM:
            self.velocity = self.current = 0.0
            return
        steps = max(1, int(math.ceil(dt / 0.0025)))
        h = dt / steps
        k = self.inc_per_s_per_rpm
        # position_ref is the demand at the end of dt: walk up to it
        position_ref -= velocity_ref * k * dt
        for _ in range(steps):
            if mode == POSITION:
                position_ref += velocity_ref * h * k
                velocity_cmd = velocity_ref + self.position_gain * (position_ref - self.position) / k
                self._velocity_loop(velocity_cmd)
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

    def _velocity_loop(self, velocity_cmd: float) -> None:
        velocity_cmd = max(-self.max_speed, min(self.max_speed, velocity_cmd))
        accel = (velocity_cmd - self.velocity) * RPM_TO_RAD_S / self.velocity_time_constant
        torque = self.inertia * accel + self.friction * self.velocity * RPM_TO_RAD_S
        current = torque / self.torque_constant
        self.current = max(-self.current_limit, min(self.current_limit, current))

    def _integrate(self, h: float) -> None:
        torque = self.torque_constant * self.current - self.friction * self.velocity * RPM_TO_RAD_S
        new_velocity = self.velocity + torque / self.inertia * h / RPM_TO_RAD_S
        if self.current == 0.0 and new_velocity * self.velocity <= 0.0:
            new_velocity = 0.0  # coasting: friction stops, never reverses
        self.position += 0.5 * (self.velocity + new_velocity) * h * self.inc_per_s_per_rpm
        self.velocity = new_velocity
        self.blocked = False
        if self.hard_stop_max is not None and self.position >= self.hard_stop_max:
            self.position, self.blocked = self.hard_stop_max, True
            self.velocity = min(self.velocity, 0.0)
        if self.hard_stop_min is not None and self.position <= self.hard_stop_min:
            self.position, self.blocked = self.hard_stop_min, True
            self.velocity = max(self.velocity, 0.0)
