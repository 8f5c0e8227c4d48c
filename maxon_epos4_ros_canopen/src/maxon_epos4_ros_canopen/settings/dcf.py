"""The settings file of epos4_settings: a DCF/EDS read with canopen, which
of its objects are settings, how values read and are written as text, and
the DCF a backup writes."""
from __future__ import annotations

import configparser
import io
import os
from dataclasses import dataclass
from typing import Dict, Iterator, List, Optional, Tuple

import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable, ObjectDictionary
from canopen.objectdictionary import datatypes as dt
from canopen.sdo.exceptions import SdoAbortedError

from ..objects import is_readable, is_writable

Key = Tuple[int, int]
PROG = "epos4_settings"

SAVE_SIGNATURE = 0x65766173  # "save" (CiA 301 0x1010)
STORE_PARAMETERS = (0x1010, 1)
IDENTITY_VENDOR, IDENTITY_PRODUCT, IDENTITY_REVISION = (0x1018, 1), (0x1018, 2), (0x1018, 3)
STATUSWORD = (0x6041, 0)
COB_INVALID = 0x80000000
RPDO_COMM, TPDO_COMM, PDO_COUNT = 0x1400, 0x1800, 4
MAPPING_OFFSET = 0x200  # 0x1400 -> 0x1600, 0x1800 -> 0x1A00

# CiA 306 ObjFlags: bit 0 "refuse write on download", bit 1 "refuse read on
# scan". EPOS Studio's DCF exports mark the drive's commands, live values
# and internal objects with them.
REFUSE_WRITE, REFUSE_READ = 0x1, 0x2

# Writable objects that are commands or set-points, not settings: never
# compared, never written back, whatever the file says.
COMMANDS: Dict[int, str] = {
    0x1003: "error history: writing clears it",
    0x1010: "store parameters: a command, written only by restore --store",
    0x1011: "restore default parameters: a command that would erase the settings at the next reset",
    0x1F51: "program control: starts and stops the drive's firmware program",
    0x6040: "controlword: a device-control command (it switches the power stage on)",
    0x6071: "target torque: a set-point",
    0x607A: "target position: a set-point",
    0x60B0: "position offset: a set-point",
    0x60B1: "velocity offset: a set-point",
    0x60B2: "torque offset: a set-point",
    0x60FE: "physical outputs: would switch the drive's outputs (a brake, say)",
    0x60FF: "target velocity: a set-point",
}
# Settings diff compares and restore leaves alone: written back, they would
# take the drive off the bus it is being configured over (after a store
# and a reset).
BUS_IDENTITY: Dict[int, str] = {
    0x2000: "node-ID: after a store and a reset the drive would answer on another node-ID",
    0x2001: "CAN bit rate: after a store and a reset the drive would leave this bus",
}


class SettingsError(Exception):
    """The tool cannot go on; the message says why and what to do."""


# ----------------------------------------------------------------- the file
@dataclass
class SettingsFile:
    """A DCF/EDS read for one node: canopen's dictionary plus what canopen's
    import leaves out (the ObjFlags and the file's own node-ID)."""

    path: str
    od: ObjectDictionary
    flags: Dict[Key, int]
    node_id: Optional[int]  # [DeviceComissioning] NodeID, when the file has one

    def value(self, key: Key) -> Optional[object]:
        var = find(self.od, key)
        return None if var is None else var.value

    def product_code(self) -> Optional[int]:
        value = self.value(IDENTITY_PRODUCT)
        if isinstance(value, int):
            return value
        return self.od.device_information.product_number

    def vendor_id(self) -> Optional[int]:
        value = self.value(IDENTITY_VENDOR)
        if isinstance(value, int):
            return value
        return self.od.device_information.vendor_number


def load_file(path: str, node_id: int) -> SettingsFile:
    """Read ``path`` for ``node_id`` ($NODEID resolved); SettingsError when
    it is no DCF/EDS canopen can read."""
    if not os.path.isfile(path):
        raise SettingsError("no such file: %s" % path)
    try:
        od = canopen.import_od(path, node_id)
        flags, file_node = _extras(path)
    except Exception as exc:  # configparser, ValueError, KeyError: the file is not a DCF/EDS
        raise SettingsError("%s: not a DCF/EDS file canopen can read (%s)" % (path, exc)) from None
    return SettingsFile(path, od, flags, file_node)


def _parser() -> configparser.RawConfigParser:
    # as canopen's import reads the file: ';' starts a comment, keys keep their case
    parser = configparser.RawConfigParser(inline_comment_prefixes=(";",))
    parser.optionxform = str  # type: ignore[assignment]
    return parser


def _section_key(section: str) -> Optional[Key]:
    text = section.lower()
    try:
        if len(text) == 4:
            return int(text, 16), 0
        if len(text) > 7 and text[4:7] == "sub":
            return int(text[:4], 16), int(text[7:], 16)
    except ValueError:
        pass
    return None


def _extras(path: str) -> Tuple[Dict[Key, int], Optional[int]]:
    """ObjFlags per object and [DeviceComissioning] NodeID: canopen's
    import_od reads neither."""
    parser = _parser()
    with open(path) as fp:
        parser.read_file(fp)
    flags: Dict[Key, int] = {}
    for section in parser.sections():
        key = _section_key(section)
        if key is not None and parser.has_option(section, "ObjFlags"):
            try:
                flags[key] = int(parser.get(section, "ObjFlags"), 0)
            except ValueError:
                pass
    node_id = None
    if parser.has_option("DeviceComissioning", "NodeID"):
        try:
            node_id = int(parser.get("DeviceComissioning", "NodeID"), 0) or None
        except ValueError:
            pass
    return flags, node_id


def find(od: ObjectDictionary, key: Key) -> Optional[ODVariable]:
    obj = od.get(key[0])
    if isinstance(obj, ODVariable):
        return obj if key[1] == 0 else None
    if isinstance(obj, (ODRecord, ODArray)):
        return obj.subindices.get(key[1])
    return None


def variables(od: ObjectDictionary) -> Iterator[ODVariable]:
    """Every variable of ``od`` in index, sub-index order."""
    for index in sorted(od.indices):
        obj = od[index]
        if isinstance(obj, ODVariable):
            yield obj
        elif isinstance(obj, (ODRecord, ODArray)):
            for sub in sorted(obj.subindices):
                yield obj.subindices[sub]


def key_of(var: ODVariable) -> Key:
    return var.index, var.subindex


def backup_skip(var: ODVariable, flags: Dict[Key, int]) -> Optional[str]:
    """Why backup does not read ``var`` (None: it reads it)."""
    if not is_readable(var):
        return "write-only"
    if flags.get(key_of(var), 0) & REFUSE_READ:
        return "the file marks it not to be read (ObjFlags bit 1: a live buffer or an internal value)"
    return None


def setting_skip(var: ODVariable, flags: Dict[Key, int]) -> Optional[str]:
    """Why ``var`` is not a setting diff compares (None: it is one)."""
    reason = backup_skip(var, flags)
    if reason is not None:
        return reason
    if not is_writable(var):
        return "read-only"
    if var.index in COMMANDS:
        return COMMANDS[var.index]
    if flags.get(key_of(var), 0) & REFUSE_WRITE:
        return "the file marks it not to be written (ObjFlags bit 0: a command or a live value)"
    return None


def restore_skip(var: ODVariable, flags: Dict[Key, int]) -> Optional[str]:
    """Why restore does not write ``var`` (None: it writes it when it differs)."""
    return setting_skip(var, flags) or BUS_IDENTITY.get(var.index)


def settings(file: SettingsFile) -> List[ODVariable]:
    """The file's settings that carry a value, in index order."""
    return [v for v in variables(file.od) if setting_skip(v, file.flags) is None and v.value is not None]


# ----------------------------------------------------------------- values
def _width(var: ODVariable) -> int:
    try:
        return len(var) // 4  # hex digits
    except Exception:  # a type canopen gives no length
        return 8


def dcf_text(var: ODVariable, value: object) -> str:
    """A value as a DCF ParameterValue. canopen's own export writes signed
    values as "0x-3", which its import cannot read back: the text is made
    here and handed to the export."""
    if var.data_type == dt.BOOLEAN:
        return "1" if value else "0"
    if var.data_type in dt.SIGNED_TYPES:
        return str(int(value))  # type: ignore[call-overload]
    if var.data_type in dt.INTEGER_TYPES:
        return "0x%0*X" % (_width(var), int(value))  # type: ignore[call-overload]
    if var.data_type in dt.FLOAT_TYPES:
        return repr(float(value))  # type: ignore[arg-type]
    if isinstance(value, (bytes, bytearray)):
        return bytes(value).hex()
    return str(value)


def shown(var: ODVariable, value: object) -> str:
    """A value for a person: decimal, with hex beside wide unsigned values."""
    if var.data_type == dt.BOOLEAN:
        return "true" if value else "false"
    if var.data_type in dt.INTEGER_TYPES and var.data_type not in dt.SIGNED_TYPES and isinstance(value, int):
        return "%d (0x%0*X)" % (value, _width(var), value) if value > 9 and _width(var) >= 8 else str(value)
    if isinstance(value, (bytes, bytearray)):
        return bytes(value).hex() or "(empty)"
    if isinstance(value, str):
        return repr(value)
    return str(value)


def decode(var: ODVariable, data: bytes) -> object:
    if var.data_type == dt.BOOLEAN:
        return bool(data[:1] != b"\x00")
    try:
        return var.decode_raw(data)
    except Exception:  # a length the type does not allow: show the bytes
        return bytes(data)


def encode(var: ODVariable, value: object) -> bytes:
    if var.data_type == dt.BOOLEAN:
        return b"\x01" if value else b"\x00"
    return var.encode_raw(value)


def where(var: ODVariable) -> str:
    return "0x%04X sub %d %s" % (var.index, var.subindex, var.name)


def abort_text(exc: SdoAbortedError) -> str:
    return "abort 0x%08X %s" % (exc.code, SdoAbortedError.CODES.get(exc.code, "(code not in CiA 301)"))



def export_dcf(file: SettingsFile, description: str) -> str:
    """canopen's DCF export of ``file.od``, with the ObjFlags of the file
    put back and the file's origin named (canopen's export writes neither)."""
    text = io.StringIO()
    canopen.export_od(file.od, text, "dcf")
    parser = _parser()
    parser.read_string(text.getvalue())
    for section in parser.sections():
        key = _section_key(section)
        if key is not None and file.flags.get(key):
            parser.set(section, "ObjFlags", str(file.flags[key]))
    if not parser.has_section("FileInfo"):
        parser.add_section("FileInfo")
    parser.set("FileInfo", "Description", description)
    parser.set("FileInfo", "CreatedBy", PROG)
    out = io.StringIO()
    parser.write(out, space_around_delimiters=False)
    return out.getvalue()
