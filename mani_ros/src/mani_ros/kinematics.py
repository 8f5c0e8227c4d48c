"""Kinematics of the MANI rover's four independently steered wheels (ROS-free).

A body command (vx, vy [m/s], wz [rad/s] in base_link, like a
geometry_msgs/Twist) and a steering mode become a steering angle [rad] and a
rim speed [m/s] per wheel, within MAX_VEL and the steering limits, and then
orientationCmd/velocityCmd set points in encoder pulses.

Every wheel of a rigid body moving with (vx, vy, wz) has the contact-point
velocity (vx - wz*y, vy + wz*x), where (x, y) is the wheel's steering axis:
the wheel points along that velocity. The modes only choose which part of
the command is used:

- ackermann (double Ackermann): vx and wz; the turn centre lies on the
  lateral axis through base_link, front and rear wheels steer opposite.
- front_ackermann: vx and wz; the turn centre lies on the rear axle line, the
  rear wheels stay straight (a car).
- point_turn: wz only; the rover turns on the spot.
- crab: vx and vy; all wheels parallel, no rotation.
- vector: vx, vy and wz together, any rigid-body motion (the rover's own
  MoveControl command: x, y, rz).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Dict, List, Mapping, Optional, Sequence, Tuple, Union

from .config import WHEELS, ManiConfig
from .protocol import DRIVE_NODES, INT16_MAX, INT16_MIN, OrientationCmd, VelocityCmd

MODE_ACKERMANN = "ackermann"
MODE_FRONT_ACKERMANN = "front_ackermann"
MODE_POINT_TURN = "point_turn"
MODE_CRAB = "crab"
MODE_VECTOR = "vector"
MODES: Tuple[str, ...] = (MODE_ACKERMANN, MODE_FRONT_ACKERMANN, MODE_POINT_TURN, MODE_CRAB,
                          MODE_VECTOR)

NODE_OF_WHEEL: Dict[str, int] = dict(zip(WHEELS, DRIVE_NODES))

# Below this rim speed [m/s] a wheel has no direction of its own: it keeps
# its previous steering angle instead of swinging round for nothing.
_STILL = 1e-9


class KinematicsError(ValueError):
    """A command the rover cannot execute; the text says why."""


@dataclass(frozen=True)
class WheelCommand:
    angle: float   # [rad] steering angle, 0 straight ahead, positive to the left
    speed: float   # [m/s] rim speed, positive rolls along the steering direction


@dataclass(frozen=True)
class RoverCommand:
    wheels: Dict[str, WheelCommand]   # keyed by wheel name, in WHEELS order
    limited: Tuple[str, ...] = ()      # what was reduced to fit the limits, for logs


Vector = Tuple[float, float]


def _wrap_pi(angle: float) -> float:
    return math.atan2(math.sin(angle), math.cos(angle))


class Kinematics:
    """Conversions for one rover configuration."""

    def __init__(self, config: ManiConfig) -> None:
        self.config = config
        self.positions = config.wheel_positions()
        self.min_angle = config.steering.min_angle
        self.max_angle = config.steering.max_angle
        self.max_speed = config.max_wheel_speed

    # -- body command -> wheels -------------------------------------------

    def body_to_wheels(self, vx: float, vy: float, wz: float, mode: str = MODE_ACKERMANN,
                       previous: Optional[Mapping[str, float]] = None) -> RoverCommand:
        """Wheel angles and speeds for a body command in a steering mode.

        previous: the wheels' present steering angles; a wheel that does not
        roll keeps its angle, and of the two equivalent angles (a, a +- pi
        with the speed reversed) the one nearer to it is chosen.
        Raises KinematicsError for an unknown mode, a non-finite value, or a
        point turn the steering limits do not allow.
        """
        for name, value in (("vx", vx), ("vy", vy), ("wz", wz)):
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise KinematicsError("%s must be a finite number, got %r" % (name, value))
        previous = self._previous(previous)
        limited: List[str] = []
        if mode == MODE_POINT_TURN:
            wheels = self._point_turn(wz, previous)
        elif mode in (MODE_ACKERMANN, MODE_FRONT_ACKERMANN):
            # The rear axle line is the turn centre's line for front_ackermann:
            # base_link then moves sideways at wz * wheel_base / 2.
            lateral = self.config.rover.wheel_base / 2.0 if mode == MODE_FRONT_ACKERMANN else 0.0
            wheels = self._fit(lambda s: (vx, lateral * wz * s, wz * s), previous, limited,
                               "turn rate reduced to the steering limits")
        elif mode == MODE_CRAB:
            wheels = self._fit(lambda s: (vx, vy * s, 0.0), previous, limited,
                               "sideways velocity reduced to the steering limits")
        elif mode == MODE_VECTOR:
            wheels = self._fit(lambda s: (vx, vy * s, wz * s), previous, limited,
                               "sideways velocity and turn rate reduced to the steering limits")
        else:
            raise KinematicsError("unknown steering mode %r (known: %s)" % (mode, ", ".join(MODES)))
        return self._limit_speed(wheels, limited)

    def wheels_command(self, angles: Sequence[float], speeds: Sequence[float]) -> RoverCommand:
        """Per-wheel angles [rad] and rim speeds [m/s] (WHEELS order) checked
        against the limits: an angle outside them is replaced by its
        equivalent a +- pi with the speed reversed where that fits, speeds are
        scaled together to MAX_VEL. KinematicsError if an angle cannot fit."""
        if len(angles) != len(WHEELS) or len(speeds) != len(WHEELS):
            raise KinematicsError("need %d steering angles and %d wheel speeds (%s), got %d and %d"
                                  % (len(WHEELS), len(WHEELS), ", ".join(WHEELS),
                                     len(angles), len(speeds)))
        wheels = {}
        for wheel, angle, speed in zip(WHEELS, angles, speeds):
            for name, value in (("steering angle", angle), ("wheel speed", speed)):
                if not isinstance(value, (int, float)) or not math.isfinite(value):
                    raise KinematicsError("%s of %s must be a finite number, got %r"
                                          % (name, wheel, value))
            fitted = self._choose(angle, speed, angle)
            if fitted is None:
                raise KinematicsError("steering angle %.3f rad of %s is outside the steering "
                                      "limits [%.3f, %.3f] rad"
                                      % (angle, wheel, self.min_angle, self.max_angle))
            wheels[wheel] = fitted
        return self._limit_speed(wheels, [])

    def _previous(self, previous: Optional[Mapping[str, float]]) -> Dict[str, float]:
        previous = previous or {}
        return {wheel: float(previous.get(wheel, 0.0)) for wheel in WHEELS}

    def _vectors(self, vx: float, vy: float, wz: float) -> Dict[str, Vector]:
        return {wheel: (vx - wz * y, vy + wz * x) for wheel, (x, y) in self.positions.items()}

    def _within(self, angle: float) -> bool:
        return self.min_angle - 1e-12 <= angle <= self.max_angle + 1e-12

    def _choose(self, angle: float, speed: float, near: float) -> Optional[WheelCommand]:
        """Of (angle, speed) and (angle +- pi, -speed), the one within the
        limits nearest to the angle `near`; None if neither fits."""
        angle = _wrap_pi(angle)
        other = _wrap_pi(angle + math.pi)
        options = [(a, s) for a, s in ((angle, speed), (other, -speed)) if self._within(a)]
        if not options:
            return None
        best = min(options, key=lambda option: abs(_wrap_pi(option[0] - near)))
        return WheelCommand(best[0], best[1])

    def _wheels_for(self, body: Tuple[float, float, float],
                    previous: Dict[str, float]) -> Optional[Dict[str, WheelCommand]]:
        wheels = {}
        for wheel, (ax, ay) in self._vectors(*body).items():
            speed = math.hypot(ax, ay)
            if speed <= _STILL:
                wheels[wheel] = WheelCommand(previous[wheel], 0.0)
                continue
            fitted = self._choose(math.atan2(ay, ax), speed, previous[wheel])
            if fitted is None:
                return None
            wheels[wheel] = fitted
        return wheels

    def _fit(self, body: Callable[[float], Tuple[float, float, float]],
             previous: Dict[str, float], limited: List[str], reason: str) -> Dict[str, WheelCommand]:
        """Wheels for body(1.0); if the steering limits refuse it, for the
        largest scale s in [0, 1] they accept (s = 0 is always straight or
        standing still, which they accept)."""
        wheels = self._wheels_for(body(1.0), previous)
        if wheels is not None:
            return wheels
        low, high = 0.0, 1.0
        for _ in range(40):
            middle = (low + high) / 2.0
            if self._wheels_for(body(middle), previous) is None:
                high = middle
            else:
                low = middle
        limited.append(reason)
        return self._wheels_for(body(low), previous)  # type: ignore[return-value]

    def _point_turn(self, wz: float, previous: Dict[str, float]) -> Dict[str, WheelCommand]:
        # The angles do not depend on wz: with wz = 0 the wheels still turn
        # to the point-turn position, ready to go.
        wheels = {}
        for wheel, (ax, ay) in self._vectors(0.0, 0.0, 1.0).items():
            fitted = self._choose(math.atan2(ay, ax), math.hypot(ax, ay) * wz, previous[wheel])
            if fitted is None:
                raise KinematicsError(
                    "point turn needs a steering angle of %.3f rad at %s, outside the steering "
                    "limits [%.3f, %.3f] rad" % (math.atan2(ay, ax), wheel, self.min_angle,
                                                 self.max_angle))
            wheels[wheel] = fitted
        return wheels

    def _limit_speed(self, wheels: Dict[str, WheelCommand], limited: List[str]) -> RoverCommand:
        fastest = max(abs(command.speed) for command in wheels.values())
        if fastest > self.max_speed:
            # Scale all wheels alike so that the path keeps its curvature.
            scale = self.max_speed / fastest
            wheels = {wheel: WheelCommand(c.angle, c.speed * scale) for wheel, c in wheels.items()}
            limited.append("speed scaled by %.3f to MAX_VEL" % scale)
        return RoverCommand({wheel: wheels[wheel] for wheel in WHEELS}, tuple(limited))

    # -- wheels -> body (odometry) -----------------------------------------

    def wheels_to_body(self, vectors: Mapping[str, Vector]) -> Tuple[float, float, float, float]:
        """Least-squares rigid-body motion (vx, vy, wz) of base_link that best
        explains the wheel contact-point vectors (velocities or displacements
        in base_link), and the RMS residual per wheel (slip). Needs at least
        two wheels."""
        if len(vectors) < 2:
            raise KinematicsError("need at least two wheels, got %d" % len(vectors))
        points = [self.positions[wheel] for wheel in vectors]
        n = float(len(points))
        cx = sum(x for x, _ in points) / n
        cy = sum(y for _, y in points) / n
        mx = sum(ax for ax, _ in vectors.values()) / n
        my = sum(ay for _, ay in vectors.values()) / n
        moment = sum((x - cx) * ay - (y - cy) * ax
                     for (x, y), (ax, ay) in zip(points, vectors.values()))
        inertia = sum((x - cx) ** 2 + (y - cy) ** 2 for x, y in points)
        wz = moment / inertia
        vx, vy = mx + wz * cy, my - wz * cx
        residual = sum((ax - (vx - wz * y)) ** 2 + (ay - (vy + wz * x)) ** 2
                       for (x, y), (ax, ay) in zip(points, vectors.values()))
        return vx, vy, wz, math.sqrt(residual / n)

    # -- units ---------------------------------------------------------------

    def angle_to_pulses(self, wheel: str, angle: float) -> int:
        """Steering angle [rad] -> orientation [steering encoder pulses]."""
        offset = self.config.steering.offsets[wheel]
        pulses = int(round((angle - offset) * self.config.STEER_ENC_PPR / (2.0 * math.pi)))
        if not INT16_MIN <= pulses <= INT16_MAX:
            raise KinematicsError("steering angle %.3f rad of %s is %d pulses, beyond int16"
                                  % (angle, wheel, pulses))
        return pulses

    def pulses_to_angle(self, wheel: str, pulses: int) -> float:
        """orientation [steering encoder pulses] -> steering angle [rad]."""
        return pulses * 2.0 * math.pi / self.config.STEER_ENC_PPR + self.config.steering.offsets[wheel]

    def speed_to_pps(self, speed: float) -> int:
        """Rim speed [m/s] -> velocity [drive encoder pulses/s], within MAX_VEL:
        the wheel rate omega = speed / radius [rad/s] as omega / 2 pi x PPR."""
        omega = speed / self.config.rover.wheel_radius
        pps = int(round(omega / (2.0 * math.pi) * self.config.DRIVE_ENC_PPR))
        limit = self.config.max_velocity_pulses
        return max(-limit, min(limit, pps))

    def pps_to_speed(self, pps: float) -> float:
        """velocity [drive encoder pulses/s] -> rim speed [m/s]."""
        return pps / self.config.DRIVE_ENC_PPR * self.config.wheel_circumference

    @property
    def metres_per_pulse(self) -> float:
        return self.config.wheel_circumference / self.config.DRIVE_ENC_PPR

    def set_points(self, command: RoverCommand) -> Dict[int, Tuple[int, int]]:
        """node_id -> (orientation [steer pulses], velocity [drive pulses/s])."""
        return {NODE_OF_WHEEL[wheel]: (self.angle_to_pulses(wheel, c.angle), self.speed_to_pps(c.speed))
                for wheel, c in command.wheels.items()}

    def command_messages(self, command: RoverCommand) -> List[Union[OrientationCmd, VelocityCmd]]:
        """orientationCmd and velocityCmd for each drive node, in node order."""
        messages: List[Union[OrientationCmd, VelocityCmd]] = []
        for node_id, (orientation, velocity) in sorted(self.set_points(command).items()):
            messages.append(OrientationCmd(node_id, orientation))
            messages.append(VelocityCmd(node_id, velocity))
        return messages
