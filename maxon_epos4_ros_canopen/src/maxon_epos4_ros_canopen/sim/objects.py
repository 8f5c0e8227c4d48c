"""Object dictionary values of one simulated node, typed by a DCF/EDS.

canopen.import_od parses the file (ParameterValue, $NODEID, BOOLEAN...;
once per file and node-ID, objects.load_dictionary);
this module keeps the live values and enforces what an SDO server must check
(existence, access, length, value range).  canopen's LocalNode does not check
length and range and has no hook for the drive's own write rules, hence this
small store.
"""
from __future__ import annotations

from typing import Any, Callable, Dict, Iterator, Optional, Tuple

import canopen
from canopen.objectdictionary import ODVariable

from ..objects import load_dictionary

Key = Tuple[int, int]

# SDO abort codes (CiA 301 table "SDO abort codes").
ABORT_TOGGLE = 0x05030000
ABORT_TIMEOUT = 0x05040000
ABORT_COMMAND = 0x05040001
ABORT_UNSUPPORTED_ACCESS = 0x06010000
ABORT_WRITE_ONLY = 0x06010001
ABORT_READ_ONLY = 0x06010002
ABORT_NO_OBJECT = 0x06020000
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_LENGTH = 0x06040042
ABORT_PARAMETER_INCOMPATIBLE = 0x06040043
ABORT_LENGTH = 0x06070010
ABORT_NO_SUBINDEX = 0x06090011
ABORT_VALUE_RANGE = 0x06090030
ABORT_VALUE_HIGH = 0x06090031
ABORT_VALUE_LOW = 0x06090032
ABORT_GENERAL = 0x08000000
ABORT_STORE = 0x08000020
ABORT_DEVICE_STATE = 0x08000022


class SdoAbort(Exception):
    """A request the node refuses; ``code`` goes into the abort frame."""

    def __init__(self, code: int, reason: str = ""):
        super().__init__("SDO abort 0x%08X %s" % (code, reason))
        self.code = code


def _initial_value(var: ODVariable) -> Any:
    for candidate in (var.value, var.default):
        if candidate is not None:
            return candidate
    if var.data_type in var.STRUCT_TYPES:
        return 0
    return "" if var.data_type == 0x9 else b""


def _variables(od: canopen.ObjectDictionary) -> Iterator[Tuple[Key, ODVariable, bool]]:
    """(key, variable, is a plain VAR without sub-indices) of every object."""
    for index in od.indices:
        obj = od[index]
        if isinstance(obj, ODVariable):
            yield (index, 0), obj, True
        else:
            for sub, var in obj.subindices.items():
                yield (index, sub), var, False


def initial_values(od: canopen.ObjectDictionary) -> Dict[Key, Any]:
    """Every object's power-on value (ParameterValue, else DefaultValue),
    as the file gives it for the node-ID ``od`` was read for."""
    return {key: _initial_value(var) for key, var, _ in _variables(od)}


class ObjectStore:
    """Live values of an object dictionary.

    ``od`` gives the objects' types and limits; it may be shared by the
    nodes of one file, and ``initial`` then holds this node's power-on
    values (those with $NODEID differ between nodes).
    ``write_hook(key, value)`` runs before an SDO/PDO write is stored and may
    raise SdoAbort; ``get``/``set`` are the drive's own unchecked access.
    """

    def __init__(self, od: canopen.ObjectDictionary, initial: Optional[Dict[Key, Any]] = None):
        self.od = od
        self.vars: Dict[Key, ODVariable] = {}
        self.plain: Dict[int, bool] = {}  # index -> is a plain VAR (no sub-indices)
        for key, var, plain in _variables(od):
            self.vars[key] = var
            self.plain[key[0]] = plain
        self.initial = initial if initial is not None else initial_values(od)
        self.values: Dict[Key, Any] = {}
        self.write_hook: Optional[Callable[[Key, Any], None]] = None
        self.after_write: Optional[Callable[[Key, Any], None]] = None
        self.power_on()

    def power_on(self, lo: int = 0x0000, hi: int = 0xFFFF) -> None:
        """Power-on values (ParameterValue, else DefaultValue) for lo..hi."""
        for key in self.vars:
            if lo <= key[0] <= hi:
                self.values[key] = self.initial[key]

    def __contains__(self, key: Key) -> bool:
        return key in self.values

    def get(self, index: int, sub: int = 0, default: Any = 0) -> Any:
        return self.values.get((index, sub), default)

    def set(self, index: int, sub: int, value: Any) -> None:
        """Drive-internal write (no checks); ignored for absent objects."""
        key = (index, sub)
        if key in self.values:
            self.values[key] = value

    def variable(self, index: int, sub: int) -> ODVariable:
        var = self.vars.get((index, sub))
        if var is None:
            if index not in self.plain:
                raise SdoAbort(ABORT_NO_OBJECT, "0x%04X" % index)
            raise SdoAbort(ABORT_NO_SUBINDEX, "0x%04X:%d" % (index, sub))
        return var

    def upload(self, index: int, sub: int) -> bytes:
        var = self.variable(index, sub)
        if not var.readable:
            raise SdoAbort(ABORT_WRITE_ONLY)
        return self.encode(var, self.values[(index, sub)])

    @staticmethod
    def encode(var: ODVariable, value: Any) -> bytes:
        if var.data_type == 0x1:  # BOOLEAN: one byte on the wire
            return b"\x01" if value else b"\x00"
        return var.encode_raw(value)

    def download(self, index: int, sub: int, data: bytes, from_sdo: bool = True) -> None:
        var = self.variable(index, sub)
        if from_sdo and not var.writable:
            raise SdoAbort(ABORT_READ_ONLY)
        size = len(var) // 8
        if var.data_type == 0x1:
            size = 1
        if size and len(data) != size:
            raise SdoAbort(ABORT_LENGTH, "%d bytes for a %d-byte object" % (len(data), size))
        if var.data_type == 0x1:
            if data[0] > 1:
                raise SdoAbort(ABORT_VALUE_RANGE)
            value: Any = bool(data[0])
        else:
            value = var.decode_raw(data)
        if var.max is not None and value > var.max:
            raise SdoAbort(ABORT_VALUE_HIGH)
        if var.min is not None and value < var.min:
            raise SdoAbort(ABORT_VALUE_LOW)
        if self.write_hook is not None:
            self.write_hook((index, sub), value)
        self.values[(index, sub)] = value
        if self.after_write is not None:
            self.after_write((index, sub), value)


def load_od(path: str, node_id: int) -> canopen.ObjectDictionary:
    """Read a DCF/EDS for ``node_id`` (resolves $NODEID)."""
    return load_dictionary(path, node_id)
