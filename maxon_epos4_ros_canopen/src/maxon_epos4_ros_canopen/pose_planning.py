"""ROS-free planning for ``go_to_pose``: SRDF group states, MoveIt joint
limits and a time-parameterized straight line in joint space.

The trajectory is a synchronized trapezoidal velocity profile: all joints
start and stop together, no joint exceeds its velocity or acceleration
limit (scaled by the caller's factors), and it is sampled with positions
and velocities at the profile's corners and on a regular grid.
"""
from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

from .trajectory_goal import TrajectoryPoint

__all__ = ["PlanningError", "JointLimit", "group_states_from_srdf", "target_positions",
           "limits_from_joint_limits", "plan_point_to_point"]


class PlanningError(Exception):
    """Bad input to go_to_pose (unknown state, missing limit, bad file)."""


@dataclass(frozen=True)
class JointLimit:
    max_velocity: float
    max_acceleration: float


def group_states_from_srdf(text: str, source: str = "SRDF") -> Dict[str, Dict[str, Dict[str, float]]]:
    """``{group: {state: {joint: value}}}`` from an SRDF document's group_state elements."""
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise PlanningError("%s is not valid XML: %s" % (source, exc)) from exc
    states: Dict[str, Dict[str, Dict[str, float]]] = {}
    for gs in root.iter("group_state"):
        name, group = gs.get("name"), gs.get("group")
        if not name or not group:
            raise PlanningError("%s: a group_state lacks its name or group attribute" % source)
        joints: Dict[str, float] = {}
        for joint in gs.iter("joint"):
            jname, value = joint.get("name"), joint.get("value")
            try:
                number = float((value or "").split()[0])
            except (ValueError, IndexError):
                raise PlanningError("%s: group_state '%s' joint '%s' has value %r, not a number"
                                    % (source, name, jname, value)) from None
            if not jname or not math.isfinite(number):
                raise PlanningError("%s: group_state '%s' has a joint without name or a non-finite value"
                                    % (source, name))
            joints[jname] = number
        states.setdefault(group, {})[name] = joints
    return states


def target_positions(states: Mapping[str, Mapping[str, Mapping[str, float]]], group: str, state: str,
                     joint_names: Sequence[str]) -> List[float]:
    """Positions of ``joint_names`` in group state ``state`` of ``group``."""
    if group not in states:
        raise PlanningError("the SRDF has no group states for group '%s' (groups: %s)"
                            % (group, ", ".join(sorted(states)) or "none"))
    if state not in states[group]:
        raise PlanningError("group '%s' has no state '%s' (states: %s)"
                            % (group, state, ", ".join(sorted(states[group]))))
    values = states[group][state]
    missing = [j for j in joint_names if j not in values]
    if missing:
        raise PlanningError("state '%s' gives no value for joint(s) %s" % (state, ", ".join(missing)))
    return [values[j] for j in joint_names]


def limits_from_joint_limits(data: Mapping[str, Any], joint_names: Sequence[str],
                             default_acceleration: Optional[float] = None,
                             source: str = "joint_limits.yaml") -> Dict[str, JointLimit]:
    """Velocity and acceleration limits from MoveIt's joint_limits.yaml content."""
    table = data.get("joint_limits") if isinstance(data, Mapping) else None
    if not isinstance(table, Mapping):
        raise PlanningError("%s has no 'joint_limits' mapping" % source)
    limits: Dict[str, JointLimit] = {}
    for name in joint_names:
        entry = table.get(name)
        if not isinstance(entry, Mapping):
            raise PlanningError("%s: no limits for joint '%s'" % (source, name))
        if not entry.get("has_velocity_limits", False):
            raise PlanningError("%s: joint '%s' has no velocity limit (has_velocity_limits: false)" % (source, name))
        vel = _positive(entry.get("max_velocity"), "%s: joint_limits/%s/max_velocity" % (source, name))
        if entry.get("has_acceleration_limits", False):
            acc = _positive(entry.get("max_acceleration"), "%s: joint_limits/%s/max_acceleration" % (source, name))
        elif default_acceleration is not None:
            acc = _positive(default_acceleration, "default acceleration")
        else:
            raise PlanningError("%s: joint '%s' has no acceleration limit; set has_acceleration_limits "
                                "and max_acceleration or give a default acceleration" % (source, name))
        limits[name] = JointLimit(vel, acc)
    return limits


def _positive(value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise PlanningError("%s must be a positive number, got %r" % (what, value))
    return float(value)


def plan_point_to_point(joint_names: Sequence[str], start: Sequence[float], goal: Sequence[float],
                        limits: Mapping[str, JointLimit], velocity_scaling: float = 1.0,
                        acceleration_scaling: float = 1.0, sample_period: float = 0.05) -> List[TrajectoryPoint]:
    """Points (time_from_start > 0) from ``start`` to ``goal``; [] when already there."""
    for what, value in (("velocity scaling", velocity_scaling), ("acceleration scaling", acceleration_scaling)):
        if not (isinstance(value, (int, float)) and 0.0 < value <= 1.0):
            raise PlanningError("%s must be in (0, 1], got %r" % (what, value))
    if not (isinstance(sample_period, (int, float)) and 0.0 < sample_period <= 1.0):
        raise PlanningError("sample period must be in (0, 1] s, got %r" % (sample_period,))
    if not (len(joint_names) == len(start) == len(goal)):
        raise PlanningError("joint names, start and goal differ in length")
    if not all(math.isfinite(v) for v in list(start) + list(goal)):
        raise PlanningError("start and goal positions must be finite numbers")
    deltas = [g - s for s, g in zip(start, goal)]
    # Profile of a path parameter u in [0, 1]: the tightest joint sets its limits.
    v_u = a_u = math.inf
    for name, d in zip(joint_names, deltas):
        if abs(d) > 1e-12:
            lim = limits[name]
            v_u = min(v_u, lim.max_velocity * velocity_scaling / abs(d))
            a_u = min(a_u, lim.max_acceleration * acceleration_scaling / abs(d))
    if math.isinf(v_u):
        return []
    if v_u * v_u / a_u >= 1.0:  # never reaches cruise speed: triangular profile
        t_acc = math.sqrt(1.0 / a_u)
        v_u = a_u * t_acc
        t_cruise = 0.0
    else:
        t_acc = v_u / a_u
        t_cruise = 1.0 / v_u - t_acc
    total = 2.0 * t_acc + t_cruise

    def profile(t: float) -> Tuple[float, float]:  # path parameter and its rate
        if t < t_acc:
            return 0.5 * a_u * t * t, a_u * t
        if t < t_acc + t_cruise:
            return 0.5 * a_u * t_acc ** 2 + v_u * (t - t_acc), v_u
        r = max(total - t, 0.0)
        return 1.0 - 0.5 * a_u * r * r, a_u * r

    n = max(int(math.ceil(total / sample_period)), 1)
    # Sample on the grid plus the profile's corners, with positions and
    # velocities only: within one phase the profile is a quadratic, which the
    # controller's cubic segments reproduce exactly, so no segment exceeds a
    # limit. (Accelerations would force quintics that overshoot at corners.)
    times = sorted({min(k * sample_period, total) for k in range(1, n + 1)}
                   | {t for t in (t_acc, t_acc + t_cruise) if 0.0 < t < total})
    points: List[TrajectoryPoint] = []
    for t in times:
        u, du = profile(t) if t < total else (1.0, 0.0)
        points.append(TrajectoryPoint(
            positions=tuple(s + d * u for s, d in zip(start, deltas)),
            velocities=tuple(d * du for d in deltas),
            time_from_start=t))
    return points
