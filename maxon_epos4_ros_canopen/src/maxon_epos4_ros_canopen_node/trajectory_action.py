"""ROS side of ``position_controllers/JointTrajectoryController``.

For each loaded JointTrajectoryController, in its namespace
(``/maxon/canopen_motor/joint_trajectory_controller`` in the CSP example):

- ``follow_joint_trajectory``: control_msgs/FollowJointTrajectory action
  server (what MoveIt's simple controller manager talks to);
- ``command``: trajectory_msgs/JointTrajectory topic (an empty trajectory
  stops and holds);
- ``state``: control_msgs/JointTrajectoryControllerState at
  ``state_publish_rate``;
- ``query_state``: control_msgs/QueryTrajectoryState service.

The ROS-free ``JointTrajectoryController`` does the work; its ``cycle`` runs
in the driver's per-SYNC hook. Goal outcomes reach actionlib through a worker
thread so that the SYNC cycle never waits for ROS publishing.

The canopen_motor node wires this in with ``attach(manager, driver,
namespace_of)``. rospy is imported here only, never by the core.
"""
from __future__ import annotations

import queue
import threading
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import actionlib
import rospy
from actionlib_msgs.msg import GoalStatus
from control_msgs.msg import (FollowJointTrajectoryAction, FollowJointTrajectoryFeedback,
                              FollowJointTrajectoryResult, JointTrajectoryControllerState)
from control_msgs.srv import QueryTrajectoryState, QueryTrajectoryStateResponse
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from maxon_epos4_ros_canopen.trajectory import Outcome
from maxon_epos4_ros_canopen.trajectory_controller import JointTrajectoryController
from maxon_epos4_ros_canopen.trajectory_goal import RESULT_NAMES, SUCCESSFUL, TrajectoryError, TrajectoryPoint

__all__ = ["RosTrajectoryController", "attach", "points_from_msg", "tolerances_from_msg"]


def points_from_msg(msg: JointTrajectory) -> List[TrajectoryPoint]:
    return [TrajectoryPoint(tuple(p.positions), tuple(p.velocities), tuple(p.accelerations),
                            p.time_from_start.to_sec()) for p in msg.points]


def tolerances_from_msg(tolerances: Sequence[Any]) -> List[Tuple[str, float, float, float]]:
    return [(t.name, t.position, t.velocity, t.acceleration) for t in tolerances]


def _point(positions: Sequence[float], velocities: Sequence[float] = (),
           accelerations: Sequence[float] = ()) -> JointTrajectoryPoint:
    return JointTrajectoryPoint(positions=list(positions), velocities=list(velocities),
                                accelerations=list(accelerations))


class RosTrajectoryController:
    """Action server, topics and service of one JointTrajectoryController."""

    def __init__(self, controller: JointTrajectoryController, driver: Any, namespace: str) -> None:
        self.controller = controller
        self.driver = driver
        self.ns = namespace.rstrip("/")
        controller.clock = lambda: rospy.Time.now().to_sec()  # header stamps are ROS time
        self._handles: Dict[str, Any] = {}  # goal id -> actionlib goal handle
        self._lock = threading.RLock()
        self._outcomes: "queue.Queue[Optional[Outcome]]" = queue.Queue()
        self._timers: List[rospy.Timer] = []
        self._closed = False
        controller.on_outcome.append(self._outcomes.put)
        self._worker = threading.Thread(target=self._deliver_outcomes, name=controller.name + "_outcomes",
                                        daemon=True)
        self._worker.start()
        self.state_pub = rospy.Publisher(self.ns + "/state", JointTrajectoryControllerState, queue_size=1)
        self.server = actionlib.ActionServer(self.ns + "/follow_joint_trajectory", FollowJointTrajectoryAction,
                                             self._on_goal, self._on_cancel, auto_start=False)
        self.server.start()
        self.command_sub = rospy.Subscriber(self.ns + "/command", JointTrajectory, self._on_command, queue_size=1)
        self.query_srv = rospy.Service(self.ns + "/query_state", QueryTrajectoryState, self._on_query)
        add = getattr(driver, "add_cycle_callback", None)
        if add is None:
            rospy.logerr("%s: the driver offers no per-cycle hook: trajectories cannot run", controller.name)
        else:
            add(self._cycle)

    # --- lifecycle --------------------------------------------------------
    def _cycle(self, *_args: Any) -> None:
        if not self._closed:
            self.controller.cycle(self.driver)

    def started(self) -> None:
        for warning in self.controller.warnings:
            rospy.logwarn("%s: %s", self.controller.name, warning)
        self._timers = [
            rospy.Timer(rospy.Duration(1.0 / self.controller.state_publish_rate), self._publish_state),
            rospy.Timer(rospy.Duration(1.0 / self.controller.action_monitor_rate), self._publish_feedback),
        ]

    def stopped(self) -> None:
        for timer in self._timers:
            timer.shutdown()
        self._timers = []

    def close(self) -> None:
        """Controller unloaded: end goals, drop topics and services."""
        self.stopped()
        self._closed = True
        remove = getattr(self.driver, "remove_cycle_callback", None)
        if remove is not None:
            remove(self._cycle)
        self.command_sub.unregister()
        self.query_srv.shutdown("controller unloaded")
        self.state_pub.unregister()
        with self._lock:
            for handle in self._handles.values():
                self._finish(handle, Outcome(None, SUCCESSFUL, "controller unloaded"), canceled=True)
            self._handles.clear()
        self._outcomes.put(None)

    # --- action -------------------------------------------------------------
    def _on_goal(self, handle: Any) -> None:
        goal = handle.get_goal()
        goal_id = handle.get_goal_id().id
        try:
            with self._lock:
                preempted = self.controller.submit(
                    goal_id, goal.trajectory.joint_names, points_from_msg(goal.trajectory),
                    goal.trajectory.header.stamp.to_sec(), tolerances_from_msg(goal.path_tolerance),
                    tolerances_from_msg(goal.goal_tolerance), goal.goal_time_tolerance.to_sec())
                handle.set_accepted("executing")
                self._handles[goal_id] = handle
                if preempted is not None:
                    old = self._handles.pop(preempted.goal_id, None)
                    if old is not None:
                        self._finish(old, preempted, canceled=True)
        except TrajectoryError as exc:
            rospy.logwarn("%s: goal rejected (%s): %s", self.controller.name, RESULT_NAMES.get(exc.code), exc.message)
            handle.set_rejected(FollowJointTrajectoryResult(error_code=exc.code, error_string=exc.message),
                                exc.message)
        except Exception as exc:  # never let a goal kill the node
            rospy.logerr("%s: goal failed: %s: %s", self.controller.name, type(exc).__name__, exc)
            handle.set_rejected(FollowJointTrajectoryResult(error_code=FollowJointTrajectoryResult.INVALID_GOAL,
                                                            error_string=str(exc)), str(exc))

    def _on_cancel(self, handle: Any) -> None:
        goal_id = handle.get_goal_id().id
        with self._lock:
            self.controller.cancel(goal_id)
            known = self._handles.pop(goal_id, None)
            if known is not None:
                self._finish(known, Outcome(goal_id, SUCCESSFUL, "canceled: holding position"), canceled=True)

    def _finish(self, handle: Any, outcome: Outcome, canceled: bool = False) -> None:
        result = FollowJointTrajectoryResult(error_code=outcome.code, error_string=outcome.message)
        status = handle.get_goal_status().status
        if status not in (GoalStatus.ACTIVE, GoalStatus.PREEMPTING, GoalStatus.PENDING, GoalStatus.RECALLING):
            return
        if canceled:
            handle.set_canceled(result, outcome.message)
        elif outcome.code == SUCCESSFUL:
            handle.set_succeeded(result, outcome.message)
        else:
            rospy.logwarn("%s: goal aborted (%s): %s", self.controller.name, RESULT_NAMES.get(outcome.code),
                          outcome.message)
            handle.set_aborted(result, outcome.message)

    def _deliver_outcomes(self) -> None:
        while True:
            outcome = self._outcomes.get()
            if outcome is None:
                return
            try:
                with self._lock:
                    handle = self._handles.pop(outcome.goal_id, None)
                    if handle is not None:
                        self._finish(handle, outcome)
            except Exception as exc:
                rospy.logerr("%s: reporting a goal's end failed: %s", self.controller.name, exc)

    # --- topic and service -------------------------------------------------
    def _on_command(self, msg: JointTrajectory) -> None:
        try:
            with self._lock:
                preempted = self.controller.submit(None, msg.joint_names, points_from_msg(msg),
                                                   msg.header.stamp.to_sec())
                if preempted is not None:
                    old = self._handles.pop(preempted.goal_id, None)
                    if old is not None:
                        self._finish(old, preempted, canceled=True)
        except TrajectoryError as exc:
            rospy.logwarn("%s/command refused (%s): %s", self.controller.name, RESULT_NAMES.get(exc.code),
                          exc.message)
        except Exception as exc:
            rospy.logerr("%s/command: %s: %s", self.controller.name, type(exc).__name__, exc)

    def _on_query(self, req: Any) -> QueryTrajectoryStateResponse:
        try:
            sample = self.controller.query_state(req.time.to_sec())
        except TrajectoryError as exc:
            raise rospy.ServiceException(exc.message) from None
        return QueryTrajectoryStateResponse(name=list(self.controller.joints), position=list(sample.positions),
                                            velocity=list(sample.velocities),
                                            acceleration=list(sample.accelerations))

    def _snapshot(self) -> Optional[Tuple[Any, Any]]:
        cycle, actual = self.controller.last_cycle, self.controller.last_actual
        if cycle is None or actual is None:
            return None
        return cycle, actual

    def _fill(self, msg: Any, cycle: Any, actual: Any) -> Any:
        """Header, joint names, desired, actual and error (state and feedback share them)."""
        msg.header.stamp = rospy.Time.now()
        msg.joint_names = list(self.controller.joints)
        msg.desired = _point(cycle.desired.positions, cycle.desired.velocities, cycle.desired.accelerations)
        msg.actual = _point(actual.positions, actual.velocities)
        msg.error = _point(cycle.error_positions, cycle.error_velocities)
        return msg

    def _publish_state(self, _event: Any) -> None:
        snap = self._snapshot()
        if snap is None:
            return
        self.state_pub.publish(self._fill(JointTrajectoryControllerState(), *snap))

    def _publish_feedback(self, _event: Any) -> None:
        snap = self._snapshot()
        with self._lock:
            handles = list(self._handles.values())
        if snap is None or not handles:
            return
        fb = self._fill(FollowJointTrajectoryFeedback(), *snap)
        for handle in handles:
            try:
                handle.publish_feedback(fb)
            except Exception as exc:
                rospy.logdebug("feedback: %s", exc)


def attach(manager: Any, driver: Any, namespace_of: Callable[[str], str]) -> Dict[str, RosTrajectoryController]:
    """Give every JointTrajectoryController the manager loads its ROS interface.

    ``namespace_of(controller name)`` is the node's controller namespace
    resolver. Returns the live adapters by controller name.
    """
    adapters: Dict[str, RosTrajectoryController] = {}

    def guarded(fn: Callable[[Any], None]) -> Callable[[Any], None]:
        def call(controller: Any) -> None:
            if not isinstance(controller, JointTrajectoryController):
                return
            try:
                fn(controller)
            except Exception as exc:  # a ROS hiccup must not break the controller manager
                rospy.logerr("%s: %s: %s", controller.name, type(exc).__name__, exc)
        return call

    def loaded(controller: JointTrajectoryController) -> None:
        adapters[controller.name] = RosTrajectoryController(controller, driver, namespace_of(controller.name))

    def unloaded(controller: JointTrajectoryController) -> None:
        adapter = adapters.pop(controller.name, None)
        if adapter is not None:
            adapter.close()

    def started(controller: JointTrajectoryController) -> None:
        if controller.name in adapters:
            adapters[controller.name].started()

    def stopped(controller: JointTrajectoryController) -> None:
        if controller.name in adapters:
            adapters[controller.name].stopped()

    manager.on_loaded.append(guarded(loaded))
    manager.on_unloaded.append(guarded(unloaded))
    manager.on_started.append(guarded(started))
    manager.on_stopped.append(guarded(stopped))
    return adapters
