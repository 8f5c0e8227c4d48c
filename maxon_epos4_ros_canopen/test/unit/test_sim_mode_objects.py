"""The virtual EPOS4's operation modes, one object each (sim/modes.py): the
target object each follows, the PPM set-point handshake frame by frame, the
homing start and end, and how every mode holds on halt and stops on a quick
stop. Stepped on simulated time; the drive is commanded and read by SDO."""
import os

import pytest

from maxon_epos4_ros_canopen.sim import modes
from maxon_epos4_ros_canopen.sim.modes import StopRamp, make_mode
from sim_stepped import SteppedNode

CONFIG = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "config")
NODE1 = os.path.join(CONFIG, "epos4_node1.dcf")
NODE1_HM = os.path.join(CONFIG, "epos4_node1_hm.dcf")
ACK, TARGET_REACHED, INTERNAL_LIMIT = 0x1000, 0x0400, 0x0800
SPEED_ZERO = FOLLOWS_COMMAND = HOMING_ATTAINED = 0x1000
HOMING_ERROR = 0x2000


def enabled(mode: int, dcf: str = NODE1, **kw) -> SteppedNode:
    drive = SteppedNode(dcf, **kw)
    drive.write(0x6060, 0, mode)
    for cw in (0x0006, 0x0007, 0x000F):
        drive.write(0x6040, 0, cw)
    assert drive.read(0x6041) & 0x6F == 0x27
    return drive


def sw(drive: SteppedNode) -> int:
    return drive.read(0x6041)


@pytest.mark.parametrize("number, key, cls", [
    (1, (0x607A, 0), modes.ProfilePosition), (3, (0x60FF, 0), modes.ProfileVelocity),
    (6, None, modes.Homing), (8, (0x607A, 0), modes.CyclicSyncPosition),
    (9, (0x60FF, 0), modes.CyclicSyncVelocity), (10, (0x6071, 0), modes.CyclicSyncTorque),
])
def test_each_mode_is_an_object_with_its_target_object(number, key, cls):
    drive = enabled(number)
    assert type(drive.node.active) is cls
    assert drive.node.active.target_object == key
    assert type(make_mode(0, drive.node)) is modes.Idle


def test_ppm_set_point_handshake_frame_by_frame():
    drive = enabled(1)
    start = drive.read(0x6064)
    assert sw(drive) & (ACK | TARGET_REACHED) == TARGET_REACHED  # idle
    drive.write(0x607A, 0, start + 4000)
    drive.tick(20)
    assert drive.read(0x6062) == start  # no edge of bit 4: no move
    drive.write(0x6040, 0, 0x001F)
    assert sw(drive) & (ACK | TARGET_REACHED) == ACK  # taken, not reached
    drive.write(0x6040, 0, 0x000F)
    assert sw(drive) & ACK == 0  # bit 4 low: acknowledge low
    drive.tick(10)
    # moving, single set-point off: a second one is buffered and acknowledged ...
    drive.write(0x607A, 0, start + 1000)
    drive.write(0x6040, 0, 0x001F)
    assert sw(drive) & ACK
    drive.write(0x6040, 0, 0x000F)
    # ... a third finds the buffer full: not acknowledged, not taken
    drive.write(0x607A, 0, start + 9000)
    drive.write(0x6040, 0, 0x001F)
    assert sw(drive) & ACK == 0
    drive.write(0x6040, 0, 0x000F)
    passed_first = []
    assert drive.run_until(lambda: passed_first.append(drive.read(0x6062)) or sw(drive) & TARGET_REACHED)
    assert max(passed_first) == start + 4000  # the first move ended on its target ...
    assert drive.read(0x6062) == start + 1000  # ... then the buffered one ran
    assert abs(drive.read(0x6064) - (start + 1000)) <= 10


def test_ppm_change_set_immediately_and_relative():
    drive = enabled(1)
    start = drive.read(0x6064)
    drive.write(0x607A, 0, 3000)
    drive.write(0x6040, 0, 0x005F)  # relative
    drive.write(0x6040, 0, 0x004F)
    drive.tick(20)
    drive.write(0x607A, 0, start - 2000)
    drive.write(0x6040, 0, 0x003F)  # absolute, at once: turns back
    drive.write(0x6040, 0, 0x000F)
    assert drive.run_until(lambda: sw(drive) & TARGET_REACHED)
    assert drive.read(0x6062) == start - 2000


def test_ppm_target_clamped_to_software_limits():
    drive = SteppedNode(NODE1)
    drive.write(0x607D, 1, -1000)
    drive.write(0x607D, 2, 1500)
    drive = enabled_from(drive, 1)
    drive.write(0x607A, 0, 5000)
    drive.write(0x6040, 0, 0x001F)
    assert sw(drive) & INTERNAL_LIMIT
    drive.write(0x6040, 0, 0x000F)
    assert drive.run_until(lambda: sw(drive) & TARGET_REACHED)
    assert drive.read(0x6062) == 1500


def enabled_from(drive: SteppedNode, mode: int) -> SteppedNode:
    drive.write(0x6060, 0, mode)
    for cw in (0x0006, 0x0007, 0x000F):
        drive.write(0x6040, 0, cw)
    return drive


def test_ppm_halt_holds_and_release_resumes():
    drive = enabled(1)
    target = drive.read(0x6064) + 8000
    drive.write(0x607A, 0, target)
    drive.write(0x6040, 0, 0x001F)
    drive.write(0x6040, 0, 0x000F)
    assert drive.run_until(lambda: drive.read(0x606B) >= 500)
    drive.write(0x6040, 0, 0x010F)
    assert drive.run_until(lambda: sw(drive) & TARGET_REACHED)  # halted: target reached
    held = drive.read(0x6062)
    assert drive.read(0x606B) == 0 and held < target
    drive.tick(40)
    assert drive.read(0x6062) == held
    drive.write(0x6040, 0, 0x000F)
    assert drive.run_until(lambda: sw(drive) & TARGET_REACHED and drive.read(0x6062) == target)


def test_pvm_halt_ramps_to_zero_and_release_returns():
    drive = enabled(3)
    drive.write(0x60FF, 0, 800)
    assert drive.run_until(lambda: sw(drive) & TARGET_REACHED)
    assert abs(drive.read(0x606C) - 800) <= 10
    drive.write(0x6040, 0, 0x010F)
    assert drive.run_until(lambda: sw(drive) & SPEED_ZERO)
    assert drive.read(0x606B) == 0
    drive.write(0x6040, 0, 0x000F)
    assert drive.run_until(lambda: abs(drive.read(0x606C) - 800) <= 10)


def test_pvm_target_beyond_max_profile_velocity_is_limited():
    drive = enabled(3)
    drive.write(0x607F, 0, 500)
    drive.write(0x60FF, 0, 900)
    assert drive.run_until(lambda: sw(drive) & TARGET_REACHED)
    assert sw(drive) & INTERNAL_LIMIT and drive.read(0x606B) == 500


def test_homing_37_start_and_end():
    drive = SteppedNode(NODE1)
    drive.write(0x6098, 0, 37)
    drive.write(0x30B0, 0, 1234)
    enabled_from(drive, 6)
    assert sw(drive) & HOMING_ATTAINED == 0
    drive.write(0x6040, 0, 0x001F)  # homing start
    assert sw(drive) & (HOMING_ATTAINED | TARGET_REACHED | 0x8000) == HOMING_ATTAINED | TARGET_REACHED | 0x8000
    assert drive.read(0x6064) == 1234


def test_homing_minus3_search_halt_and_back_off():
    drive = SteppedNode(NODE1_HM, hard_stop=(-5000.0, 1600.0))
    enabled_from(drive, 6)
    drive.write(0x6040, 0, 0x001F)
    assert drive.run_until(lambda: drive.read(0x606C) > 50)  # searching upward
    drive.write(0x6040, 0, 0x011F)  # halt: slows down with 0x609A and holds
    assert drive.run_until(lambda: sw(drive) & TARGET_REACHED)
    assert drive.read(0x606B) == 0 and sw(drive) & HOMING_ATTAINED == 0
    drive.write(0x6040, 0, 0x001F)  # release: the search goes on
    assert drive.run_until(lambda: sw(drive) & HOMING_ATTAINED, seconds=20)
    assert abs(drive.read(0x6064)) <= 2 and sw(drive) & 0x8000


def test_homing_unsupported_method_ends_in_homing_error():
    drive = SteppedNode(NODE1)
    drive.write(0x6098, 0, 1)
    enabled_from(drive, 6)
    drive.write(0x6040, 0, 0x001F)
    assert sw(drive) & (HOMING_ERROR | TARGET_REACHED) == HOMING_ERROR | TARGET_REACHED


@pytest.mark.parametrize("mode, key, value", [(9, 0x60FF, 300), (10, 0x6071, 50)])
def test_cyclic_modes_follow_their_set_point_through_halt(mode, key, value):
    drive = enabled(mode)
    assert sw(drive) & FOLLOWS_COMMAND
    drive.write(0x6040, 0, 0x010F)  # halt: the master holds a cyclic mode, not the drive
    drive.write(key, 0, value)
    assert drive.run_until(lambda: drive.read(0x606C) > 100)


def test_csp_follows_the_target_taken_at_sync_through_halt():
    drive = enabled(8)
    drive.node.on_nmt(0x01, drive.now)  # operational: SYNC is served
    start = drive.read(0x6064)
    drive.write(0x6040, 0, 0x010F)
    target = start
    for _ in range(50):
        target += 20
        drive.write(0x607A, 0, target)
        drive.node.on_sync(drive.now)
        drive.tick(2)  # 10 ms SYNC period
    assert drive.read(0x6062) == target
    assert abs(drive.read(0x6064) - target) < 30


@pytest.mark.parametrize("mode", [1, 3, 6, 8, 9, 10])
@pytest.mark.parametrize("option, final", [(0, 0x0250), (2, 0x0250), (6, 0x0617)])
def test_quick_stop_of_every_mode(mode, option, final):
    drive = enabled(mode)
    drive.write(0x605A, 0, option)
    if mode == 3:
        drive.write(0x60FF, 0, 600)
        assert drive.run_until(lambda: drive.read(0x606C) > 550)
    drive.write(0x6040, 0, 0x0002)
    assert drive.run_until(lambda: sw(drive) == final)
    assert drive.run_until(lambda: drive.read(0x606C) == 0, seconds=20.0)  # at rest (option 0: coasts)
    assert sw(drive) == final


@pytest.mark.parametrize("option, decel", [(1, 0x6084), (2, 0x6085), (5, 0x6084), (6, 0x6085)])
def test_stop_ramp_uses_the_option_codes_deceleration(option, decel):
    drive = SteppedNode(NODE1)
    drive.write(0x6084, 0, 4000)
    drive.write(0x6085, 0, 1000)
    demand = modes.Demand(0.0, 1000.0)
    ramp = StopRamp(option)
    ramp.step(0.01, demand, drive.node.store, 3200 / 60.0)
    assert demand.velocity == pytest.approx(1000.0 - 0.01 * drive.read(decel))
    assert ramp.stays_in_quick_stop == (option in (5, 6))
