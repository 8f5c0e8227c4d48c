"""A joint trajectory goal: its points, the FollowJointTrajectoryResult
codes and TrajectoryError it may be rejected or end with, its validation into
an immutable PreparedGoal (``prepare_goal``), and its splice onto the running
trajectory.
"""
from __future__ import annotations

import math
from bisect import bisect_right
from dataclasses import dataclass
from typing import List, Mapping, Optional, Sequence, Tuple

from .trajectory_spline import Sample, Segment, Trajectory

__all__ = [
    "SUCCESSFUL", "INVALID_GOAL", "INVALID_JOINTS", "OLD_HEADER_TIMESTAMP",
    "PATH_TOLERANCE_VIOLATED", "GOAL_TOLERANCE_VIOLATED", "RESULT_NAMES",
    "TrajectoryError", "TrajectoryPoint", "PreparedGoal", "prepare_goal", "build_trajectory",
]

# control_msgs/FollowJointTrajectoryResult error codes.
SUCCESSFUL = 0
INVALID_GOAL = -1
INVALID_JOINTS = -2
OLD_HEADER_TIMESTAMP = -3
PATH_TOLERANCE_VIOLATED = -4
GOAL_TOLERANCE_VIOLATED = -5

RESULT_NAMES = {
    SUCCESSFUL: "SUCCESSFUL", INVALID_GOAL: "INVALID_GOAL", INVALID_JOINTS: "INVALID_JOINTS",
    OLD_HEADER_TIMESTAMP: "OLD_HEADER_TIMESTAMP",
    PATH_TOLERANCE_VIOLATED: "PATH_TOLERANCE_VIOLATED",
    GOAL_TOLERANCE_VIOLATED: "GOAL_TOLERANCE_VIOLATED",
}


class TrajectoryError(Exception):
    """A goal or command that cannot be executed; ``code`` is the result code."""

    def __init__(self, code: int, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message


@dataclass(frozen=True)
class TrajectoryPoint:
    """One waypoint, values in the order of the message's joint_names."""
    positions: Tuple[float, ...]
    velocities: Tuple[float, ...] = ()
    accelerations: Tuple[float, ...] = ()
    time_from_start: float = 0.0


class _GoalTrajectory(Trajectory):
    """A goal spliced on: a first segment from the state it was spliced on
    at to the first point still ahead, then the goal's own points. The
    segments between points are made when the trajectory first reaches
    them, one at a time (the cycle samples forwards): taking up a goal of
    10,000 points costs the cycle no more than one of two."""

    def __init__(self, splice: float, start: Sample, goal: "PreparedGoal", k: int, first: Segment,
                 before: Trajectory) -> None:
        super().__init__(splice, start, before=before)
        self._goal = goal
        self._k = k                      # the goal's first point still ahead
        self._first = first              # times on the goal's scale (from goal.start_time)
        self._made: Tuple[int, Optional[Segment]] = (-1, None)  # the segment made last: (its end point, it)
        self.end_time = goal.start_time + goal.times[-1]
        self.end = Sample.at_rest(goal.states[-1].positions)

    def sample(self, t: float) -> Sample:
        if t < self.start_time:
            return self.before.sample(t) if self.before is not None else self._start
        if t >= self.end_time:
            return self.end
        goal = self._goal
        since = t - goal.start_time
        if since < self._first.t1:
            return self._first.sample(since)
        # the segment from point j - 1 to point j (min: since rounded onto the last point's time)
        j = min(bisect_right(goal.times, since, self._k + 1), len(goal.times) - 1)
        made_for, segment = self._made
        if made_for != j or segment is None:
            segment = goal.segment(j)
            self._made = (j, segment)
        return segment.sample(since)


def _finite(values: Sequence[float]) -> bool:
    try:
        return all(map(math.isfinite, values))
    except TypeError:  # not a number
        return False


@dataclass(frozen=True)
class PreparedGoal:
    """A goal validated, ready to replace the running trajectory (``splice``).
    Immutable: made outside any lock the cycle takes, then handed to the
    cycle whole.

    ``times`` are the points' time_from_start (the joints a partial goal
    leaves out hold where they were when it came). The goal starts at
    ``start_time``: its stamp, or (stamp 0) when it came, as in
    ros_control. No points: stop and hold.
    """
    start_time: float
    times: Tuple[float, ...]
    states: Tuple[Sample, ...]
    orders: Tuple[int, ...]           # what each point carries: 1, 3 or 5

    def segment(self, j: int) -> Segment:
        """From point j - 1 to point j; its order is what both ends carry."""
        return Segment(self.times[j - 1], self.times[j], self.states[j - 1], self.states[j],
                        min(self.orders[j - 1], self.orders[j]))

    def splice(self, at: float, current: Trajectory, stop_duration: float) -> Trajectory:
        """The trajectory that continues ``current`` with this goal from
        ``at`` (or from the goal's start, when later): it starts at the
        state ``current`` has then (the targets sent last, gone on with
        their velocity), with one new segment to the first point still
        ahead, then the goal's points. O(log n) in the number of points."""
        if not self.times:
            return Trajectory.stop(at, current.sample(at), stop_duration)
        splice = max(at, self.start_time)
        start = current.sample(splice)
        since = splice - self.start_time
        k = min(bisect_right(self.times, since), len(self.times) - 1)  # the first point still ahead
        first = Segment(since, max(self.times[k], since), start, self.states[k], self.orders[k])
        return _GoalTrajectory(splice, start, self, k, first, current)


def prepare_goal(controller_joints: Sequence[str], joint_names: Sequence[str],
                 points: Sequence[TrajectoryPoint], stamp: float, now: float, holding: Sequence[float],
                 allow_partial_joints_goal: bool = False,
                 position_limits: Optional[Mapping[str, Tuple[float, float]]] = None) -> PreparedGoal:
    """Validate a goal (the slow part of a long one: run it outside the cycle's lock).

    ``stamp`` is the goal's header stamp in seconds (0: start now);
    ``holding`` the positions the joints a partial goal leaves out keep.
    Raises TrajectoryError with INVALID_JOINTS, INVALID_GOAL or
    OLD_HEADER_TIMESTAMP. An empty ``points`` list means "stop".
    """
    names = list(joint_names)
    if len(set(names)) != len(names):
        raise TrajectoryError(INVALID_JOINTS, "joint_names contains duplicates: %s" % ", ".join(names))
    unknown = [n for n in names if n not in controller_joints]
    if unknown:
        raise TrajectoryError(INVALID_JOINTS, "joint(s) %s not controlled by this controller (joints: %s)"
                              % (", ".join(unknown), ", ".join(controller_joints)))
    missing = [n for n in controller_joints if n not in names]
    if points and missing and not allow_partial_joints_goal:
        raise TrajectoryError(INVALID_JOINTS, "goal lacks joint(s) %s (this controller needs all of: %s)"
                              % (", ".join(missing), ", ".join(controller_joints)))
    if not points:
        return PreparedGoal(0.0, (), (), ())

    n = len(names)
    last_t = -1.0
    for i, pt in enumerate(points):
        if len(pt.positions) != n:
            raise TrajectoryError(INVALID_GOAL, "point %d has %d positions for %d joints" % (i, len(pt.positions), n))
        if len(pt.velocities) not in (0, n):
            raise TrajectoryError(INVALID_GOAL, "point %d has %d velocities for %d joints" % (i, len(pt.velocities), n))
        if len(pt.accelerations) not in (0, n):
            raise TrajectoryError(INVALID_GOAL, "point %d has %d accelerations for %d joints"
                                  % (i, len(pt.accelerations), n))
        if pt.accelerations and not pt.velocities:
            raise TrajectoryError(INVALID_GOAL, "point %d has accelerations but no velocities" % i)
        if not (_finite(pt.positions) and _finite(pt.velocities) and _finite(pt.accelerations)):
            raise TrajectoryError(INVALID_GOAL, "point %d contains a value that is not a finite number" % i)
        if not (math.isfinite(pt.time_from_start) and pt.time_from_start > last_t and pt.time_from_start >= 0):
            raise TrajectoryError(INVALID_GOAL, "time_from_start must increase strictly and be >= 0 "
                                  "(point %d: %r after %r)" % (i, pt.time_from_start, max(last_t, 0.0)))
        last_t = pt.time_from_start
        if position_limits:
            for name, p in zip(names, pt.positions):
                if name in position_limits:
                    lo, hi = position_limits[name]
                    if not lo <= p <= hi:
                        raise TrajectoryError(INVALID_GOAL, "point %d: position %g of joint '%s' is outside its "
                                              "limits [%g, %g]" % (i, p, name, lo, hi))

    start_time = stamp if stamp > 0.0 else now
    if start_time + last_t < now or (stamp <= 0.0 and last_t <= 0.0):
        if stamp > 0.0:
            raise TrajectoryError(OLD_HEADER_TIMESTAMP, "the trajectory ended %.3f s ago (header.stamp too old)"
                                  % (now - start_time - last_t))
        raise TrajectoryError(INVALID_GOAL, "the last point's time_from_start must be > 0 "
                              "(a single point at 0 s would be a position step)")

    index = [names.index(name) if name in names else -1 for name in controller_joints]
    times: List[float] = []
    states: List[Sample] = []
    orders: List[int] = []
    for pt in points:
        t = float(pt.time_from_start)
        if t <= 0.0:
            continue  # the goal starts from the state it is spliced on at
        pos, vel, acc = list(holding), [0.0] * len(index), [0.0] * len(index)
        for j, k in enumerate(index):
            if k >= 0:
                pos[j] = float(pt.positions[k])
                vel[j] = float(pt.velocities[k]) if pt.velocities else 0.0
                acc[j] = float(pt.accelerations[k]) if pt.accelerations else 0.0
        times.append(t)
        states.append(Sample(tuple(pos), tuple(vel), tuple(acc)))
        orders.append(5 if pt.accelerations else 3 if pt.velocities else 1)
    return PreparedGoal(start_time, tuple(times), tuple(states), tuple(orders))


def build_trajectory(controller_joints: Sequence[str], joint_names: Sequence[str],
                     points: Sequence[TrajectoryPoint], stamp: float, now: float,
                     current: "Trajectory", allow_partial_joints_goal: bool = False,
                     position_limits: Optional[Mapping[str, Tuple[float, float]]] = None,
                     stop_duration: float = 0.0) -> Trajectory:
    """Validate a goal and splice it onto ``current`` (the running trajectory)
    at ``now``: ``prepare_goal`` and ``PreparedGoal.splice`` in one."""
    holding = current.sample(max(now, stamp)).positions
    goal = prepare_goal(controller_joints, joint_names, points, stamp, now, holding, allow_partial_joints_goal,
                        position_limits)
    trajectory = goal.splice(now, current, stop_duration)
    if current.start_time <= now:
        current.before = None  # its own predecessor only covered times already past
    return trajectory
