"""Joint trajectory execution core for Cyclic Synchronous Position (CSP).

ROS-free: the ROS adapter (``maxon_epos4_ros_canopen_node.trajectory_action``) turns
control_msgs/trajectory_msgs messages into the plain types here and calls
``TrajectoryExecutor.update`` once per SYNC cycle; the returned desired
positions are the 0x607A targets of that cycle.

Behaviour follows ros_control's joint_trajectory_controller, which MoveIt is
written against:

- Segments between points are linear (points carry positions only), cubic
  (positions and velocities) or quintic (positions, velocities and
  accelerations): the order is what both ends of a segment carry.
- A new goal starts from the controller's current desired state at the
  goal's start time (``header.stamp``, or now when zero), so a preempting
  goal continues position and velocity without a step; points that already
  lie in the past are dropped.
- Tolerances: ``constraints/<joint>/trajectory`` (path, checked while the
  trajectory runs), ``constraints/<joint>/goal`` (at the end),
  ``constraints/stopped_velocity_tolerance`` (velocity at the end) and
  ``constraints/goal_time`` (how long after the last point the goal
  tolerances may take to be met; 0 waits without limit as
  joint_trajectory_controller does). A goal's JointTolerance overrides a
  value when > 0, keeps the default when 0 and removes the check when < 0.
- Holding: on cancel, stop or abort the controller brings the desired
  velocity to zero over ``stop_trajectory_duration`` instead of commanding a
  velocity step a drive cannot follow.

Why hand-written: no maintained Python library executes ROS joint
trajectories outside ros_control (a C++ plugin Debian does not ship); the
spline formulas are the standard ones ros_control uses.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

from .cia402 import OperationMode, State, mode_name

__all__ = [
    "SUCCESSFUL", "INVALID_GOAL", "INVALID_JOINTS", "OLD_HEADER_TIMESTAMP",
    "PATH_TOLERANCE_VIOLATED", "GOAL_TOLERANCE_VIOLATED", "RESULT_NAMES",
    "TrajectoryError", "TrajectoryPoint", "Sample", "JointTolerance", "Tolerances",
    "tolerances_from_constraints", "Trajectory", "build_trajectory", "Outcome",
    "CycleOutput", "TrajectoryExecutor", "csp_readiness_problem",
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

DEFAULT_STOPPED_VELOCITY_TOLERANCE = 0.01  # rad/s, as joint_trajectory_controller


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


@dataclass(frozen=True)
class JointTolerance:
    """Tolerance of one joint; a value <= 0 means the quantity is not checked."""
    position: float = 0.0
    velocity: float = 0.0
    acceleration: float = 0.0


@dataclass(frozen=True)
class Tolerances:
    path: Mapping[str, JointTolerance]
    goal: Mapping[str, JointTolerance]
    goal_time: float = 0.0
    stopped_velocity_tolerance: float = DEFAULT_STOPPED_VELOCITY_TOLERANCE


def _number(value: Any, key: str, source: str, minimum: float = 0.0) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError("%s: '%s' must be a number, got %r" % (source, key, value))
    value = float(value)
    if not math.isfinite(value) or value < minimum:
        raise ValueError("%s: '%s' must be a finite number >= %g, got %r" % (source, key, minimum, value))
    return value


def tolerances_from_constraints(joint_names: Sequence[str], constraints: Optional[Mapping[str, Any]],
                                source: str = "constraints") -> Tolerances:
    """Tolerances from a joint_trajectory_controller ``constraints`` parameter.

    ``{goal_time: 0.5, stopped_velocity_tolerance: 0.02,
    <joint>: {trajectory: 0.1, goal: 0.01}}``; raises ValueError naming the
    key for wrong types, negative values or joints the controller lacks.
    """
    constraints = dict(constraints or {})
    if not isinstance(constraints, dict):
        raise ValueError("%s must be a mapping" % source)
    goal_time = _number(constraints.pop("goal_time", 0.0), "goal_time", source)
    stopped = _number(constraints.pop("stopped_velocity_tolerance", DEFAULT_STOPPED_VELOCITY_TOLERANCE),
                      "stopped_velocity_tolerance", source)
    path: Dict[str, JointTolerance] = {}
    goal: Dict[str, JointTolerance] = {}
    for name in joint_names:
        entry = constraints.pop(name, None) or {}
        if not isinstance(entry, dict):
            raise ValueError("%s/%s must be a mapping with 'trajectory' and 'goal'" % (source, name))
        unknown = set(entry) - {"trajectory", "goal"}
        if unknown:
            raise ValueError("%s/%s: unknown keys %s (expected 'trajectory', 'goal')"
                             % (source, name, sorted(unknown)))
        path[name] = JointTolerance(position=_number(entry.get("trajectory", 0.0), name + "/trajectory", source))
        goal[name] = JointTolerance(position=_number(entry.get("goal", 0.0), name + "/goal", source),
                                    velocity=stopped)
    if constraints:
        raise ValueError("%s: %s not joints of this controller (joints: %s)"
                         % (source, sorted(constraints), ", ".join(joint_names)))
    return Tolerances(path=path, goal=goal, goal_time=goal_time, stopped_velocity_tolerance=stopped)


def _override(default: JointTolerance, pos: float, vel: float, acc: float) -> JointTolerance:
    def pick(old: float, new: float) -> float:
        if new > 0:
            return new
        return old if new == 0 else 0.0  # < 0: no check
    return JointTolerance(pick(default.position, pos), pick(default.velocity, vel),
                          pick(default.acceleration, acc))


def merge_goal_tolerances(default: Tolerances, path_tolerance: Sequence[Tuple[str, float, float, float]],
                          goal_tolerance: Sequence[Tuple[str, float, float, float]],
                          goal_time_tolerance: float) -> Tolerances:
    """Apply a goal's JointTolerance lists (name, position, velocity, acceleration)."""
    path = dict(default.path)
    goal = dict(default.goal)
    for kind, given, target in (("path_tolerance", path_tolerance, path), ("goal_tolerance", goal_tolerance, goal)):
        for name, pos, vel, acc in given:
            if name not in target:
                raise TrajectoryError(INVALID_GOAL, "%s names joint '%s' which this controller does not control"
                                      % (kind, name))
            if not all(math.isfinite(v) for v in (pos, vel, acc)):
                raise TrajectoryError(INVALID_GOAL, "%s of joint '%s' is not finite" % (kind, name))
            target[name] = _override(target[name], pos, vel, acc)
    if not math.isfinite(goal_time_tolerance):
        raise TrajectoryError(INVALID_GOAL, "goal_time_tolerance is not finite")
    goal_time = default.goal_time if goal_time_tolerance == 0 else max(goal_time_tolerance, 0.0)
    return Tolerances(path, goal, goal_time, default.stopped_velocity_tolerance)


class _Segment:
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
        self.segments: List[_Segment] = []
        t_prev, prev = start_time, start
        for t, state, order in points:
            self.segments.append(_Segment(t_prev, t, prev, state, order))
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
        for seg in self.segments:  # few segments per goal; a scan is cheap
            if t < seg.t1:
                return seg.sample(t)
        return self.end


def _finite(values: Sequence[float]) -> bool:
    return all(isinstance(v, (int, float)) and math.isfinite(v) for v in values)


def build_trajectory(controller_joints: Sequence[str], joint_names: Sequence[str],
                     points: Sequence[TrajectoryPoint], stamp: float, now: float,
                     current: "Trajectory", allow_partial_joints_goal: bool = False,
                     position_limits: Optional[Mapping[str, Tuple[float, float]]] = None,
                     stop_duration: float = 0.0) -> Trajectory:
    """Validate a goal and splice it onto ``current`` (the running trajectory).

    ``stamp`` is the goal's header stamp in seconds (0: start now). Raises
    TrajectoryError with INVALID_JOINTS, INVALID_GOAL or OLD_HEADER_TIMESTAMP.
    An empty ``points`` list means "stop": the result decelerates to rest
    within ``stop_duration``.
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
        return Trajectory.stop(now, current.sample(now), stop_duration)

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

    splice = max(now, start_time)
    start = current.sample(splice)
    index = {name: names.index(name) for name in names}
    spliced: List[Tuple[float, Sample, int]] = []
    carried = 5  # the spliced start state has position, velocity and acceleration
    for pt in points:
        own = 5 if pt.accelerations else 3 if pt.velocities else 1
        order, carried = min(own, carried), own  # what both ends of the segment carry
        t = start_time + pt.time_from_start
        if t <= splice:
            carried = 5  # the segment starts at the spliced state instead
            continue  # already in the past
        pos, vel, acc = list(start.positions), [0.0] * len(start.positions), [0.0] * len(start.positions)
        for j, name in enumerate(controller_joints):
            if name in index:
                k = index[name]
                pos[j] = float(pt.positions[k])
                vel[j] = float(pt.velocities[k]) if pt.velocities else 0.0
                acc[j] = float(pt.accelerations[k]) if pt.accelerations else 0.0
        spliced.append((t, Sample(tuple(pos), tuple(vel), tuple(acc)), order))
    if current.start_time <= now:
        current.before = None  # its own predecessor only covered times already past
    return Trajectory(splice, start, spliced, before=current)


@dataclass(frozen=True)
class Outcome:
    """How a goal ended: ``code`` is a FollowJointTrajectoryResult code."""
    goal_id: Any
    code: int
    message: str

    @property
    def succeeded(self) -> bool:
        return self.code == SUCCESSFUL


@dataclass(frozen=True)
class CycleOutput:
    desired: Sample
    error_positions: Tuple[float, ...]
    error_velocities: Tuple[float, ...]
    outcome: Optional[Outcome] = None


@dataclass
class _Goal:
    goal_id: Any
    trajectory: Trajectory
    tolerances: Tolerances


class TrajectoryExecutor:
    """Runs one joint trajectory controller's goals; call ``update`` every SYNC.

    Not thread-safe by itself: the adapter serialises calls with one lock.
    """

    def __init__(self, joint_names: Sequence[str], tolerances: Optional[Tolerances] = None,
                 stop_trajectory_duration: float = 0.2, allow_partial_joints_goal: bool = False,
                 position_limits: Optional[Mapping[str, Tuple[float, float]]] = None) -> None:
        if not joint_names:
            raise ValueError("a trajectory controller needs at least one joint")
        self.joint_names: Tuple[str, ...] = tuple(joint_names)
        self.tolerances = tolerances or tolerances_from_constraints(self.joint_names, {})
        self.stop_trajectory_duration = max(float(stop_trajectory_duration), 0.0)
        self.allow_partial_joints_goal = allow_partial_joints_goal
        self.position_limits = dict(position_limits or {})
        self.trajectory: Optional[Trajectory] = None
        self.goal: Optional[_Goal] = None

    @property
    def started(self) -> bool:
        return self.trajectory is not None

    def reset(self, now: float, actual_positions: Sequence[float]) -> Optional[Outcome]:
        """Hold the given (measured) positions; ends any goal as preempted."""
        self.trajectory = Trajectory.hold(now, actual_positions)
        return self._end_goal(None)

    def _current(self) -> Trajectory:
        if self.trajectory is None:
            raise TrajectoryError(INVALID_GOAL, "the controller is not running (no joint state yet)")
        return self.trajectory

    def submit(self, goal_id: Any, joint_names: Sequence[str], points: Sequence[TrajectoryPoint],
               stamp: float, now: float,
               path_tolerance: Sequence[Tuple[str, float, float, float]] = (),
               goal_tolerance: Sequence[Tuple[str, float, float, float]] = (),
               goal_time_tolerance: float = 0.0) -> Optional[Outcome]:
        """Accept a goal (or, with goal_id None, a topic command) replacing the running one.

        Returns the outcome of the goal it preempts (code SUCCESSFUL,
        message "preempted"), if any. Raises TrajectoryError when rejected;
        then nothing changes.
        """
        tolerances = merge_goal_tolerances(self.tolerances, path_tolerance, goal_tolerance, goal_time_tolerance)
        trajectory = build_trajectory(self.joint_names, joint_names, points, stamp, now, self._current(),
                                      self.allow_partial_joints_goal, self.position_limits,
                                      self.stop_trajectory_duration)
        self.trajectory = trajectory
        preempted = self._end_goal(None)
        if goal_id is not None:
            # An empty goal is reached once its stop ramp is over.
            self.goal = _Goal(goal_id, trajectory, tolerances)
        return preempted

    def _end_goal(self, outcome: Optional[Outcome]) -> Optional[Outcome]:
        goal, self.goal = self.goal, None
        if goal is None:
            return None
        return outcome or Outcome(goal.goal_id, SUCCESSFUL, "preempted by a new trajectory")

    def cancel(self, goal_id: Any, now: float) -> bool:
        """Cancel ``goal_id`` if it is the running goal: decelerate and hold."""
        if self.goal is None or self.goal.goal_id != goal_id:
            return False
        self.stop(now)
        return True

    def stop(self, now: float) -> Optional[Outcome]:
        """Decelerate from the current desired state to rest and hold there."""
        if self.trajectory is None:
            return None
        self.trajectory = Trajectory.stop(now, self.trajectory.sample(now), self.stop_trajectory_duration)
        return self._end_goal(None)

    def abort(self, now: float, actual_positions: Sequence[float], code: int, message: str) -> Optional[Outcome]:
        """Give up the running goal and hold the measured positions (nothing jumps)."""
        self.trajectory = Trajectory.hold(now, actual_positions)
        goal = self.goal
        if goal is None:
            return None
        return self._end_goal(Outcome(goal.goal_id, code, message))

    def abort_and_stop(self, now: float, code: int, message: str) -> Optional[Outcome]:
        """Give up the running goal and decelerate from the desired state to rest."""
        self.trajectory = Trajectory.stop(now, self._current().sample(now), self.stop_trajectory_duration)
        goal = self.goal
        if goal is None:
            return None
        return self._end_goal(Outcome(goal.goal_id, code, message))

    def query_state(self, t: float) -> Sample:
        return self._current().sample(t)

    def update(self, now: float, actual_positions: Sequence[float],
               actual_velocities: Optional[Sequence[float]] = None) -> CycleOutput:
        """One control cycle: the desired state at ``now`` and, when a goal ends, its outcome."""
        traj = self._current()
        desired = traj.sample(now)
        err_p = tuple(d - a for d, a in zip(desired.positions, actual_positions))
        err_v = (tuple(d - a for d, a in zip(desired.velocities, actual_velocities))
                 if actual_velocities is not None else (0.0,) * len(err_p))
        outcome: Optional[Outcome] = None
        goal = self.goal
        if goal is not None and goal.trajectory is traj:
            if now < traj.end_time:
                problem = self._violation(goal.tolerances.path, err_p, err_v, actual_velocities, at_goal=False)
                if problem:
                    outcome = self._path_violation(now, actual_positions, actual_velocities, problem)
                    desired = self.trajectory.sample(now) if self.trajectory else desired
            else:
                problem = self._violation(goal.tolerances.goal, err_p, err_v, actual_velocities, at_goal=True)
                if not problem:
                    outcome = self._end_goal(Outcome(goal.goal_id, SUCCESSFUL, "goal reached"))
                elif goal.tolerances.goal_time > 0.0 and now > traj.end_time + goal.tolerances.goal_time:
                    outcome = self._end_goal(Outcome(
                        goal.goal_id, GOAL_TOLERANCE_VIOLATED,
                        "goal tolerance not met %.3f s after the trajectory's end: %s"
                        % (now - traj.end_time, problem)))
        return CycleOutput(desired, err_p, err_v, outcome)

    def _path_violation(self, now: float, actual_positions: Sequence[float],
                        actual_velocities: Optional[Sequence[float]], problem: str) -> Optional[Outcome]:
        goal = self.goal
        state = Sample(tuple(actual_positions),
                       tuple(actual_velocities) if actual_velocities is not None else (0.0,) * len(actual_positions),
                       (0.0,) * len(actual_positions))
        self.trajectory = Trajectory.stop(now, state, self.stop_trajectory_duration)
        self.goal = None
        return Outcome(goal.goal_id, PATH_TOLERANCE_VIOLATED, "path tolerance violated: %s" % problem)

    def _violation(self, tolerances: Mapping[str, JointTolerance], err_p: Sequence[float],
                   err_v: Sequence[float], actual_velocities: Optional[Sequence[float]],
                   at_goal: bool) -> str:
        for j, name in enumerate(self.joint_names):
            tol = tolerances.get(name)
            if tol is None:
                continue
            if tol.position > 0.0 and abs(err_p[j]) > tol.position:
                return "joint '%s' position error %.5f > %.5f" % (name, err_p[j], tol.position)
            if tol.velocity > 0.0:
                if at_goal and actual_velocities is not None and abs(actual_velocities[j]) > tol.velocity:
                    return "joint '%s' still moving at %.5f > %.5f" % (name, actual_velocities[j], tol.velocity)
                if not at_goal and actual_velocities is not None and abs(err_v[j]) > tol.velocity:
                    return "joint '%s' velocity error %.5f > %.5f" % (name, err_v[j], tol.velocity)
        return ""


def csp_readiness_problem(joint_name: str, state: Optional[State], mode: Any) -> str:
    """Why ``joint_name`` cannot follow CSP targets now ("" when it can).

    ``mode`` is the drive's modes of operation display (0x6061) as an int,
    an OperationMode or its ``cia402.mode_name``.
    """
    if state is None:
        return "joint '%s': drive state unknown (no statusword received yet)" % joint_name
    if state is not State.OPERATION_ENABLED:
        return "joint '%s': drive is %s, not operation enabled" % (joint_name, state.value)
    csp = OperationMode.CYCLIC_SYNC_POSITION
    if isinstance(mode, str) and not mode.strip().lstrip("-").isdigit():
        if mode.strip().lower() == mode_name(csp.value):
            return ""
        return "joint '%s' is in mode %s, not Cyclic Synchronous Position (8)" % (joint_name, mode)
    try:
        mode_value = int(getattr(mode, "value", mode))
    except (TypeError, ValueError):
        return "joint '%s': mode of operation unknown (%r)" % (joint_name, mode)
    if mode_value != csp.value:
        return "joint '%s' is in mode %d (%s), not Cyclic Synchronous Position (8)" % (
            joint_name, mode_value, mode_name(mode_value))
    return ""
