"""Tolerances of a joint trajectory goal: the controller's defaults from its
``constraints`` parameter (as joint_trajectory_controller reads it) and a
goal's JointTolerance lists applied over them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Dict, Mapping, Optional, Sequence, Tuple

from .trajectory_goal import INVALID_GOAL, TrajectoryError

__all__ = ["DEFAULT_STOPPED_VELOCITY_TOLERANCE", "JointTolerance", "Tolerances", "tolerances_from_constraints",
           "merge_goal_tolerances"]

DEFAULT_STOPPED_VELOCITY_TOLERANCE = 0.01  # rad/s, as joint_trajectory_controller


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
