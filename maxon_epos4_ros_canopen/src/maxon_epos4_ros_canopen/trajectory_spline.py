"""Joint trajectories as piecewise polynomials in absolute time.

``Sample`` is the state of all of a controller's joints at one instant;
``Segment`` the polynomial per joint between two states, linear, cubic or
quintic (the standard spline formulas ros_control uses); ``Trajectory`` a
chain of segments that holds its end state afterwards, with the quintic
stop ramp the executor brings joints to rest with.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple

__all__ = ["Sample", "Segment", "Trajectory"]


@dataclass(frozen=True)
class Sample:
    """Desired (or actual) state of all controller joints at one instant."""
    positions: Tuple[float, ...]
    velocities: Tuple[float, ...]
    accelerations: Tuple[float, ...]

    @classmethod
    def at_rest(cls, positions: Sequence[float]) -> "Sample":
        zeros = (0.0,) * len(positions)
        return cls(tuple(float(p) for p in positions), zeros, zeros)


class Segment:
    """Polynomial per joint between two states, for t in [t0, t1]."""

    __slots__ = ("t0", "t1", "coeffs")

    def __init__(self, t0: float, t1: float, start: Sample, end: Sample, order: int) -> None:
        self.t0, self.t1 = t0, t1
        T = t1 - t0
        self.coeffs: List[Tuple[float, ...]] = []
        for j in range(len(start.positions)):
            p0, p1 = start.positions[j], end.positions[j]
            if T <= 0.0:
                self.coeffs.append((p1,))
            elif order == 1:
                self.coeffs.append((p0, (p1 - p0) / T))
            elif order == 3:
                v0, v1 = start.velocities[j], end.velocities[j]
                self.coeffs.append((p0, v0,
                                    (3.0 * (p1 - p0) - (2.0 * v0 + v1) * T) / T ** 2,
                                    (2.0 * (p0 - p1) + (v0 + v1) * T) / T ** 3))
            else:
                v0, v1 = start.velocities[j], end.velocities[j]
                a0, a1 = start.accelerations[j], end.accelerations[j]
                self.coeffs.append((p0, v0, a0 / 2.0,
                                    (20.0 * (p1 - p0) - (8.0 * v1 + 12.0 * v0) * T - (3.0 * a0 - a1) * T ** 2)
                                    / (2.0 * T ** 3),
                                    (30.0 * (p0 - p1) + (14.0 * v1 + 16.0 * v0) * T + (3.0 * a0 - 2.0 * a1) * T ** 2)
                                    / (2.0 * T ** 4),
                                    (12.0 * (p1 - p0) - 6.0 * (v1 + v0) * T - (a0 - a1) * T ** 2)
                                    / (2.0 * T ** 5)))

    def sample(self, t: float) -> Sample:
        s = min(max(t - self.t0, 0.0), max(self.t1 - self.t0, 0.0))
        pos, vel, acc = [], [], []
        for c in self.coeffs:
            p = v = a = 0.0
            for k in range(len(c) - 1, -1, -1):  # Horner for p, v and a at once
                a = a * s + 2.0 * v
                v = v * s + p
                p = p * s + c[k]
            pos.append(p)
            vel.append(v)
            acc.append(a)
        return Sample(tuple(pos), tuple(vel), tuple(acc))


class Trajectory:
    """Piecewise polynomial in absolute time; holds its end state afterwards.

    Before ``start_time`` it samples ``before`` (the trajectory it replaced)
    or, without one, its first state.
    """

    def __init__(self, start_time: float, start: Sample, points: Sequence[Tuple[float, Sample, int]] = (),
                 before: Optional["Trajectory"] = None) -> None:
        self.start_time = start_time
        self.before = before
        self._start = start
        self.segments: List[Segment] = []
        t_prev, prev = start_time, start
        for t, state, order in points:
            self.segments.append(Segment(t_prev, t, prev, state, order))
            t_prev, prev = t, state
        self.end_time = t_prev
        self.end = Sample.at_rest(prev.positions) if self.segments else start

    @classmethod
    def hold(cls, now: float, positions: Sequence[float]) -> "Trajectory":
        return cls(now, Sample.at_rest(positions))

    @classmethod
    def stop(cls, now: float, state: Sample, duration: float) -> "Trajectory":
        """Decelerate from ``state`` to rest within ``duration`` (quintic, no jump)."""
        if duration <= 0.0 or not any(state.velocities):
            return cls.hold(now, state.positions)
        end = Sample.at_rest([p + v * duration / 2.0 for p, v in zip(state.positions, state.velocities)])
        return cls(now, state, [(now + duration, end, 5)])

    def sample(self, t: float) -> Sample:
        if t < self.start_time:
            return self.before.sample(t) if self.before is not None else self._start
        if t >= self.end_time:
            return self.end
        for seg in self.segments:  # a few segments (stops, holds); goals are trajectory_goal._GoalTrajectory
            if t < seg.t1:
                return seg.sample(t)
        return self.end
