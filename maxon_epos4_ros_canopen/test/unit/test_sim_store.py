"""The virtual EPOS4's non-volatile memory: 0x1010 "save" keeps the settings
across a power cycle (and NMT reset node), 0x1011 "load" brings the file's
values back at the next one; what is not stored is lost. Seen by an
independent canopen client over the bus."""
import pytest

from maxon_epos4_ros_canopen.clock import REAL
from sim_support import NODE1, NodeConfig

SAVE, LOAD = 0x65766173, 0x64616F6C


@pytest.fixture
def rig(sim_rig):
    """The wall clock: canopen's NMT master waits for the boot-up in real time."""
    return sim_rig([NodeConfig(1, NODE1)], clock=REAL)


def test_only_stored_settings_survive_a_power_cycle(rig):
    node = rig.remote(1)
    node.sdo[0x6083].raw = 20000
    node.sdo[0x1010][1].raw = SAVE
    node.sdo[0x6084].raw = 30000  # written after the save: not stored
    rig.sim.inject_fault(1, "reboot")
    assert node.sdo[0x6083].raw == 20000
    assert node.sdo[0x6084].raw != 30000


def test_reset_node_reloads_what_was_stored(rig):
    node = rig.remote(1)
    node.sdo[0x6083].raw = 20000
    node.sdo[0x1010][1].raw = SAVE
    node.sdo[0x6083].raw = 25000
    node.nmt.send_command(0x81)  # NMT reset node
    assert node.nmt.wait_for_bootup(10) is None
    assert node.sdo[0x6083].raw == 20000


def test_commands_and_set_points_are_not_stored(rig):
    node = rig.remote(1)
    node.sdo[0x607A].raw = 12345  # target position: a set-point
    node.sdo[0x1010][1].raw = SAVE
    rig.sim.inject_fault(1, "reboot")
    assert node.sdo[0x607A].raw == 0


def test_restore_defaults_takes_effect_at_the_next_power_cycle(rig):
    node = rig.remote(1)
    file_value = node.sdo[0x6083].raw
    node.sdo[0x6083].raw = 20000
    node.sdo[0x1010][1].raw = SAVE
    node.sdo[0x1011][1].raw = LOAD
    assert node.sdo[0x6083].raw == 20000  # until the next power-on
    rig.sim.inject_fault(1, "reboot")
    assert node.sdo[0x6083].raw == file_value


def test_a_wrong_signature_stores_nothing(rig):
    node = rig.remote(1)
    file_value = node.sdo[0x6083].raw
    node.sdo[0x6083].raw = 20000
    with pytest.raises(Exception) as info:
        node.sdo[0x1010][1].raw = 1
    assert getattr(info.value, "code", None) == 0x08000020
    rig.sim.inject_fault(1, "reboot")
    assert node.sdo[0x6083].raw == file_value
