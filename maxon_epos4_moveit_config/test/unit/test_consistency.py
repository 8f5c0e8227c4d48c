"""MoveIt configuration, URDF and driver configuration name the same things.

A joint or controller name that differs in one file makes MoveIt refuse to
plan or execute ("no controller for joint ..."), only visible on a machine
with MoveIt; these checks catch it here.
"""
from __future__ import annotations

import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[3]
MOVEIT = REPO / "maxon_epos4_moveit_config"
DRIVER = REPO / "maxon_epos4_ros_canopen"
XACRO_FILE = DRIVER / "urdf" / "maxon_epos4_2dof_csp.xacro"
NODE_NS = "/maxon/canopen_motor"  # namespace of the driver node in the CSP launch file


def _xacro_command():
    for candidate in (Path(sys.executable).parent / "xacro", REPO / ".venv" / "bin" / "xacro"):
        if candidate.exists():
            return str(candidate)
    return shutil.which("xacro")


@pytest.fixture(scope="module")
def urdf():
    xacro = _xacro_command()
    if xacro is None:
        pytest.fail("the xacro command is not installed: run tools/setup.sh (xacro is in requirements.txt)")
    out = subprocess.run([xacro, str(XACRO_FILE)], check=True, capture_output=True, text=True).stdout
    return ET.fromstring(out)


@pytest.fixture(scope="module")
def srdf():
    return ET.parse(MOVEIT / "config" / "maxon_epos4.srdf").getroot()


def _yaml(path: Path):
    with open(path) as f:
        return yaml.safe_load(f)


def urdf_joints(urdf):
    return {j.get("name"): j for j in urdf.findall("joint")}


def test_srdf_names_only_urdf_joints_and_links(urdf, srdf):
    joints = urdf_joints(urdf)
    links = {link.get("name") for link in urdf.findall("link")}
    assert srdf.get("name") == urdf.get("name")
    named = [j.get("name") for j in srdf.iter("joint")]
    assert named and set(named) <= set(joints), set(named) - set(joints)
    pairs = [(d.get("link1"), d.get("link2")) for d in srdf.findall("disable_collisions")]
    assert all(a in links and b in links for a, b in pairs)


def test_srdf_group_and_states(srdf, urdf):
    groups = {g.get("name"): [j.get("name") for j in g.findall("joint")] for g in srdf.findall("group")}
    assert list(groups) == ["maxon"]
    states = {s.get("name"): {j.get("name"): float(j.get("value")) for j in s.findall("joint")}
              for s in srdf.findall("group_state") if s.get("group") == "maxon"}
    assert states["start"] == {"base_link1_joint": 0.0, "link1_link2_joint": 0.0}
    assert states["pose1"] == {"base_link1_joint": 0.5, "link1_link2_joint": -0.5}
    joints = urdf_joints(urdf)
    for values in states.values():
        assert set(values) == set(groups["maxon"])
        for name, value in values.items():
            limit = joints[name].find("limit")
            assert float(limit.get("lower")) <= value <= float(limit.get("upper"))


def test_joint_limits_cover_urdf_joints_within_urdf_velocity(urdf):
    limits = _yaml(MOVEIT / "config" / "joint_limits.yaml")["joint_limits"]
    joints = urdf_joints(urdf)
    assert set(limits) <= set(joints), set(limits) - set(joints)
    for name, entry in limits.items():
        assert entry["has_velocity_limits"] and entry["has_acceleration_limits"]
        assert 0 < entry["max_velocity"] <= float(joints[name].find("limit").get("velocity"))
        assert entry["max_acceleration"] > 0


def test_kinematics_group_exists(srdf):
    kin = _yaml(MOVEIT / "config" / "kinematics.yaml")
    groups = {g.get("name") for g in srdf.findall("group")}
    assert set(kin) <= groups


def test_ompl_group_exists(srdf):
    ompl = _yaml(MOVEIT / "config" / "ompl_planning.yaml")
    groups = {g.get("name") for g in srdf.findall("group")}
    for group in groups:
        assert ompl[group]["default_planner_config"] in ompl[group]["planner_configs"]
        assert set(ompl[group]["planner_configs"]) <= set(ompl["planner_configs"])


def test_moveit_controllers_match_the_driver(urdf):
    moveit = _yaml(MOVEIT / "config" / "ros_controllers.yaml")["controller_list"]
    driver = _yaml(DRIVER / "config" / "controller_2dof_csp.yaml")
    joints = urdf_joints(urdf)
    assert len(moveit) == 1
    entry = moveit[0]
    assert entry["type"] == "FollowJointTrajectory"
    assert entry["action_ns"] == "follow_joint_trajectory"
    assert entry["name"].startswith(NODE_NS + "/")
    controller = entry["name"][len(NODE_NS) + 1:]
    assert driver[controller]["type"] == "position_controllers/JointTrajectoryController"
    assert driver[controller]["required_drive_mode"] == 8
    assert entry["joints"] == driver[controller]["joints"]
    assert set(entry["joints"]) <= set(joints)
    assert set(driver["joint_names"]) <= set(joints)
    for name, value in driver[controller]["constraints"].items():
        if isinstance(value, dict):
            assert name in entry["joints"]


def test_driver_launch_uses_the_same_namespace_and_controller():
    launch = ET.parse(DRIVER / "launch" / "maxon_epos4_canopen_motor_2dof_csp.launch").getroot()
    groups = [g for g in launch.iter("group") if g.get("ns")]
    assert groups and groups[0].get("ns").strip("/") == NODE_NS.strip("/").split("/")[0]
    nodes = [n.get("name") for n in launch.iter("node")]
    assert NODE_NS.split("/")[-1] in nodes
    spawner_args = " ".join(n.get("args", "") for n in launch.iter("node"))
    assert NODE_NS + "/joint_trajectory_controller" in spawner_args


def test_moveit_remaps_joint_states_to_the_driver():
    move_group = ET.parse(MOVEIT / "launch" / "move_group.launch").getroot()
    default = {a.get("name"): a.get("default") for a in move_group.findall("arg")}["joint_states"]
    assert default == "/" + NODE_NS.strip("/").split("/")[0] + "/joint_states"
