"""The one command check (driver/check.py check_command): a pure function of
the command, the joint's snapshot and its limits, giving the saturated
device value or the reason for refusing it; and a command converted once
on its way from a caller to the drive."""
import math
import threading
import time
from types import SimpleNamespace

import pytest

from maxon_epos4_ros_canopen.cia402 import State
from maxon_epos4_ros_canopen.driver import JointLimits
from maxon_epos4_ros_canopen.driver.check import Checked, check_command
from maxon_epos4_ros_canopen.driver.convert import Converter
from driver_support import J1, ppm_ready


class Tenfold:
    """A converter: device value = 10 × command, within ±1000."""

    def __init__(self):
        self.calls = 0

    def convert(self, kind, value, env):
        self.calls += 1
        raw = int(round(value * 10))
        if not -1000 <= raw <= 1000:
            return None, "%s %g converts to %d, outside the range" % (kind, value, raw)
        return raw, None


def joint(**changes):
    fields = dict(name="j", error=None, ready=True, halted=False, state=State.OPERATION_ENABLED,
                  homing=False, active_mode=1)  # profile position: position commands
    fields.update(changes)
    return SimpleNamespace(**fields)


LIMITS = JointLimits(lower=-50.0, upper=50.0)


def test_a_command_within_the_limits_is_converted():
    assert check_command(joint(), "position", 4.2, LIMITS, Tenfold(), {}) == Checked("position", 4.2, 42, False)


def test_a_command_beyond_the_limits_is_saturated_then_converted():
    converter = Tenfold()
    assert check_command(joint(), "position", 80.0, LIMITS, converter, {}) == Checked("position", 50.0, 500, True)
    assert converter.calls == 1


@pytest.mark.parametrize("changes, kind, value, reason", [
    ({}, "torque", 1.0, "unknown command kind 'torque' (position, velocity, effort)"),
    ({}, "position", "1", "command must be a number"),
    ({}, "position", True, "command must be a number"),
    ({}, "position", math.nan, "position command nan refused: not a finite number"),
    ({}, "position", math.inf, "position command inf refused: not a finite number"),
    ({}, "position", 10 ** 400, "position command refused: not a finite number"),
    ({"error": "fault"}, "position", 1.0, "j is in error (fault): call recover"),
    ({"ready": False}, "position", 1.0, "j is not initialized: call init"),
    ({"halted": True}, "position", 1.0, "j is halted: call recover before sending commands"),
    ({"state": State.SWITCHED_ON}, "position", 1.0, "j is not operation enabled (state switched_on)"),
    ({"homing": True}, "position", 1.0, "j is homing"),
    ({"active_mode": None}, "position", 1.0, "j has no mode for commands yet (start a controller)"),
    ({}, "velocity", 1.0, "j is in mode profile_position, which takes position commands, not velocity"),
])
def test_refusals_give_the_reason_and_convert_nothing(changes, kind, value, reason):
    converter = Tenfold()
    assert check_command(joint(**changes), kind, value, LIMITS, converter, {}) == reason
    assert converter.calls == 0


def test_a_device_value_out_of_range_is_refused():
    limits = JointLimits()
    assert check_command(joint(), "position", 200.0, limits, Tenfold(), {}) == \
        "position 200 converts to 2000, outside the range"


def test_a_command_from_a_caller_is_converted_once_on_its_way_to_the_drive(driver_rig, monkeypatch):
    rig = driver_rig
    d = ppm_ready(rig)
    calls = []
    convert = Converter.convert

    def counted(self, kind, value, env):
        calls.append(value)
        return convert(self, kind, value, env)
    monkeypatch.setattr(Converter, "convert", counted)
    assert d.set_command(J1, "position", 1234.0).success
    assert rig.until(lambda: rig.read(0x607A) == 1234)
    assert calls == [1234.0]


def test_joint_states_are_stamped_with_when_their_tpdos_arrived(real_driver_rig):
    """The joints' readings carry the wall-clock time their newest TPDO
    reached the host, not the time they are read: a drive that falls
    silent leaves the stamp at its last frame."""
    from maxon_epos4_ros_canopen.driver import joint_states_stamp
    rig = real_driver_rig
    d = ppm_ready(rig)
    frozen, thaw = threading.Event(), threading.Event()
    threading.Thread(target=lambda: rig.sim.call(lambda: (frozen.set(), thaw.wait(10.0)), timeout=20.0),
                     daemon=True).start()
    try:
        assert frozen.wait(5.0)
        cycles = d.cycles
        assert rig.until(lambda: d.cycles > cycles + 30)  # 0.3 s of cycles without a TPDO
        stamp = d.joints[J1].stamp
        frames = [m for m in rig._collect() if m.arbitration_id in (0x181, 0x281, 0x381, 0x481)]  # TPDOs 1-4
        assert frames, "the drive sent no TPDO"
        # the sniffer's stamp of the drive's last TPDO is when it went on the bus
        assert stamp == pytest.approx(frames[-1].timestamp, abs=0.005)
        assert time.time() - stamp > 0.25
        assert joint_states_stamp(d.joints) == stamp
    finally:
        thaw.set()
