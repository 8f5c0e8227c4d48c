"""A target forged on the drive's own RxPDO never becomes motion: before any
enable or halt release the driver makes the drive hold the driver's own
target with no set-point pending, and a command equal to the last one goes
out again when the drive holds another value. Positions are read from the
simulator."""
import struct

import pytest

from driver_support import J1, ppm_ready
from test_driver_adversary import forge

FORGED = 500000
PROFILE_VELOCITY = 1000  # the DCF's 0x6081: the forged frame leaves it as it is


@pytest.fixture
def rig(driver_rig):
    return driver_rig


def forge_target(rig, new_set_point_cw=None):
    """0x607A = FORGED on RxPDO 2 (0x301); with a controlword, a new
    set-point edge on RxPDO 1 (0x201) after it."""
    forge(rig, 0x301, struct.pack("<iI", FORGED, PROFILE_VELOCITY))
    if new_set_point_cw is not None:
        rig.sim_ran()
        forge(rig, 0x201, struct.pack("<Hi", new_set_point_cw & ~0x10, 0))
        forge(rig, 0x201, struct.pack("<Hi", new_set_point_cw, 0))
    assert rig.until(lambda: rig.read(0x607A) == FORGED)


def stands_still_after(rig, d, start, seconds=1.0):
    rig.had_the_chance(int(seconds * 100))
    return abs(rig.read(0x6064) - start)


@pytest.mark.parametrize("halt_mode", ["quick_stop", "halt_bit"])
def test_a_target_forged_while_halted_is_not_taken_by_recover(rig, halt_mode):
    d = ppm_ready(rig, defaults={"halt_mode": halt_mode})
    assert d.set_command(J1, "position", 2000).success
    assert rig.until(lambda: abs(rig.read(0x6064) - 2000) < 5)
    # a first halt and recover: the driver's target is now where the drive
    # stands, and the second recover finds the position it holds already
    assert d.halt().success
    assert d.recover().success
    rig.had_the_chance()
    assert d.halt().success
    # halted with the halt bit, the drive even acknowledges a forged set-point
    forge_target(rig, 0x013F if halt_mode == "halt_bit" else None)
    start = rig.read(0x6064)
    r = d.recover()
    assert r.success, r.message
    moved = stands_still_after(rig, d, start)
    assert moved < 50, moved
    assert rig.read(0x607A) != FORGED


def test_a_command_equal_to_the_last_goes_out_again_when_the_drive_holds_another(rig):
    d = ppm_ready(rig)
    assert d.set_command(J1, "position", 2000).success
    assert rig.until(lambda: abs(rig.read(0x6064) - 2000) < 5)
    forge_target(rig)
    assert d.set_command(J1, "position", 2000).success
    moved = stands_still_after(rig, d, 2000)
    assert moved < 50, moved
    assert rig.read(0x607A) == 2000
