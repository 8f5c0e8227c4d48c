"""Controller manager semantics a ros_canopen / ros_control user relies on."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, List, Tuple

import pytest
import yaml

from maxon_epos4_ros_canopen import controllers as cm

# The seeds' controller.yaml for Profile Position Mode and Profile Velocity
# Mode, merged the way a user mixes them in one file.
SEED_PPM_PVM = """
joint_names: [base_link1_joint]

joint_state_controller:
    type: joint_state_controller/JointStateController
    publish_rate: 50

joint_group_position_controller:
  type: position_controllers/JointGroupPositionController
  joints:
    - base_link1_joint
  required_drive_mode: 1

base_link1_joint_position_controller:
  type: position_controllers/JointPositionController
  joint: base_link1_joint
  required_drive_mode: 1

joint_group_velocity_controller:
  type: velocity_controllers/JointGroupVelocityController
  joints:
     - base_link1_joint
  required_drive_mode: 3

base_link1_joint_velocity_controller:
  type: velocity_controllers/JointVelocityController
  joint: base_link1_joint
  required_drive_mode: 3
"""


@dataclass
class Result:
    success: bool
    message: str = ""


class FakeJoint:
    def __init__(self, driver: "FakeDriver", name: str) -> None:
        self.driver = driver
        self.name = name

    def set_command(self, kind, value):
        return self.driver.set_command(self.name, kind, value)


class FakeDriver:
    """Records what the manager asks of the driver."""

    def __init__(self, joints=("base_link1_joint",)) -> None:
        self.modes: List[Tuple[Tuple[str, ...], int]] = []
        self.commands: List[Tuple[str, str, float]] = []
        self.fail_modes: set = set()
        self.joints = {name: FakeJoint(self, name) for name in joints}

    def switch_mode(self, joint_names, mode):
        self.modes.append((tuple(joint_names), mode))
        if mode in self.fail_modes:
            return Result(False, "drive did not confirm mode %d in 0x6061" % mode)
        return Result(True)

    def set_command(self, joint_name, kind, value):
        self.commands.append((joint_name, kind, value))
        return Result(True)


def make_manager(text: str = SEED_PPM_PVM, joints=("base_link1_joint",)):
    params = yaml.safe_load(text)
    driver = FakeDriver(joints)
    manager = cm.ControllerManager(driver, list(joints), params.get)
    return manager, driver


def states(manager):
    return {c.name: c.state for c in manager.controllers()}


def test_seed_controllers_load_and_report_initialized():
    manager, _ = make_manager()
    for name in ("joint_state_controller", "base_link1_joint_position_controller",
                 "joint_group_position_controller"):
        assert manager.load(name).success
    assert states(manager) == {
        "joint_state_controller": "initialized",
        "base_link1_joint_position_controller": "initialized",
        "joint_group_position_controller": "initialized",
    }
    jsc = manager.get("joint_state_controller")
    assert jsc.publish_rate == 50.0
    pos = manager.get("base_link1_joint_position_controller")
    assert pos.claimed_resources()[0].hardware_interface == "hardware_interface::PositionJointInterface"
    assert pos.claimed_resources()[0].resources == ["base_link1_joint"]


def test_list_controller_types_names_every_seed_type():
    manager, _ = make_manager()
    types, bases = manager.list_controller_types()
    for t in ("joint_state_controller/JointStateController",
              "position_controllers/JointPositionController",
              "position_controllers/JointGroupPositionController",
              "velocity_controllers/JointVelocityController",
              "velocity_controllers/JointGroupVelocityController",
              "effort_controllers/JointEffortController",
              "effort_controllers/JointGroupEffortController"):
        assert t in types
    assert set(bases) == {"controller_interface::ControllerBase"}


@pytest.mark.parametrize("text,name,expected", [
    ("c: {joint: base_link1_joint}", "c", "missing required key 'type'"),
    ("c: {type: foo/Bar, joint: base_link1_joint}", "c", "unknown type 'foo/Bar'"),
    ("c: {type: position_controllers/JointPositionController}", "c", "missing required key 'joint'"),
    ("c: {type: position_controllers/JointPositionController, joint: elbow}", "c", "unknown joint(s) elbow"),
    ("c: {type: position_controllers/JointPositionController, joint: base_link1_joint,"
     " required_drive_mode: 3}", "c", "required_drive_mode 3 (profile_velocity) cannot serve a position"),
    ("c: {type: velocity_controllers/JointVelocityController, joint: base_link1_joint,"
     " required_drive_mode: '3'}", "c", "required_drive_mode must be an integer"),
    ("c: {type: position_controllers/JointGroupPositionController, joints: base_link1_joint}", "c",
     "joints must be a non-empty list"),
    ("c: {type: joint_state_controller/JointStateController, publish_rate: -5}", "c",
     "publish_rate must be a positive number"),
    ("c: {type: position_controllers/JointPositionController, joint: base_link1_joint}", "other",
     "no parameters found"),
])
def test_bad_controller_configuration_is_refused_with_the_key(text, name, expected):
    manager, _ = make_manager(text)
    outcome = manager.load(name)
    assert not outcome.success
    assert expected in outcome.message
    assert manager.controllers() == []


def test_load_twice_is_refused():
    manager, _ = make_manager()
    assert manager.load("joint_state_controller").success
    outcome = manager.load("joint_state_controller")
    assert not outcome.success and "already loaded" in outcome.message


def test_starting_a_controller_switches_its_joints_to_the_required_drive_mode():
    manager, driver = make_manager()
    manager.load("joint_state_controller")
    manager.load("base_link1_joint_position_controller")
    outcome = manager.switch(["joint_state_controller", "base_link1_joint_position_controller"], [], cm.STRICT)
    assert outcome.success, outcome.message
    assert driver.modes == [(("base_link1_joint",), 1)]
    assert states(manager) == {"joint_state_controller": "running",
                               "base_link1_joint_position_controller": "running"}


def test_switch_position_to_velocity_changes_mode_in_one_call():
    manager, driver = make_manager()
    for name in ("base_link1_joint_position_controller", "base_link1_joint_velocity_controller"):
        manager.load(name)
    assert manager.switch(["base_link1_joint_position_controller"], [], cm.STRICT).success
    outcome = manager.switch(["base_link1_joint_velocity_controller"],
                             ["base_link1_joint_position_controller"], cm.STRICT)
    assert outcome.success, outcome.message
    assert driver.modes[-1] == (("base_link1_joint",), 3)
    assert states(manager)["base_link1_joint_position_controller"] == "stopped"
    assert states(manager)["base_link1_joint_velocity_controller"] == "running"


def test_two_controllers_on_one_joint_is_a_resource_conflict_in_any_strictness():
    manager, driver = make_manager()
    manager.load("base_link1_joint_position_controller")
    manager.load("joint_group_position_controller")
    assert manager.switch(["base_link1_joint_position_controller"], []).success
    for strictness in (cm.BEST_EFFORT, cm.STRICT):
        outcome = manager.switch(["joint_group_position_controller"], [], strictness)
        assert not outcome.success
        assert "resource conflict: joint base_link1_joint" in outcome.message
    assert states(manager)["joint_group_position_controller"] == "initialized"
    assert len(driver.modes) == 1


def test_strict_refuses_unknown_names_and_changes_nothing():
    manager, driver = make_manager()
    manager.load("joint_state_controller")
    outcome = manager.switch(["joint_state_controller", "nonexistent"], [], cm.STRICT)
    assert not outcome.success and "cannot start nonexistent: not loaded" in outcome.message
    assert states(manager)["joint_state_controller"] == "initialized"
    outcome = manager.switch([], ["joint_state_controller"], cm.STRICT)
    assert not outcome.success and "not running" in outcome.message


def test_best_effort_starts_what_it_can():
    manager, _ = make_manager()
    manager.load("joint_state_controller")
    outcome = manager.switch(["nonexistent", "joint_state_controller"], ["also_missing"], cm.BEST_EFFORT)
    assert outcome.success
    assert "nonexistent" in outcome.message and "also_missing" in outcome.message
    assert states(manager)["joint_state_controller"] == "running"


def test_strictness_zero_falls_back_to_best_effort_like_ros_control():
    manager, _ = make_manager()
    manager.load("joint_state_controller")
    outcome = manager.switch(["joint_state_controller"], [], 0)
    assert outcome.success and "BEST_EFFORT" in outcome.message


def test_failed_mode_switch_leaves_controller_stopped():
    manager, driver = make_manager()
    driver.fail_modes.add(3)
    manager.load("base_link1_joint_velocity_controller")
    outcome = manager.switch(["base_link1_joint_velocity_controller"], [], cm.STRICT)
    assert not outcome.success
    assert "0x6061" in outcome.message
    assert not manager.get("base_link1_joint_velocity_controller").running
    best = manager.switch(["base_link1_joint_velocity_controller"], [], cm.BEST_EFFORT)
    assert not best.success  # nothing could start


def test_commands_reach_the_driver_only_while_running_and_finite():
    manager, driver = make_manager()
    manager.load("base_link1_joint_position_controller")
    ctrl = manager.get("base_link1_joint_position_controller")
    refused = ctrl.command(driver, [1000.0])
    assert not refused.success and "not running" in refused.message
    manager.switch(["base_link1_joint_position_controller"], [])
    assert ctrl.command(driver, [1000.0]).success
    assert driver.commands == [("base_link1_joint", "position", 1000.0)]
    for bad in (float("nan"), float("inf")):
        outcome = ctrl.command(driver, [bad])
        assert not outcome.success and "not a finite number" in outcome.message
    assert len(driver.commands) == 1


def test_group_command_needs_one_value_per_joint():
    text = """
grp:
  type: velocity_controllers/JointGroupVelocityController
  joints: [base_link1_joint, base_link2_joint]
  required_drive_mode: 3
"""
    manager, driver = make_manager(text, joints=("base_link1_joint", "base_link2_joint"))
    assert manager.load("grp").success
    assert manager.switch(["grp"], [], cm.STRICT).success
    assert driver.modes == [(("base_link1_joint", "base_link2_joint"), 3)]
    grp = manager.get("grp")
    outcome = grp.command(driver, [1.0])
    assert not outcome.success and "1 values for 2 joints" in outcome.message
    assert grp.command(driver, [100.0, -200.0]).success
    assert driver.commands == [("base_link1_joint", "velocity", 100.0), ("base_link2_joint", "velocity", -200.0)]


def test_driver_refusal_is_reported():
    manager, driver = make_manager()
    driver.set_command = lambda j, k, v: Result(False, "drive is halted")
    manager.load("base_link1_joint_position_controller")
    manager.switch(["base_link1_joint_position_controller"], [])
    outcome = manager.get("base_link1_joint_position_controller").command(driver, [5.0])
    assert not outcome.success and "base_link1_joint: drive is halted" in outcome.message


def test_unload_requires_stop_and_reload_requires_force_kill():
    manager, _ = make_manager()
    manager.load("joint_state_controller")
    manager.switch(["joint_state_controller"], [])
    outcome = manager.unload("joint_state_controller")
    assert not outcome.success and "stop it before unloading" in outcome.message
    assert not manager.reload_libraries(False).success
    assert manager.reload_libraries(True).success
    assert manager.controllers() == []
    assert not manager.unload("joint_state_controller").success


def test_listeners_follow_the_lifecycle():
    manager, _ = make_manager()
    events = []
    manager.on_loaded.append(lambda c: events.append(("loaded", c.name)))
    manager.on_started.append(lambda c: events.append(("started", c.name)))
    manager.on_stopped.append(lambda c: events.append(("stopped", c.name)))
    manager.on_unloaded.append(lambda c: events.append(("unloaded", c.name)))
    manager.load("joint_state_controller")
    manager.switch(["joint_state_controller"], [])
    manager.switch([], ["joint_state_controller"])
    manager.unload("joint_state_controller")
    assert events == [("loaded", "joint_state_controller"), ("started", "joint_state_controller"),
                      ("stopped", "joint_state_controller"), ("unloaded", "joint_state_controller")]


def test_new_controller_types_plug_into_the_registry():
    class Trajectory(cm.Controller):
        interface = "position"
        claims_joints = True

    def factory(name: str, params: Any, manager: cm.ControllerManager) -> cm.Controller:
        joints = cm.parse_joints(name, params, manager.joint_names, group=True)
        return Trajectory(name, params, joints, cm.parse_drive_mode(name, params, "position"))

    type_name = "test_controllers/TrajectoryForTest"
    cm.register_controller_type(type_name, factory)
    try:
        text = "traj: {type: %s, joints: [base_link1_joint], required_drive_mode: 8}" % type_name
        manager, driver = make_manager(text)
        assert manager.load("traj").success
        assert type_name in manager.list_controller_types()[0]
        assert manager.switch(["traj"], [], cm.STRICT).success
        assert driver.modes == [(("base_link1_joint",), 8)]
    finally:
        cm._REGISTRY.pop(type_name, None)
