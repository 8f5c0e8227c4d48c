"""Motion profiles of the virtual EPOS4's profile generators, planned in
closed form and sampled at any time.

A drive's profile generator runs at its own rate, not at the rate of the
bus: sampling a closed-form plan keeps the demand on the same curve whatever
the simulator's step, so a move ends exactly on its target with the
velocity demand already at zero, never in one jump on a step's edge.
Units are the caller's (increments and increments/s here).
"""
from __future__ import annotations

import math
from typing import List, NamedTuple, Tuple


class Sample(NamedTuple):
    """Demand at one instant: position, velocity, acceleration."""

    position: float
    velocity: float
    acceleration: float


class _Segment(NamedTuple):
    start: float  # s, from the plan's start
    duration: float
    position: float
    velocity: float
    acceleration: float


def _sign(x: float) -> float:
    return 1.0 if x > 0 else -1.0 if x < 0 else 0.0


def ramp(velocity: float, target: float, accel: float, decel: float, dt: float) -> Tuple[float, float, float]:
    """Move ``velocity`` toward ``target`` over ``dt``: ``accel`` when speeding
    up in the same direction, ``decel`` otherwise.

    Returns (velocity at the end, distance covered, mean acceleration): the
    distance is the ramp's exact one, also when it reaches the target part-way
    through the step (a coarse step must not leave the demand short of the
    rotor, which the position loop would then pull back)."""
    if velocity == target or dt <= 0.0:
        return velocity, velocity * max(dt, 0.0), 0.0
    speeding_up = abs(target) > abs(velocity) and velocity * target >= 0
    rate = accel if speeding_up else decel
    if rate <= 0.0:
        return velocity, velocity * dt, 0.0
    need = abs(target - velocity) / rate
    if need <= dt:
        v = target
        distance = 0.5 * (velocity + target) * need + target * (dt - need)
    else:
        v = velocity + rate * dt * _sign(target - velocity)
        distance = 0.5 * (velocity + v) * dt
    return v, distance, (v - velocity) / dt


class PointToPoint:
    """A move from (``position``, ``velocity``) to rest at ``target``:
    trapezoidal (triangular when short) with ``vmax``, ``accel`` and
    ``decel``. A start moving away from the target, or too fast to stop
    on it, first brakes to rest and turns back."""

    def __init__(self, position: float, velocity: float, target: float,
                 vmax: float, accel: float, decel: float):
        self.target = float(target)
        vmax, accel, decel = abs(vmax), max(abs(accel), 1e-9), max(abs(decel), 1e-9)
        self.segments: List[_Segment] = []
        t, p, v = 0.0, float(position), float(velocity)
        d = self.target - p
        stopping = v * v / (2.0 * decel)
        if v * d < 0.0 or (v != 0.0 and stopping > abs(d)):
            # moving away, or too fast to stop on the target: brake, then turn back
            t, p, v = self._add(t, p, v, -_sign(v) * decel, abs(v) / decel)
            d = self.target - p
        direction = _sign(d)
        distance = abs(d)
        speed = abs(v)
        if distance > 0.0 and vmax > 0.0:
            if speed > vmax:  # slow down to vmax first (a lower limit since the last plan)
                peak = vmax
                t_change = (speed - vmax) / decel
            else:
                # the highest speed from which decel still stops on the target
                peak = math.sqrt((distance + speed * speed / (2.0 * accel))
                                 / (0.5 / accel + 0.5 / decel))
                peak = min(peak, vmax)
                t_change = (peak - speed) / accel
            rate = (peak - speed) / t_change if t_change > 0.0 else 0.0
            t, p, v = self._add(t, p, v, rate * direction, t_change)
            braking = peak * peak / (2.0 * decel)
            cruise = max(0.0, abs(self.target - p) - braking)
            if peak > 0.0 and cruise > 0.0:
                t, p, v = self._add(t, p, v, 0.0, cruise / peak)
            t, p, v = self._add(t, p, v, -direction * decel, peak / decel)
        elif v != 0.0:  # no profile velocity: stand still where the brake ends
            t, p, v = self._add(t, p, v, -_sign(v) * decel, abs(v) / decel)
            self.target = p
        self.duration = t

    def _add(self, t: float, p: float, v: float, a: float, duration: float) -> Tuple[float, float, float]:
        if duration <= 0.0:
            return t, p, v
        self.segments.append(_Segment(t, duration, p, v, a))
        return t + duration, p + v * duration + 0.5 * a * duration * duration, v + a * duration

    def sample(self, t: float) -> Sample:
        """The demand ``t`` s after the plan's start; on the target at rest from its end on."""
        if t >= self.duration:
            return Sample(self.target, 0.0, 0.0)
        for seg in self.segments:
            if t < seg.start + seg.duration:
                tau = max(0.0, t - seg.start)
                return Sample(seg.position + seg.velocity * tau + 0.5 * seg.acceleration * tau * tau,
                              seg.velocity + seg.acceleration * tau, seg.acceleration)
        return Sample(self.target, 0.0, 0.0)
