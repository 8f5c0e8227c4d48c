"""What the locomotion_control action servers share, kept ROS-free.

- ``Planner``: an LC goal (mode + body velocity, or per-wheel angles and
  speeds) -> a RoverCommand within the limits and its set points in pulses.
- ``CompletionTracker``: which drive nodes have reported task_completed for
  the present goal; thread-safe, since feedback arrives on the CAN thread.
- ``wait_for_completion``: the goal's wait for the four flags, timeout and
  preemption.
- ``SimulatedJoints``: the wheels of locomotion_control_simulation (no CAN).
- ``GoalRunner``: one goal from plan to result, for both action servers.

The mode numbers are the constants of action/LocomotionControl.action.
"""
from __future__ import annotations

import math
import threading
import time
from typing import Callable, Dict, Iterable, List, Optional, Sequence, Tuple

from .config import WHEELS, ManiConfig
from .kinematics import (MODE_ACKERMANN, MODE_CRAB, MODE_POINT_TURN, MODE_VECTOR, Kinematics,
                         KinematicsError, RoverCommand)
from .protocol import DRIVE_NODES, NODE_NAMES

# LocomotionControl.action goal modes.
GOAL_WHEELS = 0
GOAL_MODES: Dict[int, str] = {1: MODE_ACKERMANN, 2: MODE_POINT_TURN, 3: MODE_CRAB, 4: MODE_VECTOR}


class Planner:
    """LC goal -> RoverCommand and set points; remembers the steering angles
    so that a wheel that stops keeps its angle."""

    def __init__(self, config: ManiConfig) -> None:
        self.kinematics = Kinematics(config)
        self.angles: Dict[str, float] = {wheel: 0.0 for wheel in WHEELS}

    def plan(self, mode: int, vx: float, vy: float, wz: float,
             steering_angle: Sequence[float] = (), wheel_velocity: Sequence[float] = ()
             ) -> Tuple[RoverCommand, Dict[int, Tuple[int, int]]]:
        """(command, node_id -> (orientation pulses, velocity pulses/s)).
        Raises KinematicsError (a ValueError) with the reason for a goal the
        rover cannot execute."""
        if mode == GOAL_WHEELS:
            command = self.kinematics.wheels_command(list(steering_angle), list(wheel_velocity))
        elif mode in GOAL_MODES:
            command = self.kinematics.body_to_wheels(vx, vy, wz, GOAL_MODES[mode], self.angles)
        else:
            raise KinematicsError("unknown goal mode %r (0 wheels, 1 ackermann, 2 point_turn, "
                                  "3 crab, 4 vector)" % (mode,))
        return command, self.kinematics.set_points(command)

    def plan_goal(self, goal) -> Tuple[RoverCommand, Dict[int, Tuple[int, int]]]:
        """plan() for a LocomotionControlGoal (or anything with its fields)."""
        return self.plan(goal.mode, goal.twist.linear.x, goal.twist.linear.y, goal.twist.angular.z,
                         goal.steering_angle, goal.wheel_velocity)

    def commanded(self, command: RoverCommand) -> None:
        """The command went out: its angles are the wheels' new positions."""
        self.angles = {wheel: c.angle for wheel, c in command.wheels.items()}


def wheel_list(nodes: Iterable[int]) -> str:
    """'front_left (node 1), rear_right (node 3)'."""
    return ", ".join("%s (node %d)" % (NODE_NAMES[n], n) for n in sorted(nodes))


class CompletionTracker:
    """task_completed flags of the four drive nodes for the running goal.

    A node's feedback counts only after ``arm(node)``, i.e. after both set
    points of this goal were sent to it: a task_completed still on its way
    for the previous goal must not finish the new one.
    """

    def __init__(self, nodes: Sequence[int] = DRIVE_NODES) -> None:
        self.nodes = tuple(nodes)
        self._cond = threading.Condition()
        self._armed: Dict[int, bool] = {}
        self._done: Dict[int, bool] = {}
        self.changes = 0
        self.start()

    def start(self) -> None:
        with self._cond:
            self._armed = {n: False for n in self.nodes}
            self._done = {n: False for n in self.nodes}
            self.changes += 1
            self._cond.notify_all()

    def arm(self, node_id: int) -> None:
        with self._cond:
            self._armed[node_id] = True

    def report(self, node_id: int, task_completed: bool) -> None:
        with self._cond:
            if node_id in self._armed and self._armed[node_id] and self._done[node_id] != task_completed:
                self._done[node_id] = task_completed
                self.changes += 1
                self._cond.notify_all()

    def wait(self, timeout: float, seen_changes: int) -> int:
        """Block until a flag changes after ``seen_changes`` or ``timeout``
        seconds pass; returns the change counter."""
        with self._cond:
            if self.changes == seen_changes:
                self._cond.wait(timeout)
            return self.changes

    def flags(self) -> List[bool]:
        """task_completed per node, in node order (front_left first)."""
        with self._cond:
            return [self._done[n] for n in self.nodes]

    def all_done(self) -> bool:
        return all(self.flags())

    def missing(self) -> List[int]:
        with self._cond:
            return [n for n in self.nodes if not self._done[n]]

    def timeout_text(self, seconds: float) -> str:
        return ("timeout: no task_completed within %.1f s from %s"
                % (seconds, wheel_list(self.missing())))


def describe_limits(command: RoverCommand) -> str:
    """'' or '; limited: speed scaled by 0.8 to MAX_VEL' for a status text."""
    return "; limited: " + ", ".join(command.limited) if command.limited else ""


def optional_float(value: Optional[float], default: float) -> float:
    """A goal's timeout: 0 or less, not finite, or None means the configured default."""
    if value is None or not math.isfinite(value) or value <= 0.0:
        return default
    return float(value)


SUCCEEDED = "succeeded"
TIMEOUT = "timeout"
PREEMPTED = "preempted"


def wait_for_completion(tracker: CompletionTracker, timeout: float,
                        preempted: Callable[[], bool],
                        on_change: Callable[[List[bool]], None],
                        clock: Callable[[], float] = time.monotonic,
                        poll: float = 0.02) -> str:
    """Wait until all tracked nodes completed (SUCCEEDED), ``timeout`` seconds
    passed (TIMEOUT) or ``preempted()`` is true (PREEMPTED); ``on_change``
    gets the flags first and whenever they change."""
    deadline = clock() + timeout
    seen = -1
    while True:
        if preempted():
            return PREEMPTED
        changes = tracker.wait(poll, seen)
        if changes != seen:
            seen = changes
            on_change(tracker.flags())
        if tracker.all_done():
            return SUCCEEDED
        if clock() >= deadline:
            return TIMEOUT


class SimulatedJoints:
    """Steering and wheel joints of the four wheels without any CAN: the
    steering turns at simulation.steer_rate, the wheel ramps at
    simulation.drive_acceleration, and a wheel reports task_completed to the
    tracker when both reach the set point (the tolerances of the simulated
    drive nodes, converted to rad and m/s)."""

    def __init__(self, config: ManiConfig, tracker: CompletionTracker) -> None:
        sim = config.simulation
        self.tracker = tracker
        self.steer_rate = sim.steer_rate
        self.acceleration = sim.drive_acceleration
        self.radius = config.rover.wheel_radius
        self.angle_tolerance = sim.orientation_tolerance * 2.0 * math.pi / config.STEER_ENC_PPR
        self.speed_tolerance = sim.velocity_tolerance * config.wheel_circumference / config.DRIVE_ENC_PPR
        self._lock = threading.Lock()
        self.angle = {wheel: 0.0 for wheel in WHEELS}        # [rad]
        self.speed = {wheel: 0.0 for wheel in WHEELS}        # [m/s] rim speed
        self.rotation = {wheel: 0.0 for wheel in WHEELS}     # [rad] wheel joint position
        self.target_angle = dict(self.angle)
        self.target_speed = dict(self.speed)
        self.pending = {wheel: False for wheel in WHEELS}

    def command(self, command: RoverCommand) -> None:
        """New set points; every wheel reports again when it reaches them."""
        with self._lock:
            for wheel, c in command.wheels.items():
                self.target_angle[wheel], self.target_speed[wheel] = c.angle, c.speed
                self.pending[wheel] = True
        for node in DRIVE_NODES:
            self.tracker.arm(node)

    def stop(self) -> None:
        """Wheels ramp down to 0, steering stays; nothing more is reported."""
        with self._lock:
            for wheel in WHEELS:
                self.target_speed[wheel] = 0.0
                self.pending[wheel] = False

    @staticmethod
    def _toward(value: float, target: float, step: float) -> float:
        return min(target, value + step) if target >= value else max(target, value - step)

    def step(self, dt: float) -> None:
        """Advance the joints by dt seconds."""
        done = []
        with self._lock:
            for node, wheel in zip(DRIVE_NODES, WHEELS):
                self.angle[wheel] = self._toward(self.angle[wheel], self.target_angle[wheel],
                                                 self.steer_rate * dt)
                before = self.speed[wheel]
                self.speed[wheel] = self._toward(before, self.target_speed[wheel],
                                                 self.acceleration * dt)
                self.rotation[wheel] += (before + self.speed[wheel]) / 2.0 * dt / self.radius
                if (self.pending[wheel]
                        and abs(self.angle[wheel] - self.target_angle[wheel]) <= self.angle_tolerance
                        and abs(self.speed[wheel] - self.target_speed[wheel]) <= self.speed_tolerance):
                    self.pending[wheel] = False
                    done.append(node)
        for node in done:
            self.tracker.report(node, True)

    def joint_values(self) -> Tuple[List[float], List[float], List[float]]:
        """(positions, velocities, efforts=[]) of the steering joints then the
        wheel joints, WHEELS order: angles [rad], wheel rotation [rad],
        steering rates are not modelled (0), wheel rates [rad/s]."""
        with self._lock:
            positions = [self.angle[w] for w in WHEELS] + [self.rotation[w] for w in WHEELS]
            velocities = [0.0] * len(WHEELS) + [self.speed[w] / self.radius for w in WHEELS]
        return positions, velocities, []


def outcome_text(outcome: str, tracker: CompletionTracker, timeout: float,
                 command: RoverCommand) -> str:
    """The status text of a finished goal."""
    if outcome == SUCCEEDED:
        text = "all four wheels report task_completed"
    elif outcome == PREEMPTED:
        text = "preempted"
    else:
        text = tracker.timeout_text(timeout)
    return text + describe_limits(command)


# LocomotionControl.action result outcome constants.
RESULT_OUTCOME = {SUCCEEDED: 0, TIMEOUT: 1, PREEMPTED: 2}


def finish_goal(server, outcome: str, result, text: str) -> None:
    """End the goal of an actionlib SimpleActionServer (duck-typed, so this
    module stays ROS-free) with the outcome of wait_for_completion()."""
    result.outcome = RESULT_OUTCOME[outcome]
    result.status = text
    if outcome == PREEMPTED:
        server.set_preempted(result, text)
    elif outcome == SUCCEEDED:
        server.set_succeeded(result, text)
    else:
        server.set_aborted(result, text)


# start() of GoalRunner.execute: sends a planned goal to the drives; returns
# None when sent, or (result outcome constant name, reason) when it was not.
Starter = Callable[[RoverCommand, Dict[int, Tuple[int, int]]], Optional[Tuple[str, str]]]


class GoalRunner:
    """One LC goal from start to end, shared by both action servers.

    ROS enters only through duck-typed objects, so this stays ROS-free: an
    actionlib SimpleActionServer, the action's Result and Feedback message
    classes (their constants name the outcomes), a clock and loggers.
    """

    def __init__(self, server, result_type, feedback_type, planner: Planner,
                 tracker: CompletionTracker, default_timeout: float,
                 clock: Callable[[], float], log_warn: Callable[[str], None],
                 log_error: Callable[[str], None],
                 stopping: Callable[[], bool] = lambda: False) -> None:
        self.server = server
        self.stopping = stopping   # true while the node shuts down: end the wait
        self.result_type = result_type
        self.feedback_type = feedback_type
        self.planner = planner
        self.tracker = tracker
        self.default_timeout = default_timeout
        self.clock = clock
        self.log_warn = log_warn
        self.log_error = log_error

    def _abort(self, outcome: str, text: str, set_points=None) -> None:
        result = self.result_type(outcome=getattr(self.result_type, outcome), status=text,
                                  task_completed=self.tracker.flags())
        if set_points:
            result.set_orientation = [set_points[n][0] for n in DRIVE_NODES]
            result.set_velocity = [set_points[n][1] for n in DRIVE_NODES]
        self.server.set_aborted(result, text)

    def execute(self, goal, start: Starter, stop: Callable[[], str],
                on_timeout: Callable[[List[int]], None] = lambda missing: None) -> None:
        """Plan, start(), wait for the four task_completed, end the goal.
        stop() runs when the goal is canceled with no new goal to follow and
        returns a note for the status; on_timeout gets the silent nodes.
        Never raises: an unexpected error aborts the goal as BUS_ERROR."""
        try:
            self._execute(goal, start, stop, on_timeout)
        except Exception as exc:  # noqa: BLE001 - the server must survive any goal
            self.log_error("internal error: %s" % exc)
            if self.server.is_active():
                self._abort("BUS_ERROR", "internal error: %s" % exc)

    def _execute(self, goal, start: Starter, stop: Callable[[], str],
                 on_timeout: Callable[[List[int]], None]) -> None:
        timeout = optional_float(goal.timeout, self.default_timeout)
        self.tracker.start()
        try:
            command, set_points = self.planner.plan_goal(goal)
        except ValueError as exc:
            text = "invalid goal: %s" % exc
            self.log_warn(text)
            self._abort("INVALID_GOAL", text)
            return
        refused = start(command, set_points)
        if refused is not None:
            outcome, text = refused
            self.log_warn(text)
            self._abort(outcome, text, set_points)
            return
        self.planner.commanded(command)
        outcome = wait_for_completion(
            self.tracker, timeout,
            preempted=lambda: self.server.is_preempt_requested() or self.stopping(),
            on_change=lambda flags: self.server.publish_feedback(self.feedback_type(
                task_completed=flags, status="%d of 4 wheels completed" % sum(flags))),
            clock=self.clock)
        text = outcome_text(outcome, self.tracker, timeout, command)
        if outcome == PREEMPTED and not self.server.is_new_goal_available():
            text += "; no new goal: " + stop()
        elif outcome == TIMEOUT:
            self.log_warn(text)
            on_timeout(self.tracker.missing())
        result = self.result_type(task_completed=self.tracker.flags(),
                                  set_orientation=[set_points[n][0] for n in DRIVE_NODES],
                                  set_velocity=[set_points[n][1] for n in DRIVE_NODES])
        finish_goal(self.server, outcome, result, text)
