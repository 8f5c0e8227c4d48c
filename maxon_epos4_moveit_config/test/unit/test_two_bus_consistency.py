"""The two-bus example names the same things everywhere: the URDF built with
joints:=4, the two drivers' layers in launch/maxon_epos4_two_bus.launch, and
MoveIt's controller list naming both trajectory controllers."""
from __future__ import annotations

import subprocess
import xml.etree.ElementTree as ET

import yaml

from maxon_epos4_ros_canopen.config import load_config
from maxon_epos4_ros_canopen.config_reader import load_yaml_files
from test_consistency import DRIVER, MOVEIT, XACRO_FILE, _xacro_command

LAUNCH = DRIVER / "launch" / "maxon_epos4_two_bus.launch"


def _layers(group: ET.Element):
    node = next(n for n in group.iter("node") if n.get("name") == "canopen_motor")
    files = [r.get("file").replace("$(arg pkg)", str(DRIVER)) for r in node.iter("rosparam")]
    params = load_yaml_files(files)
    return node, files, load_config(params, "two_bus", lambda pkg: str(DRIVER))


def test_one_urdf_two_buses_four_joints_one_controller_list():
    urdf = ET.fromstring(subprocess.run([_xacro_command(), str(XACRO_FILE), "joints:=4"], check=True,
                                        capture_output=True, text=True).stdout)
    joints = [j.get("name") for j in urdf.findall("joint")]
    assert len(joints) == 4
    launch = ET.parse(LAUNCH).getroot()
    description = next(p for p in launch.iter("param") if p.get("name") == "/maxon/robot_description")
    assert "joints:=4" in description.get("command")
    groups = {g.get("ns"): g for g in launch.findall("group")}
    moveit = {c["name"]: c for c in yaml.safe_load((MOVEIT / "config" / "ros_controllers_two_bus.yaml").read_text())
              ["controller_list"]}
    assert len(moveit) == 2
    on_buses = []
    node_ids = []
    for ns, device in (("/maxon/bus_a", "$(arg device_a)"), ("/maxon/bus_b", "$(arg device_b)")):
        node, _, cfg = _layers(groups[ns])
        assert [p.get("value") for p in node.iter("param") if p.get("name") == "bus/device"] == [device]
        ctrl = cfg.controller("joint_trajectory_controller")
        entry = moveit[ns + "/canopen_motor/joint_trajectory_controller"]
        assert list(entry["joints"]) == list(ctrl.joints) == [n.name for n in cfg.nodes]
        assert ctrl.required_drive_mode == 8 and not cfg.warnings
        on_buses += list(ctrl.joints)
        node_ids += [n.node_id for n in cfg.nodes]
        spawner = next(n for n in groups[ns].iter("node") if n.get("name") == "controller_spawner")
        assert ns + "/canopen_motor/joint_trajectory_controller" in spawner.get("args")
    assert on_buses == joints and node_ids == [1, 2, 3, 4]
    # one /maxon/joint_states from both drivers' topics
    jsp = next(n for n in launch.iter("node") if n.get("pkg") == "joint_state_publisher")
    assert yaml.safe_load(next(r.text for r in jsp.iter("rosparam") if r.get("param") == "source_list")) == \
        ["bus_a/joint_states", "bus_b/joint_states"]
