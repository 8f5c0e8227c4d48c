"""Wheel odometry of the MANI rover from odometryFb (ROS-free).

Each drive node reports its steering position and its drive encoder count
(revolutions * DRIVE_ENC_PPR + pulses, two 16-bit counters that wrap). The
count differences of the four wheels, each along its steering direction, are
fitted with one rigid-body motion of base_link (least squares, see
Kinematics.wheels_to_body) and integrated into a planar pose in odom.

An integration step happens once per round of feedback: when all four wheels
have reported, or when a wheel reports again before the others (a silent
wheel then contributes its travel when it reports again, instead of holding
the pose still).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, Optional, Tuple

from .config import WHEELS, ManiConfig
from .kinematics import Kinematics
from .protocol import NODE_NAMES, OdometryFb

# Variance reported for the axes a planar odometry does not observe (z, roll,
# pitch): large, so that a fusion filter ignores them.
UNOBSERVED_VARIANCE = 1e6

# Shortest time [s] the plausibility check of a counter step assumes between
# two frames of a wheel (frames may arrive in bursts).
MIN_FRAME_INTERVAL = 0.1


def wrap16(difference: int) -> int:
    """A difference of two 16-bit counter values, as the shortest signed step
    (-32768..32767): 32767 -> -32768 is +1."""
    return (difference + 0x8000) % 0x10000 - 0x8000


def _diagonal(values: Tuple[float, float, float, float, float, float]) -> Tuple[float, ...]:
    matrix = [0.0] * 36
    for i, value in enumerate(values):
        matrix[i * 7] = value
    return tuple(matrix)


@dataclass(frozen=True)
class OdometryState:
    """Pose of base_link in odom and its velocity in base_link, with the
    6x6 row-major covariances of nav_msgs/Odometry (x, y, z, roll, pitch, yaw)."""
    stamp: float
    x: float
    y: float
    yaw: float
    vx: float
    vy: float
    wz: float
    pose_covariance: Tuple[float, ...]
    twist_covariance: Tuple[float, ...]
    distance: float   # [m] path length of base_link since reset


@dataclass
class _Wheel:
    pulses: int
    revolutions: int
    angle: float
    speed: float
    stamp: float
    travel: float = 0.0      # [m] since the last integration step
    reported: bool = False   # in the present round


class WheelOdometry:
    """Integrates odometryFb into an OdometryState; feed every frame to update()."""

    def __init__(self, config: ManiConfig) -> None:
        self.config = config
        self.kinematics = Kinematics(config)
        self._wheels: Dict[str, _Wheel] = {}
        self._last: Optional[OdometryState] = None
        self.counter_resets = 0   # steps taken as a restarted counter, for diagnostics
        self.reset()

    def reset(self, x: float = 0.0, y: float = 0.0, yaw: float = 0.0) -> None:
        """Start again at a pose; the next frame of each wheel is its new reference."""
        self.x, self.y, self.yaw = x, y, yaw
        self.distance = self.var_xy = self.var_yaw = 0.0
        self._wheels.clear()
        self._last = None

    @property
    def state(self) -> Optional[OdometryState]:
        """The latest state, None before the first integration step."""
        return self._last

    def current(self, stamp: float) -> OdometryState:
        """The latest state, or the start pose at rest before the first
        integration step (so a client sees odometry before any feedback)."""
        if self._last is not None:
            return self._last
        return self._state(stamp, 0.0, 0.0, 0.0, 0.0)

    def update(self, feedback: OdometryFb, stamp: float) -> Optional[OdometryState]:
        """Take one odometryFb; returns the new state when a round of
        feedback completes, else None."""
        wheel = NODE_NAMES[feedback.node_id]
        angle = self.kinematics.pulses_to_angle(wheel, feedback.orientation)
        speed = self.kinematics.pps_to_speed(feedback.velocity)
        known = self._wheels.get(wheel)
        if known is None:
            # First frame of this wheel: its counters become the reference.
            self._wheels[wheel] = _Wheel(feedback.pulses, feedback.revolutions, angle, speed, stamp)
            return self._integrate(stamp) if len(self._wheels) == len(WHEELS) and self._last is None else None
        state = None
        if known.reported:
            state = self._integrate(stamp)
        counts = (wrap16(feedback.revolutions - known.revolutions) * self.config.DRIVE_ENC_PPR
                  + wrap16(feedback.pulses - known.pulses))
        # A drive node that was zeroed (switchCmd zeroEncoders) or restarted
        # counts from 0 again: a step no wheel can make at MAX_VEL in the time
        # since its last frame is such a restart, not travel.
        plausible = (2.0 * self.config.max_velocity_pulses * max(stamp - known.stamp, MIN_FRAME_INTERVAL)
                     + self.config.DRIVE_ENC_PPR)
        if abs(counts) > plausible:
            self.counter_resets += 1
        else:
            known.travel += counts * self.kinematics.metres_per_pulse
        known.pulses, known.revolutions = feedback.pulses, feedback.revolutions
        known.angle, known.speed, known.reported, known.stamp = angle, speed, True, stamp
        if all(w.reported for w in self._wheels.values()) and len(self._wheels) == len(WHEELS):
            state = self._integrate(stamp)
        return state

    def _integrate(self, stamp: float) -> OdometryState:
        reported = {name: w for name, w in self._wheels.items() if w.reported}
        if len(reported) >= 2:
            # The travel vector of each wheel lies along its steering
            # direction; fit one rigid motion to them (chord of the arc).
            dx, dy, dyaw, _ = self.kinematics.wheels_to_body(
                {name: (w.travel * math.cos(w.angle), w.travel * math.sin(w.angle))
                 for name, w in reported.items()})
            heading = self.yaw + dyaw / 2.0
            self.x += dx * math.cos(heading) - dy * math.sin(heading)
            self.y += dx * math.sin(heading) + dy * math.cos(heading)
            self.yaw = math.atan2(math.sin(self.yaw + dyaw), math.cos(self.yaw + dyaw))
            step = math.hypot(dx, dy)
            self.distance += step
            noise = self.config.odometry
            self.var_xy += noise.xy_variance_per_m * step
            self.var_yaw += noise.yaw_variance_per_rad * abs(dyaw)
            for w in reported.values():
                w.travel, w.reported = 0.0, False
        latest = list(self._wheels.values())
        vx, vy, wz, slip = self.kinematics.wheels_to_body(
            {name: (w.speed * math.cos(w.angle), w.speed * math.sin(w.angle))
             for name, w in self._wheels.items()}) if len(latest) >= 2 else (0.0, 0.0, 0.0, 0.0)
        self._last = self._state(stamp, vx, vy, wz, slip)
        return self._last

    def _state(self, stamp: float, vx: float, vy: float, wz: float, slip: float) -> OdometryState:
        noise = self.config.odometry
        # Disagreement between the wheels (slip) widens the twist covariance.
        linear = noise.twist_variance_linear + slip * slip
        half_track = self.config.rover.track / 2.0
        angular = noise.twist_variance_angular + (slip / half_track) ** 2
        big = UNOBSERVED_VARIANCE
        return OdometryState(
            stamp=stamp, x=self.x, y=self.y, yaw=self.yaw, vx=vx, vy=vy, wz=wz,
            pose_covariance=_diagonal((self.var_xy, self.var_xy, big, big, big, self.var_yaw)),
            twist_covariance=_diagonal((linear, linear, big, big, big, angular)),
            distance=self.distance)

    def wheel_angles(self) -> Dict[str, float]:
        """The wheels' latest steering angles [rad] (for Kinematics' previous=)."""
        return {name: w.angle for name, w in self._wheels.items()}


def yaw_to_quaternion(yaw: float) -> Tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation about z."""
    return 0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0)


def counters_from_count(count: int, ppr: int) -> Tuple[int, int]:
    """(pulses, revolutions) of a drive node whose encoder has counted
    `count` pulses since zeroing, as int16 counters (the firmware's carry of
    pulses into revolutions, see docs/mani_protocol.md)."""
    revolutions = abs(count) // ppr * (1 if count >= 0 else -1)   # toward zero, as in C
    pulses = count - revolutions * ppr
    return wrap16(pulses), wrap16(revolutions)

