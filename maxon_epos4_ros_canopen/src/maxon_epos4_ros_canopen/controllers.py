"""Controller manager logic with ros_control's semantics, free of ROS.

ros_control and its controllers are not packaged for Debian 12, and the
canopen_motor_node only ever used a handful of forward-command controllers, so
this module re-creates what a ros_canopen user relies on: the controller types
named in the seeds' controller.yaml files, load/unload/switch with ros_control's
rules (strictness, resource conflicts, state names as list_controllers reports
them) and ros_canopen's `required_drive_mode`, which switches each joint's drive
to a CiA 402 mode of operation when its controller starts.

The ROS node owns topics and timers; it learns about lifecycle changes through
the manager's listener callbacks. Further controller types (the CSP joint
trajectory controller) plug in with `register_controller_type`.
"""
from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, Iterable, List, Mapping, Optional, Protocol, Sequence, Tuple

from .cia402 import OperationMode, mode_name
from .result import Result, fail, ok

BEST_EFFORT = 1
STRICT = 2

# States as ROS Noetic's controller_manager reports them.
INITIALIZED = "initialized"
RUNNING = "running"
STOPPED = "stopped"

BASE_CLASS = "controller_interface::ControllerBase"

# Which modes can serve a command interface, first = default when a controller
# gives no required_drive_mode (ros_canopen picks the first supported one).
MODES_FOR_INTERFACE = {
    "position": (OperationMode.PROFILE_POSITION, OperationMode.CYCLIC_SYNC_POSITION),
    "velocity": (OperationMode.PROFILE_VELOCITY, OperationMode.CYCLIC_SYNC_VELOCITY),
    "effort": (OperationMode.CYCLIC_SYNC_TORQUE,),
}
HARDWARE_INTERFACES = {
    "position": "hardware_interface::PositionJointInterface",
    "velocity": "hardware_interface::VelocityJointInterface",
    "effort": "hardware_interface::EffortJointInterface",
    "state": "hardware_interface::JointStateInterface",
}


class ControllerError(Exception):
    """A controller configuration or request that cannot be served."""


class Backend(Protocol):
    """What the manager needs from the driver (driver.Driver satisfies it):
    `set_command(joint, kind, value)` (thread-safe: it posts the command to
    the driver's cycle) and `switch_mode(names, mode)`, both answering with a
    Result."""

    joints: Mapping[str, Any]

    def set_command(self, joint_name: str, kind: str, value: float) -> Result:
        """Command a joint (ROS units)."""

    def switch_mode(self, joint_names: Sequence[str], mode: int) -> Result:
        """Switch the joints' drives to `mode`."""


@dataclass
class ClaimedResources:
    hardware_interface: str
    resources: List[str] = field(default_factory=list)


class Controller:
    """Base of every controller type: name, joints, state, drive mode."""

    type_name = ""
    interface = "state"  # key of HARDWARE_INTERFACES
    claims_joints = False  # whether starting it claims its joints exclusively

    def __init__(self, name: str, params: Mapping[str, Any], joints: Sequence[str],
                 required_drive_mode: Optional[int]) -> None:
        self.name = name
        self.params = dict(params)
        self.joints = list(joints)
        self.required_drive_mode = required_drive_mode
        self.state = INITIALIZED

    @property
    def running(self) -> bool:
        return self.state == RUNNING

    def claimed_resources(self) -> List[ClaimedResources]:
        resources = list(self.joints) if self.claims_joints else []
        return [ClaimedResources(HARDWARE_INTERFACES[self.interface], resources)]

    def starting(self, backend: Backend) -> Result:
        """Called after the drive modes are switched; override to prepare."""
        return ok()

    def stopping(self, backend: Backend) -> None:
        """Called when the controller stops."""


class JointStateController(Controller):
    """Publishes every joint's position, velocity and effort at publish_rate."""

    type_name = "joint_state_controller/JointStateController"
    interface = "state"

    def __init__(self, name: str, params: Mapping[str, Any], joints: Sequence[str],
                 required_drive_mode: Optional[int]) -> None:
        super().__init__(name, params, joints, required_drive_mode)
        rate = params.get("publish_rate", 50.0)
        if isinstance(rate, bool) or not isinstance(rate, (int, float)) or not math.isfinite(rate) \
                or rate <= 0:
            raise ControllerError("%s/publish_rate must be a positive number, got %r" % (name, rate))
        self.publish_rate = float(rate)


class ForwardCommandController(Controller):
    """position/velocity/effort controllers: forward a command to the drives.

    `command(values)` is what the node's command subscriber calls; a single
    joint controller takes one value, a group controller one per joint.
    """

    claims_joints = True
    group = False

    def command(self, backend: Backend, values: Sequence[float]) -> Result:
        if not self.running:
            return fail("controller %s is not running: command ignored" % self.name)
        if len(values) != len(self.joints):
            return fail("controller %s: command has %d values for %d joints: not executed"
                           % (self.name, len(values), len(self.joints)))
        for value in values:
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                return fail("controller %s: command %r is not a finite number: not executed"
                               % (self.name, value))
        messages = []
        success = True
        for joint, value in zip(self.joints, values):
            result = backend.set_command(joint, self.interface, float(value))
            if not result.success:
                success = False
            if result.message:
                messages.append("%s: %s" % (joint, result.message))
        return Result(success, "; ".join(messages))


def _command_type(package: str, class_name: str, interface: str, group: bool) -> type:
    return type(class_name, (ForwardCommandController,), {
        "type_name": "%s/%s" % (package, class_name),
        "interface": interface,
        "group": group,
    })


# A factory builds a loaded controller from its name, parameters and context.
Factory = Callable[[str, Mapping[str, Any], "ControllerManager"], Controller]


@dataclass
class _TypeEntry:
    factory: Factory
    base_class: str


_REGISTRY: Dict[str, _TypeEntry] = {}


def register_controller_type(type_name: str, factory: Factory, base_class: str = BASE_CLASS) -> None:
    """Make `type_name` loadable (e.g. position_controllers/JointTrajectoryController)."""
    _REGISTRY[type_name] = _TypeEntry(factory, base_class)


def controller_types() -> List[Tuple[str, str]]:
    """(type, base class) of every registered type, sorted by type."""
    return sorted((name, entry.base_class) for name, entry in _REGISTRY.items())


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def parse_joints(name: str, params: Mapping[str, Any], known_joints: Sequence[str],
                 group: bool) -> List[str]:
    """Joints of a controller from `joint` (single) or `joints` (group)."""
    key = "joints" if group else "joint"
    if key not in params:
        raise ControllerError("%s: missing required key '%s'" % (name, key))
    raw = params[key]
    if group:
        if not isinstance(raw, (list, tuple)) or not raw or not all(isinstance(j, str) for j in raw):
            raise ControllerError("%s/joints must be a non-empty list of joint names, got %r" % (name, raw))
        joints = list(raw)
        if len(set(joints)) != len(joints):
            raise ControllerError("%s/joints lists a joint twice: %r" % (name, joints))
    else:
        if not isinstance(raw, str) or not raw:
            raise ControllerError("%s/joint must be a joint name, got %r" % (name, raw))
        joints = [raw]
    unknown = [j for j in joints if j not in known_joints]
    if unknown:
        raise ControllerError("%s: unknown joint(s) %s; the driver has %s"
                              % (name, ", ".join(unknown), ", ".join(known_joints) or "no joints"))
    return joints


def parse_drive_mode(name: str, params: Mapping[str, Any], interface: str) -> int:
    """required_drive_mode checked against the modes that serve `interface`."""
    allowed = MODES_FOR_INTERFACE[interface]
    if "required_drive_mode" not in params:
        return int(allowed[0])
    mode = params["required_drive_mode"]
    if not _is_int(mode):
        raise ControllerError("%s/required_drive_mode must be an integer, got %r" % (name, mode))
    if mode not in allowed:
        raise ControllerError(
            "%s/required_drive_mode %d (%s) cannot serve a %s command; use one of %s"
            % (name, mode, mode_name(mode), interface,
               ", ".join("%d (%s)" % (m, mode_name(m)) for m in allowed)))
    return mode


def _joint_state_factory(name: str, params: Mapping[str, Any], manager: "ControllerManager") -> Controller:
    return JointStateController(name, params, manager.joint_names, None)


def _command_factory(cls: type) -> Factory:
    def factory(name: str, params: Mapping[str, Any], manager: "ControllerManager") -> Controller:
        joints = parse_joints(name, params, manager.joint_names, cls.group)
        mode = parse_drive_mode(name, params, cls.interface)
        return cls(name, params, joints, mode)
    return factory


register_controller_type(JointStateController.type_name, _joint_state_factory)
for _interface in ("position", "velocity", "effort"):
    _package = "%s_controllers" % _interface
    _title = _interface.capitalize()
    for _group, _class_name in ((False, "Joint%sController" % _title),
                                (True, "JointGroup%sController" % _title)):
        register_controller_type("%s/%s" % (_package, _class_name),
                                 _command_factory(_command_type(_package, _class_name, _interface, _group)))


Listener = Callable[[Controller], None]


class ControllerManager:
    """Loads, starts, stops and unloads controllers for the driver's joints.

    `lookup(name)` returns the controller's parameter dict (what sits under
    `<node namespace>/<name>` on the parameter server) or None.
    """

    def __init__(self, backend: Backend, joint_names: Sequence[str],
                 lookup: Callable[[str], Optional[Mapping[str, Any]]]) -> None:
        self.backend = backend
        self.joint_names = list(joint_names)
        self._lookup = lookup
        self._controllers: Dict[str, Controller] = {}
        self._lock = threading.RLock()
        self.on_loaded: List[Listener] = []
        self.on_unloaded: List[Listener] = []
        self.on_started: List[Listener] = []
        self.on_stopped: List[Listener] = []

    # --- queries -------------------------------------------------------
    def get(self, name: str) -> Optional[Controller]:
        return self._controllers.get(name)

    def controllers(self) -> List[Controller]:
        with self._lock:
            return list(self._controllers.values())

    def list_controller_types(self) -> Tuple[List[str], List[str]]:
        pairs = controller_types()
        return [t for t, _ in pairs], [b for _, b in pairs]

    # --- lifecycle ------------------------------------------------------
    def load(self, name: str) -> Result:
        with self._lock:
            if not isinstance(name, str) or not name.strip("/"):
                return fail("load_controller: empty controller name")
            if name in self._controllers:
                return fail("controller %s is already loaded" % name)
            params = self._lookup(name)
            if not isinstance(params, Mapping):
                return fail("controller %s: no parameters found for it (is its YAML loaded?)" % name)
            type_name = params.get("type")
            if not isinstance(type_name, str) or not type_name:
                return fail("controller %s: missing required key 'type'" % name)
            entry = _REGISTRY.get(type_name)
            if entry is None:
                return fail("controller %s: unknown type '%s'; known types: %s"
                               % (name, type_name, ", ".join(t for t, _ in controller_types())))
            try:
                controller = entry.factory(name, params, self)
            except ControllerError as exc:
                return fail(str(exc))
            controller.type_name = type_name
            self._controllers[name] = controller
        self._notify(self.on_loaded, controller)
        return ok("loaded %s (%s)" % (name, type_name))

    def unload(self, name: str) -> Result:
        with self._lock:
            controller = self._controllers.get(name)
            if controller is None:
                return fail("controller %s is not loaded" % name)
            if controller.running:
                return fail("controller %s is running: stop it before unloading" % name)
            del self._controllers[name]
        self._notify(self.on_unloaded, controller)
        return ok("unloaded %s" % name)

    def reload_libraries(self, force_kill: bool) -> Result:
        """Controller types are Python classes: nothing to reload, but honour
        ros_control's rule that no controller may be loaded unless force_kill."""
        with self._lock:
            loaded = list(self._controllers)
        if loaded and not force_kill:
            return fail("controllers still loaded (%s): call with force_kill to stop "
                                  "and unload them" % ", ".join(loaded))
        if loaded:
            self.switch([], [n for n in loaded if self._controllers[n].running], BEST_EFFORT)
            for name in loaded:
                self.unload(name)
        return ok("controller libraries reloaded")

    def switch(self, start: Iterable[str], stop: Iterable[str], strictness: int = BEST_EFFORT,
               start_asap: bool = False, timeout: float = 0.0) -> Result:
        """Stop `stop`, then start `start`, with ros_control's strictness rules.

        Starting switches each joint's drive to the controller's
        required_drive_mode; a joint whose mode switch fails keeps its
        controller stopped. start_asap/timeout are accepted for wire
        compatibility: resources are available at once here.
        """
        start = list(start)
        stop = list(stop)
        notes: List[str] = []
        if strictness not in (BEST_EFFORT, STRICT):
            notes.append("strictness %r is neither BEST_EFFORT (1) nor STRICT (2): using BEST_EFFORT"
                         % (strictness,))
            strictness = BEST_EFFORT
        strict = strictness == STRICT
        with self._lock:
            to_stop, refused = self._select(stop, "stop", lambda c: "" if c.running else "not running",
                                            strict, notes)
            if refused:
                return fail(refused)
            to_start, refused = self._select(
                start, "start", lambda c: "already running" if c.running and c not in to_stop else "",
                strict, notes)
            if refused:
                return fail(refused)
            conflict = self._conflict(to_start, to_stop)
            if conflict:
                return fail(conflict)

            for controller in to_stop:
                self._stop(controller)
            started_all = True
            for controller in to_start:
                outcome = self._start(controller)
                if not outcome.success:
                    started_all = False
                    notes.append(outcome.message)
                    if strict:
                        return fail("; ".join(notes))
            success = started_all or not strict
            if to_start and not any(c.running for c in to_start):
                success = False
        return Result(success, "; ".join(notes))

    def stop_all(self) -> None:
        """Stop every running controller (driver shutdown, node exit)."""
        with self._lock:
            for controller in list(self._controllers.values()):
                if controller.running:
                    self._stop(controller)

    # --- internals ------------------------------------------------------
    def _select(self, names: Sequence[str], verb: str, unusable: Callable[[Controller], str], strict: bool,
                notes: List[str]) -> Tuple[List[Controller], str]:
        """The loaded controllers among `names` that `unusable` finds no
        reason against; with strict, the first problem is returned instead."""
        chosen: List[Controller] = []
        for name in names:
            controller = self._controllers.get(name)
            problem = "not loaded" if controller is None else unusable(controller)
            if problem:
                message = "cannot %s %s: %s" % (verb, name, problem)
                if strict:
                    return [], message
                notes.append(message)
            elif controller not in chosen:
                chosen.append(controller)
        return chosen, ""

    def _conflict(self, to_start: Sequence[Controller], to_stop: Sequence[Controller]) -> str:
        """A joint may be claimed by one running controller only."""
        owners: Dict[str, str] = {}
        after = [c for c in self._controllers.values() if c.running and c not in to_stop]
        after += [c for c in to_start if c not in after]
        for controller in after:
            if not controller.claims_joints:
                continue
            for joint in controller.joints:
                if joint in owners:
                    return ("resource conflict: joint %s would be claimed by both %s and %s; "
                            "stop one of them in the same switch" % (joint, owners[joint], controller.name))
                owners[joint] = controller.name
        return ""

    def _start(self, controller: Controller) -> Result:
        if controller.required_drive_mode is not None and controller.joints:
            result = self.backend.switch_mode(controller.joints, controller.required_drive_mode)
            if not result.success:
                return fail("cannot start %s: switching %s to mode %d failed: %s"
                            % (controller.name, ", ".join(controller.joints), controller.required_drive_mode,
                               result.message or "no reason given"))
        outcome = controller.starting(self.backend)
        if not outcome.success:
            return fail("cannot start %s: %s" % (controller.name, outcome.message))
        controller.state = RUNNING
        self._notify(self.on_started, controller)
        return ok()

    def _stop(self, controller: Controller) -> None:
        controller.stopping(self.backend)
        controller.state = STOPPED
        self._notify(self.on_stopped, controller)

    @staticmethod
    def _notify(listeners: Sequence[Listener], controller: Controller) -> None:
        for listener in listeners:
            listener(controller)
