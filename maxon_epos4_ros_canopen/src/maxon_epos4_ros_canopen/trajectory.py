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

This module holds the executor; a goal's points, result codes and validation
are in trajectory_goal.py, the splines in trajectory_spline.py, the
tolerances in trajectory_tolerances.py.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Optional, Sequence, Tuple

from .cia402 import OperationMode, State, mode_name
from .trajectory_goal import (GOAL_TOLERANCE_VIOLATED, INVALID_GOAL, INVALID_JOINTS, OLD_HEADER_TIMESTAMP,
                              PATH_TOLERANCE_VIOLATED, SUCCESSFUL, PreparedGoal, TrajectoryError, TrajectoryPoint,
                              prepare_goal)
from .trajectory_spline import Sample, Trajectory
from .trajectory_tolerances import JointTolerance, Tolerances, merge_goal_tolerances, tolerances_from_constraints

# The goal's result codes, points and errors, the samples and the tolerances
# are what the executor takes and returns: importers find them here too.
__all__ = [
    "SUCCESSFUL", "INVALID_GOAL", "INVALID_JOINTS", "OLD_HEADER_TIMESTAMP",
    "PATH_TOLERANCE_VIOLATED", "GOAL_TOLERANCE_VIOLATED",
    "TrajectoryError", "TrajectoryPoint", "Sample", "Tolerances", "tolerances_from_constraints",
    "Outcome", "CycleOutput", "TrajectoryExecutor", "csp_readiness_problem", "STALE_READING_CYCLES",
]

# Past a goal's deadline, the updates that wait for a reading taken after it
# before judging the newest reading there is: a cycle starved for a while
# first sees the readings from before the starvation, and the next few see
# fresh ones; readings that stay old are a lost drive, which its watchdogs
# report, and the goal must still end.
STALE_READING_CYCLES = 50


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
    prepared: PreparedGoal
    tolerances: Tolerances
    trajectory: Optional[Trajectory] = None  # once the cycle took it up
    cycles_past_deadline: int = 0  # updates after end + goal_time with no reading taken after it


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
        # the desired state the last update returned: the targets sent last
        self.last_desired: Optional[Sample] = None
        self._pending: Optional[PreparedGoal] = None  # accepted, for the next update to take up
        self._accepted_at = 0.0

    @property
    def started(self) -> bool:
        return self.trajectory is not None

    def reset(self, now: float, positions: Sequence[float]) -> Optional[Outcome]:
        """Hold ``positions`` (targets the caller vouches for: never readings
        of the drive, which anyone on the bus can forge); ends any goal as
        preempted."""
        self.trajectory = Trajectory.hold(now, positions)
        self.last_desired = None
        self._pending = None
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
        The next ``update`` takes it up (see ``accept``).
        """
        holding = self.query_state(max(now, stamp), now).positions
        prepared, tolerances = self.prepare(joint_names, points, stamp, now, holding, path_tolerance,
                                            goal_tolerance, goal_time_tolerance)
        return self.accept(goal_id, prepared, tolerances, now)

    def prepare(self, joint_names: Sequence[str], points: Sequence[TrajectoryPoint], stamp: float, now: float,
                holding: Sequence[float],
                path_tolerance: Sequence[Tuple[str, float, float, float]] = (),
                goal_tolerance: Sequence[Tuple[str, float, float, float]] = (),
                goal_time_tolerance: float = 0.0,
                position_limits: Optional[Mapping[str, Tuple[float, float]]] = None
                ) -> Tuple[PreparedGoal, Tolerances]:
        """Validate and build a goal without touching the running one: a
        long goal is built here, outside the lock its caller shares with
        the cycle. ``holding``: positions for the joints a partial goal
        leaves out; ``position_limits``: a copy of ``self.position_limits``.
        Raises TrajectoryError when rejected."""
        tolerances = merge_goal_tolerances(self.tolerances, path_tolerance, goal_tolerance, goal_time_tolerance)
        prepared = prepare_goal(self.joint_names, joint_names, points, stamp, now, holding,
                                self.allow_partial_joints_goal,
                                self.position_limits if position_limits is None else position_limits)
        return prepared, tolerances

    def accept(self, goal_id: Any, prepared: PreparedGoal, tolerances: Tolerances, now: float) -> Optional[Outcome]:
        """Hand a prepared goal to the cycle: the next ``update`` splices it
        onto the trajectory that sent the last targets, at that update's
        time, so the targets go on from where they were with their velocity
        however long the goal took to build. O(1); returns the outcome of
        the goal it preempts."""
        self._current()
        self._pending = prepared
        self._accepted_at = now
        preempted = self._end_goal(None)
        if goal_id is not None:
            # An empty goal is reached once its stop ramp is over.
            self.goal = _Goal(goal_id, prepared, tolerances)
        return preempted

    def _take_up(self, now: float) -> None:
        """Splice the accepted goal on at the time it was accepted (after
        it was built: the running trajectory sent its targets meanwhile),
        from the state the running trajectory has then."""
        prepared, self._pending = self._pending, None
        current = self._current()
        self.trajectory = prepared.splice(self._accepted_at, current, self.stop_trajectory_duration)
        if current.start_time <= now:
            current.before = None  # its own predecessor only covered times already past
        if self.goal is not None and self.goal.prepared is prepared:
            self.goal.trajectory = self.trajectory

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
        if self._pending is not None:
            self._take_up(now)  # stop the goal the caller knows, not the one it replaced
        self.trajectory = Trajectory.stop(now, self.trajectory.sample(now), self.stop_trajectory_duration)
        return self._end_goal(None)

    def abort(self, now: float, positions: Sequence[float], code: int, message: str) -> Optional[Outcome]:
        """Give up the running goal and hold ``positions`` (the targets the
        caller sent last: nothing jumps, and no reading becomes a target)."""
        self.trajectory = Trajectory.hold(now, positions)
        self.last_desired = None
        self._pending = None
        goal = self.goal
        if goal is None:
            return None
        return self._end_goal(Outcome(goal.goal_id, code, message))

    def abort_and_stop(self, now: float, code: int, message: str) -> Optional[Outcome]:
        """Give up the running goal and decelerate from the desired state to rest."""
        if self._pending is not None:
            self._take_up(now)
        self.trajectory = Trajectory.stop(now, self._current().sample(now), self.stop_trajectory_duration)
        goal = self.goal
        if goal is None:
            return None
        return self._end_goal(Outcome(goal.goal_id, code, message))

    def query_state(self, t: float, now: Optional[float] = None) -> Sample:
        """The desired state at ``t``. A goal accepted but not taken up yet
        counts as taken up at ``now`` (default: when it was accepted)."""
        current = self._current()
        if self._pending is not None:
            at = self._accepted_at if now is None else now
            return self._pending.splice(at, current, self.stop_trajectory_duration).sample(t)
        return current.sample(t)

    def update(self, now: float, actual_positions: Sequence[float],
               actual_velocities: Optional[Sequence[float]] = None,
               readings_at: Optional[float] = None) -> CycleOutput:
        """One control cycle: the desired state at ``now`` and, when a goal ends, its outcome.

        ``readings_at``: when the oldest of the actual values was taken (on
        ``now``'s clock; None: at ``now``). The goal is judged only on
        readings taken after the trajectory's end, and failed only on
        readings taken after its deadline (end + goal_time)."""
        if self._pending is not None:
            self._take_up(now)
        traj = self._current()
        desired = traj.sample(now)
        sent_before = self.last_desired
        err_p = tuple(d - a for d, a in zip(desired.positions, actual_positions))
        err_v = (tuple(d - a for d, a in zip(desired.velocities, actual_velocities))
                 if actual_velocities is not None else (0.0,) * len(err_p))
        outcome: Optional[Outcome] = None
        goal = self.goal
        if goal is not None and goal.trajectory is traj:
            if now < traj.end_time:
                problem = self._violation(goal.tolerances.path, err_p, err_v, actual_velocities, at_goal=False)
                if problem:
                    outcome = self._path_violation(now, sent_before or desired, problem)
                    desired = self._current().sample(now)
            else:
                outcome = self._judge_goal(goal, traj, now, err_p, err_v, actual_velocities, readings_at)
        self.last_desired = desired
        return CycleOutput(desired, err_p, err_v, outcome)

    def _judge_goal(self, goal: _Goal, traj: Trajectory, now: float, err_p: Sequence[float],
                    err_v: Sequence[float], actual_velocities: Optional[Sequence[float]],
                    readings_at: Optional[float]) -> Optional[Outcome]:
        """At or after the trajectory's end: the goal's outcome, or None
        while it may still be met or the readings are older than what they
        would have to prove."""
        goal_time = goal.tolerances.goal_time
        deadline = traj.end_time + goal_time
        late = goal_time > 0.0 and now > deadline
        taken = now if readings_at is None else readings_at
        # readings that never come fresh must not leave the goal open for ever
        forced = goal.cycles_past_deadline >= STALE_READING_CYCLES
        if late:
            goal.cycles_past_deadline += 1
        problem = self._violation(goal.tolerances.goal, err_p, err_v, actual_velocities, at_goal=True)
        if not problem:
            if taken >= traj.end_time or forced:
                return self._end_goal(Outcome(goal.goal_id, SUCCESSFUL, "goal reached"))
            return None
        if not late or not (taken > deadline or forced):
            return None
        if taken > deadline:
            age = "joint states read %.0f ms before" % ((now - taken) * 1000.0)
        else:
            age = "no reading after the deadline; the newest was read %.0f ms before" % ((now - taken) * 1000.0)
        return self._end_goal(Outcome(
            goal.goal_id, GOAL_TOLERANCE_VIOLATED,
            "goal tolerance not met %.3f s after the trajectory's end (%s): %s"
            % (now - traj.end_time, age, problem)))

    def _path_violation(self, now: float, sent: Sample, problem: str) -> Optional[Outcome]:
        """Abort on readings outside the path tolerance: decelerate from the
        state last sent (never from the readings, which may be forged: they
        can end a goal, not steer a joint)."""
        goal = self.goal
        self.trajectory = Trajectory.stop(now, sent, self.stop_trajectory_duration)
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
