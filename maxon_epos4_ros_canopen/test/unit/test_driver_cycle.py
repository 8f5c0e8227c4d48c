"""One joint's cycle without a bus: statuswords in (as TxPDO bytes), the
RxPDO frames the cycle sends out. Covers the CiA 402 transitions the driver
commands and the profile position handshake, frame by frame."""
import math
import os
import struct

import canopen
import pytest

from maxon_epos4_ros_canopen.cia402 import State
from maxon_epos4_ros_canopen.config import load_config
from maxon_epos4_ros_canopen.driver.joint import Joint
from maxon_epos4_ros_canopen.driver.plan import plan_node

DCF = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "config", "epos4_node1.dcf")

# Statuswords as the EPOS4 (and the virtual EPOS4) send them: remote (bit 9),
# target reached (bit 10), referenced (bit 15) besides the state bits.
SW_SWITCH_ON_DISABLED = 0x0240
SW_READY = 0x0221
SW_SWITCHED_ON = 0x0233
SW_ENABLED = 0x0637
SW_ENABLED_ACK = 0x1637        # profile position: set-point acknowledge
SW_FAULT = 0x0208
SW_QUICK_STOP = 0x0617


class Harness:
    def __init__(self, **node):
        params = {"sync": {"interval_ms": 10},
                  "nodes": {"n1": dict({"id": 1, "name": "j", "eds_file": DCF, "pos_to_device": "pos",
                                        "pos_from_device": "obj6064", "vel_to_device": "vel",
                                        "vel_from_device": "obj606C"}, **node)}}
        cfg = load_config(params, "test")
        od = canopen.import_od(DCF, 1)
        self.network = canopen.Network()
        node_ = canopen.RemoteNode(1, od)
        self.network.add_node(node_)
        node_.tpdo.read(from_od=True)
        node_.rpdo.read(from_od=True)
        self.node = node_
        self.joint = Joint(cfg.nodes[0], od, plan_node(cfg.nodes[0], od, cfg.sync, "test"))
        self.joint.bind(node_)
        self.frames = []
        self.tpdo(sw=SW_SWITCH_ON_DISABLED, mode=1, pos=0, vel=0)

    def tpdo(self, sw=None, mode=None, pos=None, vel=None):
        """What the drive's TxPDOs 1-3 carry (mapping of the project's DCF)."""
        t1, t2, t3 = (self.node.tpdo.map[n] for n in (1, 2, 3))
        if sw is not None:
            t1.data = bytearray(struct.pack("<Hb", sw, mode if mode is not None else t1.data[2]))
        if vel is not None:
            t2.data = bytearray(struct.pack("<ii", 0, vel))
        if pos is not None:
            t3.data = bytearray(struct.pack("<ii", pos, 0))

    def cycle(self, **tpdo):
        if tpdo:
            self.tpdo(**tpdo)
        self.joint.read()
        sent = []
        self.joint.write(lambda cob, data: sent.append((cob, data)))
        self.frames.extend(sent)
        return dict(sent)

    def controlword(self):
        return struct.unpack_from("<H", self.node.rpdo.map[1].data)[0]


@pytest.fixture
def h():
    return Harness()


def test_enable_walks_the_state_machine(h):
    j = h.joint
    j.request_state(State.OPERATION_ENABLED)
    expected = [(SW_SWITCH_ON_DISABLED, 0x0006), (SW_READY, 0x0007), (SW_SWITCHED_ON, 0x000F)]
    for sw, cw in expected:
        h.cycle(sw=sw)
        assert h.controlword() == cw, hex(sw)
    h.cycle(sw=SW_ENABLED)
    assert j.state == State.OPERATION_ENABLED and j.error is None
    assert h.controlword() & 0x000F == 0x000F


def test_fault_reset_only_when_asked_and_as_a_rising_edge(h):
    j = h.joint
    j.request_state(State.OPERATION_ENABLED)
    h.cycle(sw=SW_FAULT)
    assert h.controlword() == 0x0000  # no fault reset unless recover/init asks
    j.request_state(State.OPERATION_ENABLED, fault_reset=True)
    words = []
    for _ in range(4):
        h.cycle(sw=SW_FAULT)
        words.append(h.controlword())
    assert words == [0x0080, 0x0000, 0x0080, 0x0000]
    h.cycle(sw=SW_SWITCH_ON_DISABLED)
    assert h.controlword() == 0x0006


def test_leaving_the_reached_state_is_an_error_not_a_retry(h):
    j = h.joint
    j.request_state(State.OPERATION_ENABLED)
    for sw in (SW_SWITCH_ON_DISABLED, SW_READY, SW_SWITCHED_ON, SW_ENABLED):
        h.cycle(sw=sw, pos=1234)
    h.cycle(sw=SW_QUICK_STOP, pos=1300)
    assert j.error and "quick_stop_active" in j.error
    assert j.target_state is None and j.halted
    h.cycle(sw=SW_SWITCH_ON_DISABLED)
    assert h.controlword() == 0x0000  # holds: does not re-enable by itself


def ppm_enabled(h):
    j = h.joint
    j.request_state(State.OPERATION_ENABLED)
    for sw in (SW_SWITCH_ON_DISABLED, SW_READY, SW_SWITCHED_ON, SW_ENABLED):
        h.cycle(sw=sw, mode=1, pos=500)
    j.ready = True
    j.active_mode = 1
    j.reset_targets()
    # the reset target goes through the handshake once
    for sw in (SW_ENABLED, SW_ENABLED, SW_ENABLED_ACK, SW_ENABLED):
        h.cycle(sw=sw)
    h.frames.clear()
    return j


def test_profile_position_handshake_frame_by_frame(h):
    j = ppm_enabled(h)
    assert j.set_command("position", 1000).success
    out = h.cycle(sw=SW_ENABLED)
    # 1: the target goes out first (RxPDO 2 = 0x607A + 0x6081), no edge yet
    assert struct.unpack_from("<i", out[0x301])[0] == 1000
    assert h.controlword() & 0x0010 == 0
    # 2: new set-point edge with change set immediately
    h.cycle(sw=SW_ENABLED)
    assert h.controlword() & 0x0030 == 0x0030
    # 3: held until the drive acknowledges
    h.cycle(sw=SW_ENABLED)
    assert h.controlword() & 0x0010
    h.cycle(sw=SW_ENABLED_ACK)
    assert h.controlword() & 0x0010 == 0
    # a new target waits for the acknowledge to drop
    assert j.set_command("position", 2000).success
    h.cycle(sw=SW_ENABLED_ACK)
    assert struct.unpack_from("<i", h.node.rpdo.map[2].data)[0] == 1000
    h.cycle(sw=SW_ENABLED)
    assert struct.unpack_from("<i", h.node.rpdo.map[2].data)[0] == 2000


def test_controlword_pdo_every_cycle_others_on_change_and_refresh(h):
    from maxon_epos4_ros_canopen.driver.joint import REFRESH_CYCLES
    ppm_enabled(h)
    h.cycle(sw=SW_ENABLED)
    h.cycle(sw=SW_ENABLED)
    assert [cob for cob, _ in h.frames] == [0x201, 0x201]
    h.frames.clear()
    for _ in range(REFRESH_CYCLES):
        h.cycle(sw=SW_ENABLED)
    cobs = [cob for cob, _ in h.frames]
    assert cobs.count(0x201) == REFRESH_CYCLES
    assert cobs.count(0x301) == cobs.count(0x401) == cobs.count(0x501) == 1


def test_cyclic_target_goes_out_every_cycle(h):
    j = h.joint
    j.request_state(State.OPERATION_ENABLED)
    for sw in (SW_SWITCH_ON_DISABLED, SW_READY, SW_SWITCHED_ON, SW_ENABLED):
        h.cycle(sw=sw, mode=8, pos=0)
    j.ready, j.active_mode = True, 8
    assert j.set_command("position", 10).success
    for _ in range(3):
        out = h.cycle(sw=SW_ENABLED)
        assert struct.unpack_from("<i", out[0x301])[0] == 10


def test_halt_sets_bit_8_and_refuses_commands(h):
    j = ppm_enabled(h)
    j.halted = True
    h.cycle(sw=SW_ENABLED)
    assert h.controlword() & 0x0100
    r = j.set_command("position", 5)
    assert not r.success and "halted" in r.message


def test_readings_follow_the_from_device_expressions():
    h = Harness(pos_from_device="obj6064/2", vel_from_device="smooth(obj606C, vel, 0.5)")
    h.cycle(pos=1000, vel=100)
    assert h.joint.position == 500
    assert h.joint.velocity == 100      # the first value passes (old is NaN)
    h.cycle(vel=200)
    assert h.joint.velocity == 150
    assert math.isclose(h.joint.effort, 0.0)


def test_short_pdo_keeps_the_last_readings(h):
    h.cycle(pos=1000)
    h.node.tpdo.map[3].data = bytearray(b"\x01")
    h.cycle()
    assert h.joint.position == 1000
