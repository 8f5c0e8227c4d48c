"""The configuration layers: every seed YAML loads; mistakes name key and source."""
import os

import pytest

from maxon_epos4_ros_canopen.config import ConfigError, load_config, parse_cansend
from maxon_epos4_ros_canopen.config_reader import load_yaml_files, merge_params
from maxon_epos4_ros_canopen.objects import ObjectKey

FIXTURES = os.path.join(os.path.dirname(os.path.abspath(__file__)), "fixtures")
DCF_NAMES = [
    "epos4_node1.dcf",
    "epos4_50_15_can_ec90flat_gp52c_mile800_node1.dcf",
    "epos4_50_15_can_ec90flat_gp52c_mile800_node1_hm.dcf",
    "epos4_50_15_can_ec90flat_gp52c_mile800_node2.dcf",
]


def seed(*names):
    return [os.path.join(FIXTURES, n) for n in names]


@pytest.fixture
def pkgdir(tmp_path):
    """A package directory with the DCF names the node layers use (placeholders)."""
    (tmp_path / "config").mkdir()
    for n in DCF_NAMES:
        (tmp_path / "config" / n).write_text("")
    return tmp_path


@pytest.fixture
def resolver(pkgdir):
    calls = []

    def resolve(pkg):
        calls.append(pkg)
        if pkg in ("epos4_ros_canopen", "maxon_epos4_ros_canopen"):
            return str(pkgdir)
        raise LookupError("no package %s" % pkg)
    resolve.calls = calls
    return resolve


def load(files, resolver, **overrides):
    tree = load_yaml_files(seed(*files))
    tree = merge_params(tree, overrides)
    return load_config(tree, "test:" + "+".join(files), resolver)


# ---------------------------------------------------------------- seed 001

def test_tutorial_ppm_files_load_verbatim(resolver, pkgdir):
    cfg = load(["seed_001/can.yaml", "seed_001/controller_ppm.yaml", "seed_001/node.yaml"], resolver)
    assert cfg.bus.device == "can0"
    assert cfg.bus.master_allocator == "canopen::SimpleMaster::Allocator"
    assert cfg.sync.interval_ms == 10 and cfg.sync.update_ms == 10 and cfg.sync.overflow == 0
    assert cfg.heartbeat.rate == 20
    assert (cfg.heartbeat.can_id, cfg.heartbeat.data) == (0x77F, b"\x05")
    (node,) = cfg.nodes
    assert (node.key, node.node_id, node.name) == ("node1", 1, "base_link1_joint")
    assert node.eds_file == str(pkgdir / "config" / "epos4_node1.dcf")
    assert resolver.calls == ["epos4_ros_canopen"]
    assert node.switching_state == 2
    assert node.pos_to_device.text == "pos" and node.pos_from_device.text == "obj6064"
    assert node.vel_from_device.objects == (ObjectKey(0x606C),)
    assert node.eff_from_device.evaluate({}) == 0.0
    assert node.motor_allocator == "canopen::Motor402::Allocator"
    assert cfg.joint_names == ("base_link1_joint",)
    by_name = {c.name: c for c in cfg.controllers}
    assert set(by_name) == {"joint_state_controller", "joint_group_position_controller",
                            "base_link1_joint_position_controller"}
    assert by_name["joint_state_controller"].publish_rate == 50
    assert by_name["joint_group_position_controller"].group is True
    assert by_name["joint_group_position_controller"].joints == ("base_link1_joint",)
    assert by_name["base_link1_joint_position_controller"].required_drive_mode == 1
    assert by_name["base_link1_joint_position_controller"].type == "position_controllers/JointPositionController"
    assert cfg.warnings == ()


def test_tutorial_pvm_controllers(resolver):
    cfg = load(["seed_001/can.yaml", "seed_001/controller_pvm.yaml", "seed_001/node.yaml"], resolver)
    modes = {c.name: c.required_drive_mode for c in cfg.controllers}
    assert modes == {"joint_state_controller": None, "joint_group_velocity_controller": 3,
                     "base_link1_joint_velocity_controller": 3}


def test_tutorial_homing_overlay_merges_under_node(resolver):
    cfg = load(["seed_001/can.yaml", "seed_001/node.yaml", "seed_001/node_hm_overlay.yaml"], resolver)
    overlay = {k: v for k, v, _ in cfg.nodes[0].dcf_overlay}
    assert overlay[ObjectKey(0x6099, 1)] == "100"
    assert overlay[ObjectKey(0x6099, 2)] == "10"
    assert overlay[ObjectKey(0x30B2)] == "1500"
    assert len(overlay) == 8
    # The defaults of node.yaml survive the second file's defaults (deep merge).
    assert cfg.nodes[0].switching_state == 2


def test_tutorial_ros_layer_publish_and_placeholder_node(resolver):
    cfg = load(["seed_001/can.yaml", "seed_001/node.yaml", "seed_001/ros.yaml"], resolver)
    (node,) = cfg.nodes
    (pub,) = node.publish
    assert (pub.key, pub.force, pub.topic) == (ObjectKey(0x1A00), False, "base_link1_joint_1A00")
    assert any("nodes/node2 is empty" in w for w in cfg.warnings)


def test_publish_force_flag(resolver):
    cfg = load(["seed_001/can.yaml", "seed_001/node.yaml"], resolver,
               nodes={"node1": {"publish": ["1003sub0!", "6041"]}})
    specs = [(p.key, p.force, p.topic) for p in cfg.nodes[0].publish]
    assert specs == [(ObjectKey(0x1003, 0), True, "base_link1_joint_1003sub0"),
                     (ObjectKey(0x6041), False, "base_link1_joint_6041")]


# ---------------------------------------------------------------- seed 000

@pytest.mark.parametrize("files, joints", [
    (["canopen_bus_layer.yaml", "controller_1dof_ppm.yaml", "node_layer_1dof_ppm.yaml"], 1),
    (["canopen_bus_layer.yaml", "controller_1dof_ppm.yaml", "node_layer_1dof_ppm_hm.yaml", "ros_layer.yaml"], 1),
    (["canopen_bus_layer.yaml", "controller_2dof_pvm.yaml", "node_layer_2dof_pvm.yaml"], 2),
    (["canopen_bus_layer.yaml", "controller_2dof_csp.yaml", "node_layer_2dof_csp.yaml"], 2),
])
def test_application_note_layers_load(resolver, files, joints):
    cfg = load(["seed_000/" + f for f in files], resolver)
    assert len(cfg.nodes) == joints
    assert [n.node_id for n in cfg.nodes] == list(range(1, joints + 1))
    assert not [w for w in cfg.warnings if "unknown" in w]


def test_nodes_as_list_and_trajectory_controller(resolver):
    cfg = load(["seed_000/canopen_bus_layer.yaml", "seed_000/controller_2dof_csp.yaml",
                "seed_000/node_layer_2dof_csp.yaml"], resolver)
    assert [n.name for n in cfg.nodes] == ["base_link1_joint", "link1_link2_joint"]
    arm = cfg.controller("arm_controller")
    assert arm.required_drive_mode == 8 and arm.joints == ("base_link1_joint", "link1_link2_joint")
    assert arm.constraints["goal_time"] == 0.6
    assert arm.params["state_publish_rate"] == 25
    n = cfg.nodes[0]
    assert n.pos_to_device.evaluate({"pos": 3.141592653589793}) == 57600.0
    assert dict((k, v) for k, v, _ in n.dcf_overlay)[ObjectKey(0x60C2, 1)] == "10"


def test_node_value_overrides_default_and_overlays_merge(resolver):
    tree = {
        "bus": {"device": "vcan0"}, "sync": {"interval_ms": 10},
        "defaults": {"eds_pkg": "maxon_epos4_ros_canopen",
                     "eds_file": "config/epos4_50_15_can_ec90flat_gp52c_mile800_node1.dcf",
                     "switching_state": 5, "dcf_overlay": {"6098": "0", "1017": "100"}},
        "nodes": {"node1": {"id": 1, "switching_state": 3, "dcf_overlay": {"1017": "200"}},
                  "node2": {"id": 2}},
    }
    cfg = load_config(tree, "inline", resolver)
    n1, n2 = cfg.nodes
    assert n1.name == "node1"  # the key is the name when none is given
    assert n1.switching_state == 3 and n2.switching_state == 5
    assert dict((k, v) for k, v, _ in n1.dcf_overlay) == {ObjectKey(0x6098): "0", ObjectKey(0x1017): "200"}
    assert dict((k, v) for k, v, _ in n2.dcf_overlay) == {ObjectKey(0x6098): "0", ObjectKey(0x1017): "100"}


def test_absolute_eds_file_needs_no_package(pkgdir):
    path = str(pkgdir / "config" / "epos4_node1.dcf")
    cfg = load_config({"sync": {"interval_ms": 10}, "nodes": {"n": {"id": 3, "eds_file": path}}}, "inline")
    assert cfg.nodes[0].eds_file == path


def test_unknown_options_are_warnings(resolver):
    cfg = load(["seed_001/can.yaml", "seed_001/node.yaml"], resolver,
               bus={"device": "can0", "driver_plugin": "can::OtherInterface", "bitrate": 1000000},
               nodes={"node1": {"sync_monitor": True}}, use_realtime_scheduler=True)
    text = "\n".join(cfg.warnings)
    assert "bus/bitrate" in text
    assert "nodes/node1/sync_monitor" in text
    assert "use_realtime_scheduler" in text
    assert "can::OtherInterface" in text


def test_shutdown_deadline_key(resolver):
    """``timeouts/shutdown`` (s): the driver's own key, 5 s when absent;
    other keys under ``timeouts`` are warnings, as every unknown option."""
    cfg = load(["seed_001/can.yaml", "seed_001/node.yaml"], resolver)
    assert cfg.shutdown_timeout == 5.0 and not any("timeouts" in w for w in cfg.warnings)
    cfg = load(["seed_001/can.yaml", "seed_001/node.yaml"], resolver, timeouts={"shutdown": 2.5, "sdo": 1})
    assert cfg.shutdown_timeout == 2.5
    assert [w for w in cfg.warnings if "timeouts" in w] == ["test:seed_001/can.yaml+seed_001/node.yaml: "
                                                             "unknown option timeouts/sdo ignored"]


def test_heartbeat_and_sync_variants(resolver):
    cfg = load(["seed_001/node.yaml"], resolver, sync={"interval_ms": 0, "update_ms": 20})
    assert cfg.sync.interval_ms == 0 and cfg.sync.update_ms == 20 and cfg.heartbeat is None
    cfg = load(["seed_001/can.yaml", "seed_001/node.yaml"], resolver, sync={"overflow": 240})
    assert cfg.sync.overflow == 240
    assert parse_cansend("12345678#01.02") == (0x12345678, b"\x01\x02", True)


# ---------------------------------------------------------------- mistakes

def fails(resolver, match, files=("seed_001/can.yaml", "seed_001/node.yaml"), **overrides):
    with pytest.raises(ConfigError) as e:
        load(list(files), resolver, **overrides)
    msg = str(e.value)
    assert msg.startswith("test:"), msg  # the source is named
    assert match in msg, msg
    return msg


@pytest.mark.parametrize("overrides, key", [
    ({"nodes": {"node1": {"id": "one"}}}, "nodes/node1/id"),
    ({"nodes": {"node1": {"id": 128}}}, "nodes/node1/id"),
    ({"nodes": {"node1": {"name": ["x"]}}}, "nodes/node1/name"),
    ({"nodes": {"node1": {"switching_state": 7}}}, "nodes/node1/switching_state"),
    ({"nodes": {"node1": {"dcf_overlay": {"60ZZ": "1"}}}}, "nodes/node1/dcf_overlay/60ZZ"),
    ({"nodes": {"node1": {"dcf_overlay": {"6098": [1]}}}}, "nodes/node1/dcf_overlay/6098"),
    ({"nodes": {"node1": {"publish": ["6041x"]}}}, "nodes/node1/publish[0]"),
    ({"nodes": {"node1": {"eds_pkg": "no_such_pkg"}}}, "nodes/node1/eds_pkg"),
    ({"nodes": {"node1": {"eds_file": "config/missing.dcf"}}}, "nodes/node1/eds_file"),
    ({"nodes": {"node1": {"pos_to_device": "__import__('os').system('true')"}}}, "nodes/node1/pos_to_device"),
    ({"nodes": {"node1": {"vel_from_device": "obj606C.__class__"}}}, "nodes/node1/vel_from_device"),
    ({"bus": {"device": 0}}, "bus/device"),
    ({"bus": {"loopback": "yes"}}, "bus/loopback"),
    ({"sync": {"interval_ms": "ten"}}, "sync/interval_ms"),
    ({"sync": {"overflow": 1}}, "sync/overflow"),
    ({"sync": {"interval_ms": 0}}, "sync/update_ms"),
    ({"heartbeat": {"rate": 20, "msg": "hello"}}, "heartbeat/msg"),
    ({"heartbeat": {"msg": "77f#05", "rate": 20, "extra": 1}, "heartbeat_x": 1}, None),
    ({"heartbeat": {"rate": -1, "msg": "77f#05"}}, "heartbeat/rate"),
    # numbers no float holds, or no period the drive can take: ConfigError, not OverflowError
    ({"sync": {"interval_ms": 10 ** 400}}, "sync/interval_ms"),
    ({"sync": {"interval_ms": -10 ** 400}}, "sync/interval_ms"),
    ({"sync": {"interval_ms": 1e300}}, "sync/interval_ms"),
    ({"sync": {"interval_ms": float("inf")}}, "sync/interval_ms"),
    ({"sync": {"interval_ms": 10, "update_ms": 10 ** 400}}, "sync/update_ms"),
    ({"heartbeat": {"rate": 10 ** 400, "msg": "77f#05"}}, "heartbeat/rate"),
    ({"timeouts": {"shutdown": 0}}, "timeouts/shutdown"),
    ({"timeouts": {"shutdown": "5 s"}}, "timeouts/shutdown"),
    ({"timeouts": {"shutdown": float("inf")}}, "timeouts/shutdown"),
    ({"timeouts": 5}, "timeouts"),
])
def test_wrong_values_name_the_key(resolver, overrides, key):
    if key is None:  # unknown keys are not errors
        load(["seed_001/can.yaml", "seed_001/node.yaml"], resolver, **overrides)
        return
    fails(resolver, key + ":", **overrides)


def test_missing_required_keys(resolver, pkgdir):
    path = str(pkgdir / "config" / "epos4_node1.dcf")
    with pytest.raises(ConfigError, match="nodes/n/id: required"):
        load_config({"sync": {"interval_ms": 10}, "nodes": {"n": {"eds_file": path}}}, "f.yaml")
    with pytest.raises(ConfigError, match="nodes/n/eds_file: required"):
        load_config({"sync": {"interval_ms": 10}, "nodes": {"n": {"id": 1}}}, "f.yaml")
    with pytest.raises(ConfigError, match=r"nodes\[0\]/name: required"):
        load_config({"sync": {"interval_ms": 10}, "nodes": [{"id": 1, "eds_file": path}]}, "f.yaml")
    with pytest.raises(ConfigError, match="f.yaml: nodes: required"):
        load_config({"sync": {"interval_ms": 10}}, "f.yaml")
    with pytest.raises(ConfigError, match="nodes/b/id: node-ID 1 is also used by a"):
        load_config({"sync": {"interval_ms": 10}, "nodes": {"a": {"id": 1, "eds_file": path},
                                                             "b": {"id": 1, "eds_file": path}}}, "f.yaml")


def test_controller_mistakes(resolver):
    files = ("seed_001/can.yaml", "seed_001/node.yaml", "seed_001/controller_ppm.yaml")
    fails(resolver, "c/required_drive_mode: mode 4 is not supported", files,
          c={"type": "position_controllers/JointPositionController", "joint": "base_link1_joint",
             "required_drive_mode": 4})
    fails(resolver, "c/required_drive_mode: expected an integer", files,
          c={"type": "position_controllers/JointPositionController", "joint": "base_link1_joint",
             "required_drive_mode": "1"})
    fails(resolver, "c/joint: required", files, c={"type": "position_controllers/JointPositionController"})
    fails(resolver, "joint_state_controller/publish_rate", files,
          joint_state_controller={"publish_rate": "fast"})
    fails(resolver, "joint_names: expected a list", files, joint_names="base_link1_joint")


def test_yaml_with_wrong_type_from_file(tmp_path, resolver):
    bad = tmp_path / "bad.yaml"
    bad.write_text("nodes:\n  node1:\n    id: [1]\n")
    tree = load_yaml_files(seed("seed_001/can.yaml", "seed_001/node.yaml") + [str(bad)])
    with pytest.raises(ConfigError) as e:
        load_config(tree, str(bad), resolver)
    assert str(e.value).startswith(str(bad) + ": nodes/node1/id: expected an integer")
    notmap = tmp_path / "list.yaml"
    notmap.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="list.yaml"):
        load_yaml_files([str(notmap)])


# ------------------------------------------- the package's own configuration

PKG = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
PKG_CONFIG = os.path.join(PKG, "config")


def _shipped(name):
    return os.path.join(PKG_CONFIG, name)


@pytest.mark.parametrize("example", ["1dof_ppm", "1dof_ppm_hm", "2dof_pvm", "2dof_csp"])
def test_shipped_layers_load_and_plan_against_their_dcfs(example):
    """What the launch files load: bus, controller, node and ROS layers; the
    driver can plan init from the DCFs (overlay objects exist, values fit)."""
    from maxon_epos4_ros_canopen.driver import Driver
    controller = "controller_%s.yaml" % example.replace("_hm", "")
    files = ["canopen_bus_layer.yaml", controller, "node_layer_%s.yaml" % example, "ros_layer.yaml"]
    missing = [f for f in files if not os.path.isfile(_shipped(f))]
    if missing:
        pytest.fail("the package lacks %s" % missing)
    tree = load_yaml_files([_shipped(f) for f in files])
    cfg = load_config(tree, "config/" + example, lambda pkg: PKG)
    assert not [w for w in cfg.warnings if "unknown" in w], cfg.warnings
    driver = Driver(cfg)  # plans only; nothing is sent before init()
    assert list(driver.joints) == [n.name for n in cfg.nodes]
    for j in driver.joints.values():
        assert j.plan.writes
