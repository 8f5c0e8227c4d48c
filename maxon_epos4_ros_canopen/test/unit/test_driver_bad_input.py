"""Bad input to the driver's services is answered with a Result and changes
nothing in the drive (its values read from the simulator)."""
import pytest

from driver_support import J1, ppm_ready


@pytest.fixture
def rig(driver_rig):
    return driver_rig


@pytest.mark.parametrize("text", ["9.9999999999999999e2", "1000.0", "1e3", "1_000",
                                  "\u0661\u0660\u0660\u0660", "\uff11\uff10\uff10\uff10", "0x", "+-1000"])
def test_set_object_takes_an_integer_in_decimal_or_hex_only(rig, text):
    d = ppm_ready(rig)
    before = rig.read(0x6081)
    r = d.set_object(J1, "6081", text)
    assert not r.success and "not an integer (decimal or 0x hex)" in r.message, r.message
    assert rig.read(0x6081) == before
    assert d.set_object(J1, "6081", "0x3E8").success
    assert rig.read(0x6081) == 1000


@pytest.mark.parametrize("obj, text, allowed", [("6081", "4294967296", "1..50000"),   # the DCF's limits
                                                ("6081", "0", "1..50000"),
                                                ("6098", "38", "-4..37"),
                                                ("6098", "-0x81", "-4..37")])
def test_set_object_out_of_range_names_the_range(rig, obj, text, allowed):
    d = ppm_ready(rig)
    before = rig.read(int(obj, 16))
    r = d.set_object(J1, obj, text)
    assert not r.success and "allowed " + allowed in r.message, r.message
    assert rig.read(int(obj, 16)) == before


@pytest.mark.parametrize("args", [(None,), (None, 1), ([J1], None), (J1, None), (5, 1), ([None], 1), ([[J1]], 1), ((), 1)])
def test_switch_mode_answers_bad_arguments(rig, args):
    d = ppm_ready(rig)
    r = d.switch_mode(*args)
    assert not r.success, r.message
    assert rig.read(0x6061) == 1
    assert d.set_command(J1, "position", 10).success
    assert rig.until(lambda: rig.read(0x607A) == 10)
