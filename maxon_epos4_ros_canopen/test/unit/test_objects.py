"""Object strings and values: what set_object/get_object and dcf_overlay accept."""
import os

import pytest
from canopen.objectdictionary import ObjectDictionary, ODRecord, ODVariable
from canopen.objectdictionary import datatypes as dt

from maxon_epos4_ros_canopen.objects import (
    ObjectKey, ObjectStringError, ObjectValueError, decode_value, encode_value,
    find_variable, parse_object_key, parse_publish_spec, strip_yaml_tag)


@pytest.mark.parametrize("text, key", [
    ("6081", ObjectKey(0x6081, 0)),
    ("0x6081", ObjectKey(0x6081, 0)),
    ("0X6081", ObjectKey(0x6081, 0)),
    ("6099sub02", ObjectKey(0x6099, 2)),
    ("6099sub2", ObjectKey(0x6099, 2)),
    ("6099SUB0A", ObjectKey(0x6099, 10)),
    ("1016sub1", ObjectKey(0x1016, 1)),
    ("!!str 6081", ObjectKey(0x6081, 0)),
    (" 60ff ", ObjectKey(0x60FF, 0)),
    (6098, ObjectKey(0x6098, 0)),  # an unquoted YAML key
])
def test_object_strings(text, key):
    assert parse_object_key(text) == key


@pytest.mark.parametrize("text", ["", "sub2", "60811", "6081sub", "6081sub100", "6081.2",
                                  "0x", "g081", "6081 sub2", "-6081", None, 1.5, True])
def test_bad_object_strings(text):
    with pytest.raises(ObjectStringError):
        parse_object_key(text)


def test_object_key_prints_like_ros_canopen():
    assert str(ObjectKey(0x6099, 2)) == "6099sub02"
    assert str(ObjectKey(0x6081)) == "6081"


def test_publish_specs():
    assert parse_publish_spec("1003sub0!") == (ObjectKey(0x1003, 0), True)
    assert parse_publish_spec("1A00") == (ObjectKey(0x1A00, 0), False)
    assert strip_yaml_tag("!!str 1000") == "1000"


def _var(index, sub, dtype, access="rw", lo=None, hi=None):
    v = ODVariable("v", index, sub)
    v.data_type, v.access_type, v.min, v.max = dtype, access, lo, hi
    return v


@pytest.mark.parametrize("dtype, text, value", [
    (dt.UNSIGNED32, "1000", 1000),
    (dt.UNSIGNED32, "0x7F0064", 0x7F0064),
    (dt.UNSIGNED32, "!!str 1000", 1000),
    (dt.UNSIGNED32, "4294967295", 0xFFFFFFFF),
    (dt.INTEGER8, "-3", -3),
    (dt.INTEGER32, "-0x10", -16),
    (dt.INTEGER16, "+12", 12),
    (dt.INTEGER16, " 0X1f ", 31),
    (dt.REAL32, "1.5", 1.5),
    (dt.BOOLEAN, "true", True),
    (dt.BOOLEAN, "0", False),
    (dt.VISIBLE_STRING, "EPOS4", "EPOS4"),
    (dt.DOMAIN, "0a0B", b"\x0a\x0b"),
    (dt.DOMAIN, "0x0a 0b", b"\x0a\x0b"),
])
def test_encode(dtype, text, value):
    assert encode_value(_var(0x2000, 0, dtype), text) == value


@pytest.mark.parametrize("dtype, text, match", [
    (dt.UNSIGNED32, "-1", "out of range"),
    (dt.UNSIGNED32, "4294967296", "out of range"),
    (dt.INTEGER8, "128", "allowed -128..127"),
    (dt.UNSIGNED16, "abc", "not an integer"),
    (dt.UNSIGNED16, "1.5", "not an integer"),
    (dt.UNSIGNED16, "nan", "not an integer"),
    # an integer object takes decimal or 0x hex, nothing that passes through float
    (dt.UNSIGNED16, "12.0", "not an integer"),
    (dt.UNSIGNED16, "9.9999999999999999e2", "not an integer"),
    (dt.UNSIGNED16, "1e3", "not an integer"),
    (dt.UNSIGNED16, "1_000", "not an integer"),
    (dt.UNSIGNED16, "\u0661\u0660\u0660\u0660", "not an integer"),   # Arabic-Indic 1000
    (dt.UNSIGNED16, "\uff11\uff10", "not an integer"),                 # fullwidth 10
    (dt.UNSIGNED16, "0x", "not an integer"),
    (dt.UNSIGNED16, "--1", "not an integer"),
    (dt.UNSIGNED16, "", "not an integer"),
    (dt.UNSIGNED16, "65536", "allowed 0..65535"),
    (dt.INTEGER32, "-2147483649", "allowed -2147483648..2147483647"),
    (dt.REAL32, "inf", "not a finite number"),
    (dt.REAL32, "nan", "not a finite number"),
    (dt.REAL32, "1e39", "out of range"),
    (dt.BOOLEAN, "maybe", "not a boolean"),
    (dt.DOMAIN, "0g", "not a hex byte string"),
    (dt.VISIBLE_STRING, "\u00e9", "ASCII"),
])
def test_encode_refuses(dtype, text, match):
    with pytest.raises(ObjectValueError, match=match):
        encode_value(_var(0x2000, 0, dtype), text)


def test_eds_limits_narrow_the_range():
    v = _var(0x1600, 0, dt.UNSIGNED8, lo=0, hi=12)
    assert encode_value(v, "12") == 12
    with pytest.raises(ObjectValueError, match="allowed 0..12"):
        encode_value(v, "13")


def test_decode():
    assert decode_value(_var(0x2000, 0, dt.INTEGER32), -5) == "-5"
    assert decode_value(_var(0x2000, 0, dt.REAL64), 0.25) == "0.25"
    assert decode_value(_var(0x2000, 0, dt.BOOLEAN), True) == "1"
    assert decode_value(_var(0x2000, 0, dt.DOMAIN), b"\x01\xab") == "01ab"
    assert decode_value(_var(0x2000, 0, dt.VISIBLE_STRING), b"EPOS4") == "EPOS4"


def test_find_variable():
    od = ObjectDictionary()
    od.add_object(_var(0x6081, 0, dt.UNSIGNED32))
    rec = ODRecord("rec", 0x6099)
    rec.add_member(_var(0x6099, 0, dt.UNSIGNED8, "ro"))
    rec.add_member(_var(0x6099, 2, dt.UNSIGNED32))
    od.add_object(rec)
    assert find_variable(od, ObjectKey(0x6099, 2)).subindex == 2
    assert find_variable(od, ObjectKey(0x6081)).index == 0x6081
    with pytest.raises(ObjectStringError, match="0x1234 is not in"):
        find_variable(od, ObjectKey(0x1234))
    with pytest.raises(ObjectStringError, match="no sub-index 5"):
        find_variable(od, ObjectKey(0x6099, 5))
    with pytest.raises(ObjectStringError, match="single variable"):
        find_variable(od, ObjectKey(0x6081, 1))


REPO = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", ".."))
VENDOR = os.path.join(os.path.dirname(REPO), "shared", "vendor_dcf")


@pytest.mark.skipif(not os.path.isdir(VENDOR), reason="../shared/vendor_dcf (maxon's DCFs, test data) is not present")
def test_vendor_dcf_objects_round_trip():
    import canopen
    od = canopen.import_od(os.path.join(VENDOR, "epos4_50_15_can_ec90flat_gp52c_mile800_node1_unedited_boolean.dcf"), 1)
    boolean = find_variable(od, parse_object_key("2200sub2"))
    assert boolean.data_type == dt.BOOLEAN
    assert encode_value(boolean, "true") is True
    homing = find_variable(od, parse_object_key("6098"))
    assert encode_value(homing, "-3") == -3
    with pytest.raises(ObjectValueError):
        encode_value(homing, "200")
    speed = find_variable(od, parse_object_key("6099sub02"))
    assert decode_value(speed, encode_value(speed, "10")) == "10"
