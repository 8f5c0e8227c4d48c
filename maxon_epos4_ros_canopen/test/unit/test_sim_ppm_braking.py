"""Profile Position on the virtual EPOS4 ends on its target, as a real
EPOS4's profile does: with the position window off (0x6067 = 0xFFFFFFFF),
"target reached" rises as the profile ends, and the rotor is then at most
10 increments past the target, whatever the length of the simulator's steps
(1 ms on a quiet host, 20 ms when its loop is starved).

The node is stepped on simulated time, one ``tick`` per step, and commanded
by SDO download frames as a master sends them; the shaft position is read
from the simulator's motor model, not from anything the drive reports."""
import glob
import os
from typing import Tuple

import pytest

from sim_stepped import SteppedNode

HERE = os.path.dirname(os.path.abspath(__file__))
CONFIG = os.path.join(os.path.dirname(os.path.dirname(HERE)), "config")
REPO = os.path.dirname(os.path.dirname(os.path.dirname(HERE)))
VENDOR_DIR = os.path.join(os.path.dirname(REPO), "shared", "vendor_dcf")  # beside the clone
# maxon's export as EPOS Studio wrote it (the BOOLEAN object left in).
UNEDITED = sorted(glob.glob(os.path.join(VENDOR_DIR, "*_node1_unedited_boolean.dcf")))
DCFS = [os.path.join(CONFIG, "epos4_node1.dcf")] + UNEDITED
WINDOW_OFF = 0xFFFFFFFF
TARGET_REACHED = 0x0400
OVERSHOOT_LIMIT = 10.0  # increments
STEPS = [0.001, 0.005, 0.010, 0.020]  # s
# (distance in increments, profile velocity in rpm, acceleration, deceleration in rpm/s);
# None keeps the file's value.
MOVES = [
    (3000, None, None, None),
    (-7000, None, None, None),
    (20000, 600, 2000, None),
    (555, None, None, None),
    (40000, 3000, 5000, 20000),
]


def move(dcf: str, step: float, distance: int, velocity, accel, decel) -> Tuple[float, float, float]:
    """(overshoot at the rise of target reached, largest overshoot until 1 s
    after it, time of the rise): overshoot counts past the target, in the
    direction of the move."""
    drive = SteppedNode(dcf, step=step)
    drive.write(0x6067, 0, WINDOW_OFF)
    for index, value in ((0x6081, velocity), (0x6083, accel), (0x6084, decel)):
        if value is not None:
            drive.write(index, 0, value)
    drive.write(0x6060, 0, 1)
    for cw in (0x0006, 0x0007, 0x000F):
        drive.write(0x6040, 0, cw)
    for _ in range(5):
        drive.tick()
    target = int(round(drive.shaft)) + distance
    drive.write(0x607A, 0, target)
    drive.write(0x6040, 0, 0x001F)
    assert not drive.statusword() & TARGET_REACHED
    drive.write(0x6040, 0, 0x000F)
    sign = 1.0 if distance > 0 else -1.0
    worst = -float("inf")
    rise = None
    ticks = 0
    while ticks < int(30.0 / step):
        drive.tick()
        ticks += 1
        over = (drive.shaft - target) * sign
        worst = max(worst, over)
        if rise is None and drive.statusword() & TARGET_REACHED:
            rise = (over, ticks * step)
            end = ticks + int(1.0 / step)
        if rise is not None and ticks >= end:
            break
    assert rise is not None, "target reached never rose (%s, step %g s, move %d)" % (dcf, step, distance)
    return rise[0], worst, rise[1]


@pytest.mark.parametrize("dcf", DCFS, ids=[os.path.basename(p) for p in DCFS])
@pytest.mark.parametrize("step", STEPS, ids=["%gms" % (s * 1000) for s in STEPS])
def test_ppm_target_reached_rises_on_the_target(dcf, step):
    figures = []
    for distance, velocity, accel, decel in MOVES:
        at_rise, worst, _ = move(dcf, step, distance, velocity, accel, decel)
        figures.append((distance, round(at_rise, 1), round(worst, 1)))
    assert all(at_rise <= OVERSHOOT_LIMIT for _, at_rise, _ in figures), \
        "(move, overshoot at target reached, largest) in inc: %s" % figures
    assert all(worst <= OVERSHOOT_LIMIT for _, _, worst in figures), \
        "(move, overshoot at target reached, largest) in inc: %s" % figures


@pytest.mark.parametrize("step", STEPS, ids=["%gms" % (s * 1000) for s in STEPS])
def test_ppm_move_takes_the_profile_time(step):
    """The braking fix keeps the profile: a 3000 inc move at 1000 rpm and
    10000 rpm/s (3200 inc/turn) takes 3000/53333 + 0.1 s = 0.156 s; target
    reached rises then, not a step or a settling time later."""
    _, _, rise = move(DCFS[0], step, 3000, 1000, 10000, 10000)
    assert rise == pytest.approx(3000 / (1000 * 3200 / 60.0) + 0.1, abs=step + 0.003)
