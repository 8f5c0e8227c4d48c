"""A mode switch goes through the node layer's switching state: a drive
that was turning there may still turn. The new mode must hold where the
drive came to rest, read from the simulated drive's own objects."""
from driver_support import DCF1, DCF2, J1, J2, ppm_ready


def test_back_to_profile_position_from_a_turning_drive_holds_where_it_came_to_rest(driver_rig):
    rig = driver_rig
    d = ppm_ready(rig)
    assert d.switch_mode([J1], 3).success
    assert d.set_command(J1, "velocity", 500).success
    assert rig.until(lambda: abs(rig.read(0x606C) - 500) < 5)
    assert d.switch_mode([J1], 1).success
    rig.had_the_chance(50)
    assert rig.read(0x606C) == 0
    assert abs(rig.read(0x607A) - rig.read(0x6064)) < 50, (rig.read(0x607A), rig.read(0x6064))


def test_a_switch_to_the_mode_a_drive_is_in_returns_with_the_halt_bit_released(driver_rig):
    """The node switches running controllers' joints back to their modes
    after recover: the drives run free again once that call returns, as
    read over SDO at once (the driver's hold sets the halt bit for one cycle)."""
    rig = driver_rig
    d = rig.start(nodes=((1, DCF1, J1), (2, DCF2, J2)))
    assert d.init().success
    assert d.switch_mode([J1, J2], 3).success
    assert d.set_command(J1, "velocity", 500).success
    assert rig.until(lambda: abs(rig.read(0x606C) - 500) < 5)
    assert d.switch_mode([J1, J2], 3).success
    for node in (1, 2):
        assert rig.read(0x6040, node=node) & 0x010F == 0x000F, (node, hex(rig.read(0x6040, node=node)))
    assert rig.read(0x60FF) == 0  # the hold: the switch stopped the drive


def test_a_switch_to_profile_position_it_is_in_returns_once_the_drive_took_the_held_set_point(driver_rig):
    """In profile position the hold is a set-point the drive must
    acknowledge before the halt bit goes: the call waits for that, so a
    command right after it moves the drive."""
    rig = driver_rig
    d = ppm_ready(rig)
    start = rig.read(0x6064)
    assert d.halt().success
    assert d.recover().success
    assert d.switch_mode([J1], 1).success
    assert rig.read(0x6040) & 0x0100 == 0, hex(rig.read(0x6040))
    assert d.set_command(J1, "position", start + 2000).success
    assert rig.until(lambda: abs(rig.read(0x6064) - (start + 2000)) < 5)
