"""A stop the driver commands in a cyclic mode (halt, an error) decelerates
the shaft no harder than the drive's configured quick stop deceleration
(0x6085): the driver uses the drive's own quick stop there. The shaft is the
simulator's, recorded at every tick."""
import struct

import pytest

from maxon_epos4_ros_canopen.cia402 import State
from driver_support import J1
from test_driver_adversary import forge
from test_driver_quick_stop_recover import Shaft

SPEED = 3000          # rpm
# The shaft's deceleration is judged twice: on average from its fastest
# moment after the stop command to rest, within MEAN_SLACK of 0x6085; and at
# worst over any WINDOW, within WORST_SLACK. The slack is the simulated
# motor's: it overshoots for some 50 ms where its position loop takes over
# from the velocity loop, and a starved simulator loop shakes it (measured
# on a loaded host: mean 6,000-10,700, worst 10,800-12,700 rpm/s for 0x6085
# = 10,000). A stop that holds a target brakes at 31,000-33,000 rpm/s at worst.
WINDOW = 0.1          # s
MEAN_SLACK = 1.25
WORST_SLACK = 1.5


@pytest.fixture
def rig(driver_rig):
    return driver_rig


def moving(rig, mode, **kw):
    d = rig.start(**kw)
    assert d.init().success
    assert d.switch_mode([J1], mode).success
    if mode == 9:
        assert d.set_command(J1, "velocity", SPEED).success
    else:  # CSP: a target that moves on every cycle, SPEED rpm worth
        per_s = SPEED * rig.sim.nodes[1].motor.inc_per_s_per_rpm
        start = rig.read(0x6064)
        step = per_s * 0.01

        def ramp(driver, _state={"n": 0}):
            _state["n"] += 1
            driver.set_command(J1, "position", start + step * _state["n"])
        d.add_cycle_callback(ramp)
        rig.ramp = ramp
    assert rig.until(lambda: abs(rig.read(0x606C) - SPEED) < 300)
    return d


def mean_deceleration(samples):
    head = [s for s in samples if s[0] - samples[0][0] <= 0.05]
    t_peak, _, v_peak = max(head, key=lambda s: abs(s[2]))
    t_rest = next(t for t, _, v in samples if t > t_peak and abs(v) < 5)
    return abs(v_peak) / (t_rest - t_peak)


def hardest_deceleration(samples):
    worst = 0.0
    j = 0
    for i, (t, _, v) in enumerate(samples):
        while samples[j][0] < t - WINDOW:
            j += 1
        t0, _, v0 = samples[j]
        if t - t0 >= WINDOW / 2 and abs(v0) > abs(v):
            worst = max(worst, (abs(v0) - abs(v)) / (t - t0))
    return worst


def stop_and_measure(rig, d, stop):
    shaft = Shaft(rig)
    start = rig.sim.clock()
    stop(d)
    assert rig.until(lambda: abs(rig.read(0x606C)) < 5)
    rig.had_the_chance()
    samples = shaft.since(start)
    assert rig.state() in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE)   # powered
    decel = rig.read(0x6085)
    mean, worst = mean_deceleration(samples), hardest_deceleration(samples)
    assert mean <= MEAN_SLACK * decel and worst <= WORST_SLACK * decel, (mean, worst, decel)


def forged_fault(rig):
    def stop(d):
        for _ in range(100):   # until the driver has read one (the drive's own TPDO1 may come first)
            forge(rig, 0x181, struct.pack("<Hb", 0x0208, 9))
            if rig.until(lambda: d.joints[J1].error is not None, 0.05):
                return
        raise AssertionError("the forged statusword never reached the driver")
    return stop


@pytest.mark.parametrize("mode", [9, 8])
def test_halt_in_a_cyclic_mode_respects_the_quick_stop_deceleration(rig, mode):
    d = moving(rig, mode, defaults={"halt_mode": "halt_bit"})

    def halt(d):
        assert d.halt().success
        if mode == 8:  # set_command is refused from the halt on; it must not go on after recover
            d.remove_cycle_callback(rig.ramp)
    stop_and_measure(rig, d, halt)
    assert d.recover().success
    assert rig.state() == State.OPERATION_ENABLED


@pytest.mark.parametrize("mode", [9, 8])
def test_an_error_in_a_cyclic_mode_stops_at_the_quick_stop_deceleration(rig, mode):
    d = moving(rig, mode)
    stop_and_measure(rig, d, forged_fault(rig))
