"""Object strings and object values as ros_canopen users write them.

Object strings name an entry of a CANopen object dictionary the way
ros_canopen's services, ``dcf_overlay`` keys and ``publish`` lists do:
``6081``, ``0x6081``, ``6099sub02``, ``6099sub2`` (index and sub-index are
hexadecimal, as in ros_canopen). Values travel as strings and are encoded
and decoded by the data type the object dictionary gives the object.

canopen's ODVariable packs values into bytes; what it does not do is read a
human's string ("0x7F0064", "-3", "true") with range checks and clear
errors, which is what this module adds.
"""
from __future__ import annotations

import functools
import math
import os
import re
from dataclasses import dataclass
from typing import Tuple, Union

import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable, ObjectDictionary
from canopen.objectdictionary import datatypes as dt

__all__ = [
    "ObjectKey",
    "ObjectStringError",
    "ObjectValueError",
    "parse_object_key",
    "parse_publish_spec",
    "strip_yaml_tag",
    "find_variable",
    "load_dictionary",
    "encode_value",
    "decode_value",
    "is_readable",
    "is_writable",
]

Value = Union[int, float, bool, str, bytes]

# How many parsed files (one per file and node-ID) load_dictionary keeps: a
# simulator and a driver of 127 drives each, about 160 kB apiece for an EPOS4 DCF.
DICTIONARY_CACHE = 256


def load_dictionary(path: str, node_id: int) -> ObjectDictionary:
    """canopen.import_od of a DCF/EDS for ``node_id`` ($NODEID resolved),
    parsed once per process while the file stays as it is (same path,
    modification time and size): a simulator and a driver in one process,
    and every test of a suite, read the same files again and again, and
    parsing one takes tens of milliseconds. The dictionary is shared:
    callers only read it (the driver's and the simulator's nodes of one
    file already share one)."""
    st = os.stat(path)
    return _parsed(path, st.st_mtime_ns, st.st_size, node_id)


@functools.lru_cache(maxsize=DICTIONARY_CACHE)
def _parsed(path: str, mtime_ns: int, size: int, node_id: int) -> ObjectDictionary:
    return canopen.import_od(path, node_id)


class ObjectStringError(ValueError):
    """An object string that does not name an object (or not in this dictionary)."""


class ObjectValueError(ValueError):
    """A value that does not fit the object's data type, range or access."""


@dataclass(frozen=True, order=True)
class ObjectKey:
    index: int
    subindex: int = 0

    def __str__(self) -> str:
        if self.subindex:
            return "%04Xsub%02X" % (self.index, self.subindex)
        return "%04X" % self.index


_KEY_RE = re.compile(
    r"^(?:0x)?([0-9a-f]{1,4})(?:sub(?:0x)?([0-9a-f]{1,2}))?$", re.IGNORECASE)
_YAML_STR_TAG = "!!str"

# Sizes in bits of the integer types canopen knows.
_INT_BITS = {
    dt.INTEGER8: 8, dt.INTEGER16: 16, dt.INTEGER24: 24, dt.INTEGER32: 32,
    dt.INTEGER40: 40, dt.INTEGER48: 48, dt.INTEGER56: 56, dt.INTEGER64: 64,
    dt.UNSIGNED8: 8, dt.UNSIGNED16: 16, dt.UNSIGNED24: 24, dt.UNSIGNED32: 32,
    dt.UNSIGNED40: 40, dt.UNSIGNED48: 48, dt.UNSIGNED56: 56, dt.UNSIGNED64: 64,
}


def strip_yaml_tag(text: str) -> str:
    """Remove a leading ``!!str`` tag.

    ``rosservice call ... '!!str 6081'`` normally reaches the node as
    ``6081`` because YAML consumes the tag; a client that passes the text on
    unparsed sends the tag itself, which means the same thing.
    """
    text = text.strip()
    if text.startswith(_YAML_STR_TAG):
        text = text[len(_YAML_STR_TAG):].strip()
    return text


def parse_object_key(text: str) -> ObjectKey:
    """``6081`` / ``0x6081`` / ``6099sub02`` / ``6099sub2`` -> ObjectKey."""
    if not isinstance(text, str):
        # YAML turns an unquoted 6081 into the integer 6081; ros_canopen reads
        # object ids as hex text, so the digits are what the user meant.
        if isinstance(text, int) and not isinstance(text, bool):
            text = str(text)
        else:
            raise ObjectStringError("object must be a string like '6081' or '6099sub02', got %r" % (text,))
    cleaned = strip_yaml_tag(text)
    m = _KEY_RE.match(cleaned)
    if not m:
        raise ObjectStringError(
            "bad object string %r: expected a hex index like '6081', '0x6081', "
            "'6099sub02' or '6099sub2'" % (text,))
    return ObjectKey(int(m.group(1), 16), int(m.group(2), 16) if m.group(2) else 0)


def parse_publish_spec(text: str) -> Tuple[ObjectKey, bool]:
    """A ros layer ``publish`` entry: ``"6041"`` or ``"1003sub0!"``.

    The trailing ``!`` asks for the object to be read from the device (SDO)
    every time it is published instead of using the cached value.
    """
    if not isinstance(text, str):
        return parse_object_key(text), False
    cleaned = text.strip()
    force = cleaned.endswith("!")
    if force:
        cleaned = cleaned[:-1]
    return parse_object_key(cleaned), force


def find_variable(od: ObjectDictionary, key: ObjectKey) -> ODVariable:
    """The ODVariable for key, or ObjectStringError naming what is missing."""
    try:
        obj = od[key.index]
    except KeyError:
        raise ObjectStringError("object 0x%04X is not in the object dictionary" % key.index) from None
    if isinstance(obj, ODVariable):
        if key.subindex != 0:
            raise ObjectStringError(
                "object 0x%04X has no sub-index %d (it is a single variable)" % (key.index, key.subindex))
        return obj
    if isinstance(obj, (ODRecord, ODArray)):
        # canopen makes up any sub-index of an ODArray on access; only the
        # ones the file defines (or lies below the highest defined) exist.
        subs = obj.subindices
        if key.subindex in subs or (isinstance(obj, ODArray) and subs and 0 < key.subindex <= max(subs)):
            return obj[key.subindex]
        raise ObjectStringError("object 0x%04X has no sub-index %d" % (key.index, key.subindex))
    raise ObjectStringError("object 0x%04X is not a variable" % key.index)


def is_readable(var: ODVariable) -> bool:
    return "r" in var.access_type or var.access_type == "const"


def is_writable(var: ODVariable) -> bool:
    return "w" in var.access_type


def _int_range(var: ODVariable) -> Tuple[int, int]:
    bits = _INT_BITS[var.data_type]
    if var.data_type in dt.SIGNED_TYPES:
        lo, hi = -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    else:
        lo, hi = 0, (1 << bits) - 1
    # LowLimit/HighLimit of the EDS narrow the type's range.
    if var.min is not None:
        lo = max(lo, var.min)
    if var.max is not None:
        hi = min(hi, var.max)
    return lo, hi


# An integer as a user writes one: decimal or 0x hex, an optional sign, ASCII
# digits only. Nothing passes through float (which would take 9.99...9e2 for
# 1000), and none of int()'s extras: no "1_000", no digits of other scripts.
_INTEGER = re.compile(r"([+-]?)(?:0[xX]([0-9a-fA-F]+)|([0-9]+))")


def _parse_int(text: str) -> int:
    m = _INTEGER.fullmatch(text.strip(" \t"))
    if m is None:
        raise ObjectValueError("%r is not an integer (decimal or 0x hex)" % text)
    sign, hex_digits, dec_digits = m.groups()
    value = int(hex_digits, 16) if hex_digits is not None else int(dec_digits, 10)
    return -value if sign == "-" else value


def _parse_hex_bytes(text: str) -> bytes:
    t = text.strip()
    if t[:2].lower() == "0x":
        t = t[2:]
    t = t.replace(" ", "").replace(":", "")
    if len(t) % 2 or not re.fullmatch(r"[0-9a-fA-F]*", t):
        raise ObjectValueError("%r is not a hex byte string like '0a1b2c'" % text)
    return bytes.fromhex(t)


def encode_value(var: ODVariable, text: str) -> Value:
    """Parse text into the Python value canopen's ``.raw`` takes for var.

    Raises ObjectValueError with the accepted range on anything that does not
    fit; never truncates or wraps a number silently.
    """
    if not isinstance(text, str):
        text = str(text)
    text = strip_yaml_tag(text)
    dtype = var.data_type
    name = "0x%04X sub %d" % (var.index, var.subindex)
    if dtype == dt.BOOLEAN:
        low = text.lower()
        if low in ("1", "true", "yes", "on"):
            return True
        if low in ("0", "false", "no", "off"):
            return False
        raise ObjectValueError("%r is not a boolean (true/false/1/0) for %s" % (text, name))
    if dtype in _INT_BITS:
        value = _parse_int(text)
        lo, hi = _int_range(var)
        if not lo <= value <= hi:
            raise ObjectValueError("%s out of range for %s: allowed %d..%d" % (text, name, lo, hi))
        return value
    if dtype in dt.FLOAT_TYPES:
        try:
            value = float(text)
        except ValueError:
            raise ObjectValueError("%r is not a number for %s" % (text, name)) from None
        if not math.isfinite(value):
            raise ObjectValueError("%r is not a finite number for %s" % (text, name))
        if dtype == dt.REAL32 and abs(value) > 3.4028234663852886e38:
            raise ObjectValueError("%r out of range for REAL32 %s" % (text, name))
        if var.min is not None and value < var.min or var.max is not None and value > var.max:
            raise ObjectValueError("%s out of range for %s: allowed %s..%s" % (text, name, var.min, var.max))
        return value
    if dtype == dt.VISIBLE_STRING:
        try:
            text.encode("ascii")
        except UnicodeEncodeError:
            raise ObjectValueError("VISIBLE_STRING %s takes ASCII text only" % name) from None
        return text
    if dtype == dt.UNICODE_STRING:
        return text
    if dtype in (dt.OCTET_STRING, dt.DOMAIN):
        return _parse_hex_bytes(text)
    raise ObjectValueError("data type 0x%X of %s is not supported" % (dtype, name))


def decode_value(var: ODVariable, value: Value) -> str:
    """The string a service answer carries for a value of var."""
    if var.data_type == dt.BOOLEAN:
        return "1" if value else "0"
    if isinstance(value, (bytes, bytearray)):
        if var.data_type in (dt.VISIBLE_STRING, dt.UNICODE_STRING):
            return bytes(value).decode("ascii", "replace")
        return bytes(value).hex()
    if isinstance(value, float):
        return repr(value)
    return str(value)
