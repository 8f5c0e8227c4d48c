"""Each mode's behaviour through its own object (driver/modes.py), on a
stand-in for the axis that records what the mode asks of it: the profile
position handshake frame by frame, the homing start and end, and how every
mode holds and stops."""
import pytest

from maxon_epos4_ros_canopen import cia402
from maxon_epos4_ros_canopen.driver.modes import MODES, TARGET_OF_KIND

SW_ENABLED = 0x0637
ACK = cia402.SW_SET_POINT_ACKNOWLEDGE


class FakeAxis:
    def __init__(self):
        self.statusword = SW_ENABLED
        self.homing = False
        self.sent = []           # (kind, value) sent with send_target
        self.quick_stopped = False

    def send_target(self, kind, value):
        self.sent.append((kind, value))

    def stop_with_quick_stop(self):
        self.quick_stopped = True


def fresh(number):
    mode = MODES[number].fresh()
    assert mode is not MODES[number] and type(mode) is type(MODES[number])
    return mode


@pytest.mark.parametrize("number, kind, cyclic", [(1, "position", False), (3, "velocity", False), (6, None, False),
                                                  (8, "position", True), (9, "velocity", True),
                                                  (10, "effort", True)])
def test_each_mode_knows_its_command_and_target(number, kind, cyclic):
    mode = MODES[number]
    assert mode.command_kind == kind and mode.cyclic is cyclic
    assert mode.target == (TARGET_OF_KIND[kind] if kind else None)


def test_profile_position_handshake_frame_by_frame():
    ppm, axis = fresh(1), FakeAxis()
    assert ppm.controlword_bits(axis) == 0x0020          # idle: change set immediately only
    ppm.command(axis, 1000)
    # 1: the target goes out (whether it changed or not), no edge yet
    assert ppm.controlword_bits(axis) == 0x0020 and axis.sent == [("position", 1000)]
    # 2: the new set-point edge
    assert ppm.controlword_bits(axis) == 0x0030
    # 3: held until the drive acknowledges
    assert ppm.controlword_bits(axis) == 0x0030
    axis.statusword = SW_ENABLED | ACK
    assert ppm.controlword_bits(axis) == 0x0020           # acknowledged: edge cleared
    # a new target waits for the acknowledge to drop
    ppm.command(axis, 2000)
    assert ppm.controlword_bits(axis) == 0x0020 and axis.sent == [("position", 1000)]
    axis.statusword = SW_ENABLED
    assert ppm.controlword_bits(axis) == 0x0020 and axis.sent[-1] == ("position", 2000)
    assert ppm.controlword_bits(axis) == 0x0030


def test_profile_position_sends_a_repeated_target_again():
    ppm, axis = fresh(1), FakeAxis()
    for _ in range(2):
        ppm.command(axis, 1000)
        ppm.controlword_bits(axis)
        ppm.controlword_bits(axis)
        axis.statusword = SW_ENABLED | ACK
        ppm.controlword_bits(axis)
        axis.statusword = SW_ENABLED
        ppm.controlword_bits(axis)
    assert axis.sent == [("position", 1000), ("position", 1000)]


def test_profile_position_holds_with_the_halt_bit_until_its_own_set_point_is_acknowledged():
    ppm, axis = fresh(1), FakeAxis()
    ppm.hold(axis, 500)
    assert ppm.holding()
    assert ppm.controlword_bits(axis) == 0x0120 and axis.sent == [("position", 500)]
    assert ppm.controlword_bits(axis) == 0x0130
    axis.statusword = SW_ENABLED | ACK
    assert ppm.controlword_bits(axis) == 0x0120
    axis.statusword = SW_ENABLED
    assert ppm.controlword_bits(axis) == 0x0020           # released: the drive holds 500
    assert not ppm.holding()


def test_profile_position_stop_drops_what_was_not_sent():
    ppm, axis = fresh(1), FakeAxis()
    ppm.command(axis, 1000)
    ppm.stop(axis)
    assert ppm.controlword_bits(axis) == 0x0020 and axis.sent == []
    assert not axis.quick_stopped                        # the axis's halt bit stops it


def test_homing_start_and_end():
    hm, axis = fresh(6), FakeAxis()
    assert hm.controlword_bits(axis) == 0
    axis.homing = True
    assert hm.controlword_bits(axis) == cia402.CW_HOMING_START    # start, and kept while it runs
    assert hm.controlword_bits(axis) == cia402.CW_HOMING_START
    axis.homing = False
    assert hm.controlword_bits(axis) == 0                          # end (or interrupt)
    hm.stop(axis)
    assert not axis.quick_stopped


def test_profile_velocity_sends_every_command_and_stops_with_the_halt_bit():
    pvm, axis = fresh(3), FakeAxis()
    pvm.command(axis, 300)
    pvm.command(axis, 300)
    assert axis.sent == [("velocity", 300), ("velocity", 300)]
    assert pvm.controlword_bits(axis) == 0
    pvm.stop(axis)
    assert not axis.quick_stopped and pvm.stops_with_halt_bit()


@pytest.mark.parametrize("number", [8, 9, 10])
def test_cyclic_modes_stop_with_the_drives_quick_stop(number):
    mode, axis = fresh(number), FakeAxis()
    mode.command(axis, 123)
    assert axis.sent == []                                # the cycle sends the target every SYNC
    assert mode.controlword_bits(axis) == 0
    mode.hold(axis, 500)
    assert not mode.holding()
    mode.stop(axis)
    assert axis.quick_stopped and not mode.stops_with_halt_bit()


def test_an_axis_runs_its_own_instances():
    a, b = fresh(1), fresh(1)
    a.command(FakeAxis(), 1)
    assert b.pending is None


def test_profile_position_enabled_from_another_state_needs_no_set_point():
    """The enable itself leaves the drive holding where it is: a set-point of
    a position read before it would pull a shaft that crept back."""
    ppm, axis = fresh(1), FakeAxis()
    ppm.hold(axis, 500)
    ppm.enabled(axis)
    assert not ppm.holding()
    assert ppm.controlword_bits(axis) == 0x0020 and axis.sent == []
    ppm.command(axis, 700)                                # a command after it goes through as ever
    ppm.enabled(axis)
    assert ppm.controlword_bits(axis) == 0x0020 and axis.sent == [("position", 700)]
