"""Boot-ups, forged and real, against the virtual EPOS4: a heartbeat byte
other than 0x00 is no boot-up; a drive is treated as rebooted only once its
own SDO answers confirm it; and after recover from a real reboot the drive
stands still. The drive's state, position and shaft are read from the
simulator."""
import pytest

from maxon_epos4_ros_canopen.cia402 import State
from driver_support import J1, moving_in
from test_driver_adversary import forge
from test_driver_quick_stop_recover import Shaft

POWERED = {State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE}
REFERENCE = 5000  # where the drive stands before the forged heartbeat


@pytest.fixture
def rig(driver_rig):
    return driver_rig


def csp_at(rig, position, **kw):
    return moving_in(rig, 8, "position", position, 0x6064, **kw)


def test_a_heartbeat_byte_0x80_is_no_boot_up(rig):
    d = csp_at(rig, REFERENCE)
    before = d.joints[J1].counters["undefined_nmt_state"]
    forge(rig, 0x701, b"\x80")
    assert rig.until(lambda: d.joints[J1].counters["undefined_nmt_state"] == before + 1)
    rig.had_the_chance()
    assert d.joints[J1].error is None and not d.joints[J1].rebooted
    assert d.set_command(J1, "position", REFERENCE + 100).success
    assert rig.until(lambda: abs(rig.read(0x6064) - (REFERENCE + 100)) < 20)


@pytest.mark.parametrize("state_byte", [0x00, 0x04, 0x7F, 0x80, 0x84, 0xFF])
def test_a_forged_heartbeat_never_makes_recover_reset_an_enabled_drive(rig, state_byte):
    d = csp_at(rig, REFERENCE)
    shaft = Shaft(rig)
    start = rig.sim.clock()
    forge(rig, 0x701, bytes([state_byte]))
    rig.had_the_chance()
    # (the drive may have moved a little: a starved simulator loop shakes
    # the simulated motor; what must not happen is a reset to 0)
    before = rig.read(0x6064)
    assert abs(before) > 1000
    r = d.recover()
    assert r.success, r.message
    assert "rebooted" not in r.message
    rig.had_the_chance()
    states = {s[1] for s in shaft.since(start)}
    assert states <= POWERED, states                           # never unpowered
    assert rig.state() == State.OPERATION_ENABLED
    assert abs(rig.read(0x6064) - before) < 50                 # the position reference kept
    assert d.joints[J1].error is None
    assert d.set_command(J1, "position", REFERENCE + 100).success
    assert rig.until(lambda: abs(rig.read(0x6064) - (REFERENCE + 100)) < 20)


@pytest.mark.parametrize("mode, command", [(8, ("position", REFERENCE)), (1, ("position", REFERENCE)),
                                           (3, ("velocity", 0)), (9, ("velocity", 0))])
def test_after_recover_from_a_real_reboot_the_drive_stands_still(rig, mode, command):
    d = rig.start()
    assert d.init().success
    assert d.switch_mode([J1], mode).success
    assert d.set_command(J1, *command).success
    if command[0] == "position":
        assert rig.until(lambda: abs(rig.read(0x6064) - REFERENCE) < 20)
    rig.sim.inject_fault(1, "reboot")
    assert rig.until(lambda: "rebooted" in (d.joints[J1].error or ""))
    r = d.recover()
    assert r.success, r.message
    assert "rebooted" in r.message
    assert rig.state() == State.OPERATION_ENABLED
    after = rig.read(0x6064)
    shaft = Shaft(rig)
    start = rig.sim.clock()
    assert rig.until(lambda: rig.sim.clock() - start > 1.0 and len(shaft.since(start)) > 100)
    moved = abs(rig.read(0x6064) - after)
    fastest = max(abs(s[2]) for s in shaft.since(start))
    assert rig.state() == State.OPERATION_ENABLED
    assert moved < 5 and fastest < 5, (moved, fastest)         # increments, rpm
