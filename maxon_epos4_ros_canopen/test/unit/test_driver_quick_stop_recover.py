"""Recover from Quick Stop Active keeps the drive powered (CiA 402
transition 16 with quick stop option codes 5-8), and with option codes 1-4
waits for the drive's own end of the ramp instead of disabling the voltage
of a moving drive. What is checked is the simulated drive itself: its power
state and its shaft, recorded at every tick of the simulator."""
import threading

import pytest

from maxon_epos4_ros_canopen.cia402 import State
from driver_support import J1, moving_in


@pytest.fixture
def rig(driver_rig):
    return driver_rig


class Shaft:
    """Every tick of the simulated node 1: (time, power state, shaft rpm)."""

    def __init__(self, rig, node=1):
        self.samples = []
        self._lock = threading.Lock()
        drive = rig.sim.nodes[node]
        tick = drive.tick

        def recorded(now):
            tick(now)
            with self._lock:
                self.samples.append((now, drive.state, drive.motor.velocity))
        rig.sim.call(lambda: setattr(drive, "tick", recorded))

    def since(self, start):
        with self._lock:
            return [s for s in self.samples if s[0] >= start]


def pvm_at(rig, rpm, **kw):
    return moving_in(rig, 3, "velocity", rpm, 0x606C, **kw)


def test_recover_during_the_quick_stop_ramp_keeps_the_drive_powered(rig):
    d = pvm_at(rig, 3000)                       # DCF: 0x605A = 6, stay in Quick Stop Active
    assert rig.read(0x605A) == 6
    shaft = Shaft(rig)
    start = rig.sim.clock()
    assert d.halt().success
    assert rig.state() == State.QUICK_STOP_ACTIVE
    assert abs(rig.read(0x606C)) > 1000         # still on the ramp
    r = d.recover()
    assert r.success, r.message
    assert rig.until(lambda: abs(rig.read(0x606C)) < 5)
    rig.had_the_chance()
    samples = shaft.since(start)
    states = {s[1] for s in samples}
    assert states <= {State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE}, states   # never unpowered
    assert rig.state() == State.OPERATION_ENABLED
    assert rig.read(0x60FF) == 0                # holds zero speed, not the 3000 before the halt


def test_plain_halt_then_recover_keeps_the_drive_powered(rig):
    d = pvm_at(rig, 1000)
    assert d.halt().success
    assert rig.until(lambda: abs(rig.read(0x606C)) < 2)
    assert rig.state() == State.QUICK_STOP_ACTIVE
    shaft = Shaft(rig)
    start = rig.sim.clock()
    rig.drain()
    r = d.recover()
    assert r.success, r.message
    rig.had_the_chance()
    states = {s[1] for s in shaft.since(start)}
    assert states <= {State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE}, states
    # the controlwords recover sent: never disable voltage (bit 1 clear)
    words = [int.from_bytes(f[:2], "little") for f in rig.sent(0x201)]
    assert words and all(w & 0x0002 for w in words), sorted(set(words))
    assert rig.state() == State.OPERATION_ENABLED


def test_recover_with_option_code_2_waits_for_the_drive_to_end_its_ramp(rig):
    """0x605A = 2: the drive leaves Quick Stop Active for Switch On Disabled
    by itself once at rest; enable operation does not take it back. A recover
    during the ramp must not cut the power of the moving drive."""
    d = pvm_at(rig, 3000, defaults={"dcf_overlay": {"605A": "2"}})
    assert rig.read(0x605A) == 2
    shaft = Shaft(rig)
    start = rig.sim.clock()
    assert d.halt().success
    assert abs(rig.read(0x606C)) > 1000
    r = d.recover()
    assert r.success, r.message
    rig.had_the_chance()
    samples = shaft.since(start)
    # wherever the drive had no power, its shaft was at rest
    unpowered = [s for s in samples if s[1] not in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE)]
    assert unpowered, "the drive ends option 2's ramp in Switch On Disabled"
    assert max(abs(s[2]) for s in unpowered) < 5, max(abs(s[2]) for s in unpowered)
    assert rig.state() == State.OPERATION_ENABLED


def test_recover_follows_the_quick_stop_option_the_drive_has_now(rig):
    """0x605A changed with set_object after init: recover reads it over SDO."""
    d = pvm_at(rig, 1000, defaults={"dcf_overlay": {"605A": "2"}})
    assert d.set_object(J1, "605A", "6").success
    assert d.halt().success
    assert rig.until(lambda: abs(rig.read(0x606C)) < 2)
    rig.had_the_chance()
    assert rig.state() == State.QUICK_STOP_ACTIVE            # option 6: it stays there
    shaft = Shaft(rig)
    start = rig.sim.clock()
    r = d.recover()
    assert r.success, r.message
    rig.had_the_chance()
    assert {s[1] for s in shaft.since(start)} <= {State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE}
    assert rig.state() == State.OPERATION_ENABLED
