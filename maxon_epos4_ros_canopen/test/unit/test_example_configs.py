"""The package's launch files, YAML layers and URDFs fit together.

What a user runs (`roslaunch maxon_epos4_ros_canopen
maxon_epos4_canopen_motor_1dof_ppm.launch sim:=true`) loads these YAML files
into the node's namespace and spawns these controllers; a mismatch shows
only at run time on a robot, so it is checked here.
"""
from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Dict, List

import pytest

from maxon_epos4_ros_canopen import controllers as cm
from maxon_epos4_ros_canopen.config import load_config
from maxon_epos4_ros_canopen.config_reader import load_yaml_files

PKG = Path(__file__).resolve().parents[2]
LAUNCHES = ["maxon_epos4_canopen_motor_1dof_ppm.launch", "maxon_epos4_canopen_motor_1dof_ppm_hm.launch",
            "maxon_epos4_canopen_motor_2dof_pvm.launch"]


def resolver(package: str) -> str:
    assert package == "maxon_epos4_ros_canopen", package
    return str(PKG)


def subst(text: str) -> str:
    return text.replace("$(find maxon_epos4_ros_canopen)", str(PKG))


def launch_parts(name: str) -> Dict[str, object]:
    root = ET.parse(PKG / "launch" / name).getroot()
    node = next(n for n in root.iter("node") if n.get("type") == "canopen_motor_node")
    spawner = next(n for n in root.iter("node") if n.get("type") == "controller_manager")
    xacro_param = next(p for p in root.iter("param") if p.get("name") == "/maxon/robot_description")
    return {
        "args": {a.get("name"): a.get("default") for a in root.findall("arg")},
        "yaml": [subst(r.get("file")) for r in node.findall("rosparam")],
        "config_files_arg": subst(node.get("args")).split()[1:],
        "spawn": spawner.get("args").split(),
        "xacro": re.search(r"'([^']+)'", subst(xacro_param.get("command"))).group(1),
        "group_ns": next(g.get("ns") for g in root.iter("group") if g.get("ns")),
        "node_pkg": node.get("pkg"),
        "spawner_pkg": spawner.get("pkg"),
        "xacro_command": xacro_param.get("command"),
    }


@pytest.mark.parametrize("launch", LAUNCHES)
def test_launch_arguments_and_names(launch):
    parts = launch_parts(launch)
    assert parts["args"] == {"sim": "false", "device": "can0"}
    assert parts["group_ns"] == "/maxon"
    # ros_canopen's and ros_control's package names, as in maxon's original launch files
    assert parts["node_pkg"] == "canopen_motor_node"
    assert parts["spawner_pkg"] == "controller_manager"
    assert parts["xacro_command"].startswith("$(find xacro)/xacro ")
    assert parts["spawn"][0] == "spawn"
    # the error messages can name the files the launch file really loads
    assert parts["config_files_arg"] == parts["yaml"]
    for path in parts["yaml"]:
        assert Path(path).is_file(), path


@pytest.mark.parametrize("launch", LAUNCHES)
def test_layers_load_and_every_spawned_controller_loads(launch):
    parts = launch_parts(launch)
    params = load_yaml_files(parts["yaml"])
    config = load_config(params, launch, resolver)
    for node in config.nodes:
        assert Path(node.eds_file).is_file(), node.eds_file
    assert list(config.joint_names) == [n.name for n in config.nodes]

    class NoDriver:
        def switch_mode(self, joints, mode):
            raise AssertionError("not called by load")

        set_command = switch_mode

    prefix = "/maxon/canopen_motor/"
    manager = cm.ControllerManager(NoDriver(), list(config.joint_names),
                                   lambda name: params.get(name[len(prefix):] if name.startswith(prefix) else name))
    for name in parts["spawn"][1:]:
        assert name.startswith(prefix), name
        outcome = manager.load(name)
        assert outcome.success, outcome.message
    for controller in config.controllers:
        assert manager.load(controller.name).success or manager.get(prefix + controller.name)


def urdf_joints(path: str) -> List[str]:
    xacro = pytest.importorskip("xacro", reason="xacro (PyPI, in .venv) expands the URDF files")
    doc = xacro.process_file(path)
    return [j.getAttribute("name") for j in doc.getElementsByTagName("joint") if j.parentNode.tagName == "robot"]


@pytest.mark.parametrize("launch", LAUNCHES)
def test_urdf_joints_match_the_controllers(launch):
    parts = launch_parts(launch)
    config = load_config(load_yaml_files(parts["yaml"]), launch, resolver)
    assert urdf_joints(parts["xacro"]) == list(config.joint_names)


def test_homing_example_uses_a_dcf_with_a_homing_method():
    params = load_yaml_files(launch_parts("maxon_epos4_canopen_motor_1dof_ppm_hm.launch")["yaml"])
    config = load_config(params, "hm", resolver)
    text = Path(config.nodes[0].eds_file).read_text()
    section = text.split("[6098]", 1)[1].split("\n[", 1)[0]
    value = re.search(r"^ParameterValue=(.+)$", section, re.M).group(1).strip()
    assert int(value, 0) != 0, "0x6098 is 0 in the homing DCF: init would not home"


def test_virtual_epos4_that_cannot_open_its_device_does_not_end_the_launch():
    # sim:=true device:=vcan9: the simulator says which device it cannot open
    # and exits alone; the driver then answers driver/init with the reason.
    root = ET.parse(PKG / "launch" / "virtual_epos4.launch").getroot()
    node = next(n for n in root.iter("node") if n.get("type") == "virtual_epos4_node")
    assert node.get("required") in (None, "false")
