"""``position_controllers/JointTrajectoryController`` for the controller manager.

ROS-free: owns a ``TrajectoryExecutor`` and, once per SYNC cycle
(``cycle``, called from the driver's per-cycle hook), samples the running
trajectory and sets each joint's CSP target (0x607A through the joint's
position command). The ROS adapter (``maxon_epos4_ros_canopen_node.trajectory_action``) turns
actions, topics and services into ``submit``/``cancel``/``query_state`` and
learns how goals end through ``on_outcome``.

Importing this module registers the type with ``controllers``.
"""
from __future__ import annotations

import math
import threading
import time
from typing import Any, Callable, List, Mapping, Optional, Sequence, Tuple

from .cia402 import OperationMode
from .controllers import Controller, ControllerError, parse_joints, register_controller_type
from .result import Result, fail, ok
from .trajectory import CycleOutput, Outcome, TrajectoryExecutor, csp_readiness_problem
from .trajectory_goal import INVALID_GOAL, PATH_TOLERANCE_VIOLATED, TrajectoryError, TrajectoryPoint
from .trajectory_spline import Sample
from .trajectory_tolerances import tolerances_from_constraints

__all__ = ["TYPE_NAME", "JointTrajectoryController", "interpolation_period_problem"]

TYPE_NAME = "position_controllers/JointTrajectoryController"
CSP = int(OperationMode.CYCLIC_SYNC_POSITION)


def interpolation_period_problem(joint: str, period_value: Any, period_index: Any, sync_interval_ms: float) -> str:
    """Why the drive's 0x60C2 does not match the SYNC period ("" when it does).

    The EPOS4 interpolates between consecutive CSP targets over 0x60C2
    (value sub1 times 10^index s, sub2); maxon advises it equal the SYNC
    period, or motion between targets is jerky.
    """
    try:
        value, index = int(period_value), int(period_index)
    except (TypeError, ValueError):
        return "joint '%s': interpolation time period 0x60C2 unreadable (%r, %r)" % (joint, period_value,
                                                                                     period_index)
    period_ms = value * 10.0 ** (index + 3)
    if sync_interval_ms <= 0:
        return "joint '%s': SYNC is disabled (sync/interval_ms 0) but CSP needs cyclic targets" % joint
    if abs(period_ms - sync_interval_ms) > 1e-6:
        return ("joint '%s': interpolation time period 0x60C2 is %g ms but sync/interval_ms is %g ms; set "
                "dcf_overlay \"60C2sub1\": \"%d\" (with \"60C2sub2\": \"-3\") so the drive interpolates over "
                "one SYNC period" % (joint, period_ms, sync_interval_ms, int(round(sync_interval_ms))))
    return ""


def _positive(name: str, params: Mapping[str, Any], key: str, default: float, allow_zero: bool = False) -> float:
    value = params.get(key, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or value < 0 or (value == 0 and not allow_zero):
        raise ControllerError("%s/%s must be a %s number, got %r"
                              % (name, key, "non-negative" if allow_zero else "positive", value))
    return float(value)


class JointTrajectoryController(Controller):
    """Follows joint trajectories in Cyclic Synchronous Position mode."""

    type_name = TYPE_NAME
    interface = "position"
    claims_joints = True

    def __init__(self, name: str, params: Mapping[str, Any], joints: Sequence[str],
                 required_drive_mode: Optional[int], position_limits: Optional[Mapping[str, Tuple[float, float]]] = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(name, params, joints, required_drive_mode)
        try:
            tolerances = tolerances_from_constraints(self.joints, params.get("constraints"), name + "/constraints")
        except ValueError as exc:
            raise ControllerError(str(exc)) from None
        allow_partial = params.get("allow_partial_joints_goal", False)
        if not isinstance(allow_partial, bool):
            raise ControllerError("%s/allow_partial_joints_goal must be true or false, got %r" % (name, allow_partial))
        self.state_publish_rate = _positive(name, params, "state_publish_rate", 25.0)
        self.action_monitor_rate = _positive(name, params, "action_monitor_rate", 20.0)
        self.executor = TrajectoryExecutor(
            self.joints, tolerances, _positive(name, params, "stop_trajectory_duration", 0.2, allow_zero=True),
            allow_partial, position_limits)
        self.clock = clock  # the adapter sets ROS time so header stamps compare
        self.on_outcome: List[Callable[[Outcome], None]] = []
        self.warnings: List[str] = []
        self.last_cycle: Optional[CycleOutput] = None
        self.last_actual: Optional[Sample] = None
        # Per joint, the last target the driver accepted from this
        # controller. Targets come from the trajectory, from these, or from
        # the driver's own target (target_position: a command or a position
        # it read over SDO), never from TxPDO readings: anyone on the bus can
        # forge those. Readings only judge the tolerances.
        self._sent: List[float] = [math.nan] * len(self.joints)
        self._not_ready = "not started"
        self._lock = threading.RLock()

    # --- lifecycle (controller manager) --------------------------------
    def starting(self, backend: Any) -> Result:
        try:
            positions = self._driver_targets([backend.joints[j] for j in self.joints])
        except (AttributeError, KeyError, TypeError, ValueError) as exc:
            return fail("joint targets unavailable: %s" % exc)
        unknown = [j for j, p in zip(self.joints, positions) if not math.isfinite(p)]
        if unknown:
            return fail("the driver holds no known position target for %s (driver not initialised?)"
                        % ", ".join(unknown))
        with self._lock:
            self.executor.reset(self.clock(), positions)
            self._sent = list(positions)
            self._not_ready = ""
            # Reject goals beyond the driver's joint limits up front instead of
            # aborting halfway when the driver refuses a target.
            for joint in self.joints:
                limits = getattr(backend.joints[joint], "limits", None)
                lower, upper = getattr(limits, "lower", None), getattr(limits, "upper", None)
                if lower is not None and upper is not None:
                    self.executor.position_limits[joint] = (float(lower), float(upper))
        self.warnings = self._check_interpolation_period(backend)
        return ok("; ".join(self.warnings))

    def stopping(self, backend: Any) -> None:
        with self._lock:
            outcome = self.executor.stop(self.clock())
            if outcome is not None:
                outcome = Outcome(outcome.goal_id, PATH_TOLERANCE_VIOLATED, "controller %s stopped" % self.name)
        self._notify(outcome)

    def _check_interpolation_period(self, backend: Any) -> List[str]:
        config = getattr(backend, "config", None)
        interval = getattr(getattr(config, "sync", None), "interval_ms", None)
        get_object = getattr(backend, "get_object", None)
        if interval is None or get_object is None:
            return []
        warnings = []
        for joint in self.joints:
            value = get_object(joint, "60C2sub1", False)
            index = get_object(joint, "60C2sub2", False)
            if not (getattr(value, "success", False) and getattr(index, "success", False)):
                warnings.append("joint '%s': cannot read 0x60C2 (%s)" % (joint, getattr(value, "message", "")))
                continue
            problem = interpolation_period_problem(joint, _as_int(value.value), _as_int(index.value), interval)
            if problem:
                warnings.append(problem)
        return warnings

    # --- requests (ROS threads) ------------------------------------------
    def submit(self, goal_id: Any, joint_names: Sequence[str], points: Sequence[TrajectoryPoint], stamp: float,
               path_tolerance: Sequence[Tuple[str, float, float, float]] = (),
               goal_tolerance: Sequence[Tuple[str, float, float, float]] = (),
               goal_time_tolerance: float = 0.0) -> Optional[Outcome]:
        """Start a goal (goal_id None: a topic command); returns the preempted goal's outcome.

        Raises TrajectoryError when the goal is rejected.

        The goal is validated and built outside the lock the cycle takes
        every SYNC (10,000 points take a while); the cycle then takes the
        built goal, an immutable object, and splices it on at the time it
        was accepted, from where the targets sent last were going.
        """
        with self._lock:
            self._check_ready()
            now = self.clock()
            holding = self.executor.query_state(max(now, stamp), now).positions
            limits = dict(self.executor.position_limits)
        prepared, tolerances = self.executor.prepare(joint_names, points, stamp, now, holding, path_tolerance,
                                                     goal_tolerance, goal_time_tolerance, limits)
        with self._lock:
            self._check_ready()
            return self.executor.accept(goal_id, prepared, tolerances, self.clock())

    def _check_ready(self) -> None:
        if not self.running:
            raise TrajectoryError(INVALID_GOAL, "controller %s is not running" % self.name)
        if self._not_ready:
            raise TrajectoryError(INVALID_GOAL, self._not_ready)

    def cancel(self, goal_id: Any) -> bool:
        with self._lock:
            return self.executor.cancel(goal_id, self.clock())

    def query_state(self, t: float) -> Sample:
        with self._lock:
            if not self.executor.started:
                raise TrajectoryError(INVALID_GOAL, "controller %s has not started" % self.name)
            return self.executor.query_state(t, self.clock())

    # --- every SYNC (driver thread) ----------------------------------------
    def cycle(self, backend: Any) -> None:
        """Sample the trajectory and set the CSP targets; never raises."""
        if not self.running:
            return
        outcomes: List[Outcome] = []
        try:
            with self._lock:
                self._cycle(backend, outcomes)
        except Exception as exc:  # a bug here must not kill the driver's cycle thread
            with self._lock:
                outcome = self.executor.abort(self.clock(), self._last_sent(), PATH_TOLERANCE_VIOLATED,
                                              "internal error: %r" % (exc,))
            outcomes.append(outcome)
        for outcome in outcomes:
            self._notify(outcome)

    def _last_sent(self) -> List[float]:
        """The targets sent last (the desired ones for a joint never sent to)."""
        desired = self.executor.query_state(self.clock()).positions
        return [s if math.isfinite(s) else d for s, d in zip(self._sent, desired)]

    def _driver_targets(self, joints: Sequence[Any]) -> List[float]:
        """Where the driver holds each joint now: its own position target
        (the last command, or the position it read over SDO when it enabled
        the drive); the last target sent from here where it tells none."""
        out = []
        for joint, sent in zip(joints, self._sent):
            target = float(getattr(joint, "target_position", math.nan))
            out.append(target if math.isfinite(target) else sent)
        return out

    def _send(self, backend: Any, name: str, j: int, target: float) -> Any:
        result = backend.set_command(name, "position", target)
        if getattr(result, "success", False):
            self._sent[j] = target
        return result

    def _cycle(self, backend: Any, outcomes: List[Outcome]) -> None:
        now = self.clock()
        joints = [backend.joints[j] for j in self.joints]
        positions = tuple(float(j.position) for j in joints)
        velocities = tuple(float(j.velocity) for j in joints)
        self.last_actual = Sample(positions, velocities, (0.0,) * len(positions))
        problems = [_joint_problem(name, joint) for name, joint in zip(self.joints, joints)]
        problem = next((p for p in problems if p), "")
        if problem:
            if not self._not_ready:
                # The joints that still can follow decelerate to rest over
                # stop_trajectory_duration instead of freezing at full speed.
                outcomes.append(self.executor.abort_and_stop(now, PATH_TOLERANCE_VIOLATED, "aborted: %s" % problem))
            self._not_ready = problem
            out = self.executor.update(now, positions, velocities)
            self.last_cycle = out
            for j, (name, target, joint_problem) in enumerate(zip(self.joints, out.desired.positions, problems)):
                if not joint_problem:
                    self._send(backend, name, j, target)
            return
        if self._not_ready:
            # Back after recover/re-enable: hold where the driver holds the
            # joints (recover enables at 0x6064 read over SDO), so nothing
            # jumps and no reading becomes a target.
            held = self._driver_targets(joints)
            unknown = [n for n, p in zip(self.joints, held) if not math.isfinite(p)]
            if unknown:
                self._not_ready = "joint(s) %s: the driver's position target is unknown" % ", ".join(unknown)
                return
            self.executor.reset(now, held)
            self._sent = list(held)
            self._not_ready = ""
        # the goal is judged on readings no older than what they must prove:
        # after a starved stretch the first readings taken in can predate it
        age = max(_motion_age(joint) for joint in joints)
        out = self.executor.update(now, positions, velocities, now - age)
        self.last_cycle = out
        outcomes.append(out.outcome)
        for j, (name, target) in enumerate(zip(self.joints, out.desired.positions)):
            result = self._send(backend, name, j, target)
            if not getattr(result, "success", False):
                reason = "joint '%s' refused target %.6f: %s" % (name, target, getattr(result, "message", ""))
                outcomes.append(self.executor.abort(now, self._last_sent(), PATH_TOLERANCE_VIOLATED, reason))
                break

    def _notify(self, outcome: Optional[Outcome]) -> None:
        if outcome is None:
            return
        for listener in list(self.on_outcome):
            listener(outcome)


def _motion_age(joint: Any) -> float:
    """The age (s) of a joint's position and velocity readings; infinite
    while one has not arrived, 0.0 for a joint that does not tell."""
    motion_age = getattr(joint, "motion_age", None)
    if motion_age is None:
        return 0.0
    age = float(motion_age())
    return age if not math.isnan(age) else math.inf


def _joint_problem(name: str, joint: Any) -> str:
    """Why the driver's joint cannot follow CSP targets now ("" when it can)."""
    error = getattr(joint, "error", None)
    if error:
        return "joint '%s' is in error (%s)" % (name, error)
    if getattr(joint, "halted", False):
        return "joint '%s' is halted (call driver/recover)" % name
    # mode_display is the drive's own 0x6061; `mode` is what was requested
    mode = getattr(joint, "mode_display", getattr(joint, "mode", None))
    return csp_readiness_problem(name, getattr(joint, "state", None), mode)


def _as_int(value: Any) -> Any:
    if isinstance(value, str):
        try:
            return int(value, 0)
        except ValueError:
            return value
    return value


def _factory(name: str, params: Mapping[str, Any], manager: Any) -> Controller:
    joints = parse_joints(name, params, manager.joint_names, group=True)
    mode = params.get("required_drive_mode", CSP)
    if mode != CSP or isinstance(mode, bool):
        raise ControllerError("%s/required_drive_mode must be 8 (Cyclic Synchronous Position), got %r"
                              % (name, mode))
    return JointTrajectoryController(name, params, joints, CSP)


register_controller_type(TYPE_NAME, _factory)
