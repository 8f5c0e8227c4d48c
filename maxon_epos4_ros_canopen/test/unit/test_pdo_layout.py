"""The compact PDO layout (node layer ``pdo_layout: compact``): what each
mode combination maps, in how many frames, never more than 8 bytes a
frame; and the DCF's mapping untouched without the option."""
import os

import can
import canopen
import pytest

from maxon_epos4_ros_canopen.config import ConfigError, load_config
from maxon_epos4_ros_canopen.driver.plan import (CONTROLWORD, MODES_DISPLAY, MODES_OF_OPERATION, POSITION_ACTUAL,
                                                 STATUSWORD, TARGET_POSITION, TARGET_TORQUE, TARGET_VELOCITY,
                                                 VELOCITY_ACTUAL, dcf_maps, plan_node)
from maxon_epos4_ros_canopen.objects import ObjectKey, load_dictionary
from maxon_epos4_ros_canopen.sim.runner import NodeConfig as SimNode
from maxon_epos4_ros_canopen.sim.runner import Simulator

HERE = os.path.dirname(os.path.abspath(__file__))
DCF1 = os.path.normpath(os.path.join(HERE, "..", "..", "config", "epos4_node1.dcf"))
CW, SW, POS, VEL = CONTROLWORD, STATUSWORD, POSITION_ACTUAL, VELOCITY_ACTUAL
TP, TV, TT = TARGET_POSITION, TARGET_VELOCITY, TARGET_TORQUE


def plan(node=None, top=None):
    node_params = {"id": 1, "eds_file": DCF1}
    node_params.update(node or {})
    params = {"sync": {"interval_ms": 10}, "nodes": {"n1": node_params}}
    params.update(top or {})
    cfg = load_config(params, "test")
    n = cfg.nodes[0]
    return plan_node(n, load_dictionary(n.eds_file, n.node_id), cfg.sync, "test")


def frames(maps):
    return [[k for k, _ in m.entries] for m in maps if m.enabled]


# modes -> (RxPDO contents, TxPDO contents) with position and velocity feedback
CASES = [
    ([8], [[CW, TP]], [[SW, POS], [VEL]]),
    ([9], [[CW, TV]], [[SW, POS], [VEL]]),
    ([10], [[CW, TT]], [[SW, POS], [VEL]]),
    ([1], [[CW, TP]], [[SW, POS], [VEL]]),
    ([3], [[CW, TV]], [[SW, POS], [VEL]]),
    ([6], [[CW]], [[SW, POS], [VEL]]),
    ([1, 3], [[CW, TP], [TV]], [[SW, POS], [VEL]]),
    ([3, 8], [[CW, TP], [TV]], [[SW, POS], [VEL]]),      # the cyclic target rides with the controlword
    ([1, 3, 6, 8, 9, 10], [[CW, TP, TT], [TV]], [[SW, POS], [VEL]]),
]


@pytest.mark.parametrize("modes,rx,tx", CASES, ids=[",".join(map(str, c[0])) for c in CASES])
def test_compact_layout_per_mode_combination(modes, rx, tx):
    p = plan({"pdo_layout": "compact", "modes": modes})
    assert p.source == "compact" and p.modes == tuple(modes)
    assert frames(p.rx) == rx
    assert frames(p.tx) == tx
    for m in p.rx + p.tx:
        assert sum(bits for _, bits in m.entries) <= 64
        assert m.enabled == bool(m.entries)
        assert m.trans_type == 1  # synchronous: RxPDOs act at the next SYNC, TxPDOs answer every SYNC
    # modes of operation travel by SDO, and the plan says so
    assert MODES_OF_OPERATION in p.sdo_rx() and MODES_DISPLAY in p.sdo_tx()
    assert set(p.sdo_rx()).isdisjoint(p.rx_keys())
    for mode in modes:
        assert p.supports(mode)


def test_csp_frame_counts_with_and_without_velocity_feedback():
    with_vel = plan({"pdo_layout": "compact", "modes": ["CSP"]})
    assert len(frames(with_vel.rx)) + len(frames(with_vel.tx)) == 3
    position_only = plan({"pdo_layout": "compact", "modes": ["CSP"], "vel_from_device": "0"})
    assert len(frames(position_only.rx)) + len(frames(position_only.tx)) == 2
    assert VELOCITY_ACTUAL in position_only.sdo_tx()
    assert not position_only.supports(3)  # PVM's target is not mapped


def test_compact_maps_what_the_conversions_read():
    # torque actual value (0x6077, 16 bit) for the effort: fits beside statusword and position
    p = plan({"pdo_layout": "compact", "modes": [10], "eff_from_device": "obj6077"})
    assert frames(p.tx) == [[SW, POS, ObjectKey(0x6077)], [VEL]]


def test_compact_cob_ids_are_the_predefined_connection_set():
    p = plan({"id": 1, "pdo_layout": "compact", "modes": [8]})
    assert [m.cob_id for m in p.rx] == [0x201, 0x301, 0x401, 0x501]
    assert [m.cob_id for m in p.tx] == [0x181, 0x281, 0x381, 0x481]
    assert [m.enabled for m in p.tx] == [True, True, False, False]


def test_modes_come_from_the_controllers_of_the_joint():
    top = {"joint_names": ["n1"],
           "traj": {"type": "position_controllers/JointTrajectoryController", "joints": ["n1"],
                    "required_drive_mode": 8},
           "vel": {"type": "velocity_controllers/JointVelocityController", "joint": "n1",
                   "required_drive_mode": 3},
           "other": {"type": "velocity_controllers/JointVelocityController", "joint": "elsewhere",
                     "required_drive_mode": 9}}
    p = plan({"pdo_layout": "compact"}, top)
    assert p.modes == (3, 8)
    assert frames(p.rx) == [[CW, TP], [TV]]
    # an explicit modes key wins over the controllers
    assert plan({"pdo_layout": "compact", "modes": [9]}, top).modes == (9,)


@pytest.mark.parametrize("node,key,text", [
    ({"pdo_layout": "compact"}, "nodes/n1/modes", "give modes"),
    ({"pdo_layout": "small"}, "nodes/n1/pdo_layout", "not a layout"),
    ({"modes": [2]}, "nodes/n1/modes[0]", "not a supported mode"),
    ({"modes": ["fast"]}, "nodes/n1/modes[0]", "not a supported mode"),
    ({"modes": {"a": 1}}, "nodes/n1/modes", "expected a list"),
])
def test_bad_layout_options_name_the_key(node, key, text):
    with pytest.raises(ConfigError) as e:
        plan(node)
    assert e.value.key == key and text in e.value.problem


def test_without_the_option_the_dcf_mapping_is_used_unchanged():
    p = plan({"modes": [8]})
    od = canopen.import_od(DCF1, 1)
    assert p.source == "dcf"
    for mine, theirs in ((p.rx, dcf_maps(od, True)), (p.tx, dcf_maps(od, False))):
        assert [(m.number, m.cob_id, m.enabled, m.entries) for m in mine] == \
            [(m.number, m.cob_id, m.enabled, m.entries) for m in theirs]
    assert p.sdo_rx() == [] and p.sdo_tx() == []
    assert plan().source == "dcf"


def test_compact_layout_on_the_wire():
    """Written to a virtual EPOS4 over SDO as the plan says, each SYNC brings
    exactly the planned TxPDOs, of the planned lengths."""
    channel = "pdo_layout_wire_%d" % os.getpid()
    sim_bus = can.Bus(interface="virtual", channel=channel)
    master = can.Bus(interface="virtual", channel=channel)
    sniffer = can.Bus(interface="virtual", channel=channel)
    sim = Simulator(sim_bus, [SimNode(1, DCF1)]).start()
    network = canopen.Network(master)
    network.connect()
    try:
        p = plan({"pdo_layout": "compact", "modes": [8]})
        node = canopen.RemoteNode(1, canopen.import_od(DCF1, 1))
        network.add_node(node)
        p.write_with_canopen(node)
        node.nmt.state = "OPERATIONAL"
        seen = {}

        def sync_and_collect():
            network.send_message(0x80, b"")
            for _ in range(50):
                msg = sniffer.recv(0.1)
                if msg is None:
                    break
                if 0x180 <= msg.arbitration_id < 0x500:
                    seen[msg.arbitration_id] = len(msg.data)
                if len(seen) >= 2:
                    break
        for _ in range(5):
            sync_and_collect()
            if len(seen) >= 2:
                break
        assert seen == {0x181: 6, 0x281: 4}
    finally:
        network.disconnect()
        sim.stop()
        for bus in (sim_bus, master, sniffer):
            bus.shutdown()
