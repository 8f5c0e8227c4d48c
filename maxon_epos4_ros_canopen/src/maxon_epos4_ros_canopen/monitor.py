"""A CANopen bus monitor for the field: every frame as the objects and states
it carries, instead of candump's hex.

``Decoder.decode(frame)`` turns one python-can message into a ``Decoded``
(node, kind, the objects it touches, a text); it never raises, whatever the
frame holds. Object names and data types come from the nodes' DCFs (or the
EPOS4 dictionary of this package when none is given); PDO contents from the
DCFs' mapping or from a mapping read from the drive (``read_pdo_mapping``).
``Filter`` keeps the frames of some nodes or objects; ``format_line`` is a
decoded frame as the monitor prints it. The command (bus load, candump's log
format, the live session) is in monitor_cli.py.
"""
from __future__ import annotations

import re
import struct
from dataclasses import dataclass, field
from typing import Callable, Dict, Iterable, List, Optional, Sequence, Set, Tuple

import can
from canopen.objectdictionary.datatypes import DATA_TYPES
from canopen.objectdictionary import ODArray, ODRecord, ODVariable, ObjectDictionary
from canopen.sdo.exceptions import SdoAbortedError

from .epos4_errors import describe as describe_error

NMT_COMMANDS = {0x01: "start", 0x02: "stop", 0x80: "enter pre-operational", 0x81: "reset node",
                0x82: "reset communication"}
NMT_STATES = {0x00: "boot-up", 0x04: "stopped", 0x05: "operational", 0x7F: "pre-operational"}
ERROR_REGISTER_BITS = ((0x01, "generic"), (0x02, "current"), (0x04, "voltage"), (0x08, "temperature"),
                       (0x10, "communication"), (0x20, "device profile"), (0x40, "reserved"),
                       (0x80, "manufacturer (EPOS4: motion)"))
# function code (COB-ID >> 7) of the predefined connection set -> (kind, PDO number)
_PDO_FUNCTIONS = {0x3: ("TPDO", 1), 0x4: ("RPDO", 1), 0x5: ("TPDO", 2), 0x6: ("RPDO", 2),
                  0x7: ("TPDO", 3), 0x8: ("RPDO", 3), 0x9: ("TPDO", 4), 0xA: ("RPDO", 4)}
_ABORT_CODES = dict(SdoAbortedError.CODES)

ObjectRef = Tuple[int, int]  # (index, subindex)


@dataclass
class Decoded:
    node: Optional[int]           # None for bus-wide frames (SYNC, TIME, NMT to all)
    kind: str                     # NMT, SYNC, TIME, EMCY, TPDO1..4, RPDO1..4, SDO, HEARTBEAT, LSS, ...
    text: str
    objects: Set[ObjectRef] = field(default_factory=set)


@dataclass
class PdoEntry:
    index: int
    subindex: int
    bits: int


def error_register_text(register: int) -> str:
    names = [n for bit, n in ERROR_REGISTER_BITS if register & bit]
    return "0x%02X (%s)" % (register, ", ".join(names) if names else "no error")


def parse_object(text: str) -> ObjectRef:
    """``6041``, ``0x6041``, ``1A00sub1``, ``6099sub02`` -> (index, subindex or -1 for any)."""
    m = re.fullmatch(r"(?:0x)?([0-9A-Fa-f]{1,4})(?:sub(?:0x)?([0-9A-Fa-f]{1,2}))?", text.strip())
    if not m:
        raise ValueError("object %r: expected INDEX or INDEXsubSUB in hexadecimal (6041, 1A00sub1)" % text)
    return int(m.group(1), 16), int(m.group(2), 16) if m.group(2) else -1


class Decoder:
    """Decodes frames of one bus. ``dictionaries`` maps node-ID -> the node's
    object dictionary (from its DCF); ``default`` serves names for other nodes."""

    def __init__(self, dictionaries: Optional[Dict[int, ObjectDictionary]] = None,
                 default: Optional[ObjectDictionary] = None) -> None:
        self.dictionaries: Dict[int, ObjectDictionary] = dict(dictionaries or {})
        self.default = default
        # (COB-ID) -> (node, kind, entries); from the DCFs, replaced by what is read from a drive
        self.pdo_maps: Dict[int, Tuple[int, str, List[PdoEntry]]] = {}
        self._segments: Dict[Tuple[int, str], Tuple[ObjectRef, bytearray]] = {}
        for node_id, od in self.dictionaries.items():
            for kind, maps in (("RPDO", pdo_maps_from_od(od, node_id, receive=True)),
                               ("TPDO", pdo_maps_from_od(od, node_id, receive=False))):
                for number, (cob_id, entries) in maps.items():
                    self.pdo_maps[cob_id] = (node_id, "%s%d" % (kind, number), entries)

    # --- names and values -------------------------------------------------
    def _od(self, node: Optional[int]) -> Optional[ObjectDictionary]:
        if node is not None and node in self.dictionaries:
            return self.dictionaries[node]
        return self.default

    def variable(self, node: Optional[int], index: int, subindex: int) -> Optional[ODVariable]:
        od = self._od(node)
        if od is None:
            return None
        try:
            obj = od[index]
            if isinstance(obj, (ODRecord, ODArray)):
                return obj[subindex]
            return obj if subindex == 0 else None
        except (KeyError, IndexError, TypeError):
            return None

    def object_name(self, node: Optional[int], index: int, subindex: int) -> str:
        od = self._od(node)
        ref = "%04X" % index if subindex == 0 else "%04Xsub%d" % (index, subindex)
        var = self.variable(node, index, subindex)
        if var is None:
            return ref
        parent = None
        try:
            parent = od[index] if od is not None else None
        except KeyError:
            pass
        if isinstance(parent, (ODRecord, ODArray)):
            return "%s: %s (%s)" % (parent.name, var.name, ref)
        return "%s (%s)" % (var.name, ref)

    def value_text(self, node: Optional[int], index: int, subindex: int, data: bytes) -> str:
        var = self.variable(node, index, subindex)
        if var is not None:
            size = 0  # bits of a numeric type; strings and domains take all bytes
            if var.data_type not in DATA_TYPES:
                try:
                    size = len(var)
                except (TypeError, ValueError):
                    pass
            raw = data[:size // 8] if size and len(data) >= size // 8 else data
            try:
                value = var.decode_raw(raw)
                if isinstance(value, int):
                    shown = value & ((1 << size) - 1) if value < 0 and size else value
                    return "%d (0x%X)" % (value, shown)
                if isinstance(value, float):
                    return "%g" % value
                if isinstance(value, (bytes, bytearray)):
                    return _hex(value)
                return repr(value)
            except Exception:  # a value that does not fit the type: show the bytes
                pass
        return _hex(data)

    # --- frames -----------------------------------------------------------
    def decode(self, frame: can.Message) -> Decoded:
        try:
            return self._decode(frame)
        except Exception as exc:  # never let one odd frame stop the monitor
            return Decoded(None, "MALFORMED", "cannot decode (%s: %s)" % (type(exc).__name__, exc))

    def _decode(self, frame: can.Message) -> Decoded:
        data = bytes(frame.data)
        cob = frame.arbitration_id
        if frame.is_error_frame:
            return Decoded(None, "ERROR", "CAN error frame")
        if frame.is_extended_id:
            return Decoded(None, "EXTENDED", "29-bit identifier: not CANopen")
        if frame.is_remote_frame:
            return self._remote(cob)
        function, node = cob >> 7, cob & 0x7F
        if cob == 0x000:
            return self._nmt(data)
        if cob == 0x080:
            if not data:
                return Decoded(None, "SYNC", "SYNC")
            if len(data) == 1:
                return Decoded(None, "SYNC", "SYNC counter %d" % data[0])
            return Decoded(None, "SYNC", "SYNC malformed: %d bytes" % len(data))
        if function == 0x1 and node:
            return self._emcy(node, data)
        if cob == 0x100:
            return Decoded(None, "TIME", "TIME stamp" if len(data) == 6 else "TIME malformed: %d bytes" % len(data))
        if cob in self.pdo_maps:
            return self._pdo(cob, data)
        if function in _PDO_FUNCTIONS and node:
            kind, number = _PDO_FUNCTIONS[function]
            return Decoded(node, "%s%d" % (kind, number),
                           "node %d %s%d: %s (mapping unknown: give the node's DCF or --read-mapping)"
                           % (node, kind, number, _hex(data) or "no data"))
        if function == 0xB and node:
            return self._sdo(node, data, from_server=True)
        if function == 0xC and node:
            return self._sdo(node, data, from_server=False)
        if function == 0xE and node:
            return self._heartbeat(node, data)
        if cob in (0x7E4, 0x7E5):
            return Decoded(None, "LSS", "LSS %s command 0x%02X" % ("answer" if cob == 0x7E4 else "request",
                                                                  data[0]) if data else "LSS malformed: no data")
        return Decoded(None, "OTHER", "COB-ID 0x%03X: not in CANopen's predefined connection set" % cob)

    def _remote(self, cob: int) -> Decoded:
        node = cob & 0x7F
        if cob >> 7 == 0xE:
            return Decoded(node, "GUARD", "node %d node-guarding request (RTR)" % node)
        if cob in self.pdo_maps:
            node, kind, _ = self.pdo_maps[cob]
            return Decoded(node, kind, "node %d %s request (RTR)" % (node, kind))
        return Decoded(node or None, "RTR", "remote request for COB-ID 0x%03X" % cob)

    def _nmt(self, data: bytes) -> Decoded:
        if len(data) != 2:
            return Decoded(None, "NMT", "NMT malformed: %d bytes (expected 2)" % len(data))
        command = NMT_COMMANDS.get(data[0], "unknown command 0x%02X" % data[0])
        if data[1] == 0:
            return Decoded(None, "NMT", "NMT %s -> all nodes" % command)
        return Decoded(data[1], "NMT", "NMT %s -> node %d" % (command, data[1]))

    def _emcy(self, node: int, data: bytes) -> Decoded:
        if len(data) == 0:
            return Decoded(node, "EMCY", "node %d EMCY malformed: no data" % node)
        if len(data) < 3:
            return Decoded(node, "EMCY", "node %d EMCY malformed: %d bytes (expected 8): %s"
                           % (node, len(data), _hex(data)))
        code, register = struct.unpack_from("<HB", data)
        text = ("node %d EMCY error reset (no error), error register %s" if code == 0 else
                "node %d EMCY %s, error register %s") % ((node, error_register_text(register)) if code == 0 else
                                                        (node, describe_error(code), error_register_text(register)))
        if any(data[3:]):
            text += ", manufacturer data %s" % _hex(data[3:])
        return Decoded(node, "EMCY", text, {(0x603F, 0), (0x1001, 0)})

    def _heartbeat(self, node: int, data: bytes) -> Decoded:
        if len(data) != 1:
            return Decoded(node, "HEARTBEAT", "node %d heartbeat malformed: %d bytes" % (node, len(data)))
        state = data[0] & 0x7F
        name = NMT_STATES.get(state, "unknown state 0x%02X" % state)
        if state == 0:
            return Decoded(node, "HEARTBEAT", "node %d boot-up" % node)
        toggle = " (node-guarding answer, toggle %d)" % (data[0] >> 7) if data[0] & 0x80 else ""
        return Decoded(node, "HEARTBEAT", "node %d heartbeat: %s%s" % (node, name, toggle))

    def _pdo(self, cob: int, data: bytes) -> Decoded:
        node, kind, entries = self.pdo_maps[cob]
        parts, objects, bit = [], set(), 0
        payload = int.from_bytes(data, "little")
        for e in entries:
            objects.add((e.index, e.subindex))
            if bit + e.bits > len(data) * 8:
                parts.append("%s: missing (frame has %d bytes)" % (self.object_name(node, e.index, e.subindex),
                                                                   len(data)))
                break
            raw = ((payload >> bit) & ((1 << e.bits) - 1)).to_bytes((e.bits + 7) // 8, "little")
            bit += e.bits
            parts.append("%s = %s" % (self.object_name(node, e.index, e.subindex),
                                      self.value_text(node, e.index, e.subindex, raw)))
        if not entries:
            parts.append("no objects mapped" + (": %s" % _hex(data) if data else ""))
        elif len(data) * 8 > bit and len(data) > (bit + 7) // 8:
            parts.append("%d extra byte(s)" % (len(data) - (bit + 7) // 8))
        return Decoded(node, kind, "node %d %s: %s" % (node, kind, ", ".join(parts)), objects)

    def _sdo(self, node: int, data: bytes, from_server: bool) -> Decoded:
        who = "answer" if from_server else "request"
        if len(data) != 8:
            return Decoded(node, "SDO", "node %d SDO %s malformed: %d bytes (expected 8): %s"
                           % (node, who, len(data), _hex(data)))
        command = data[0]
        cs = command >> 5
        index, subindex = struct.unpack_from("<HB", data, 1)
        name = self.object_name(node, index, subindex)
        ref = {(index, subindex)}
        key = (node, "up" if (from_server and cs in (0, 2)) or (not from_server and cs in (2, 3)) else "down")
        if cs == 4:
            code = struct.unpack_from("<I", data, 4)[0]
            self._segments.pop((node, "up"), None)
            self._segments.pop((node, "down"), None)
            return Decoded(node, "SDO", "node %d SDO abort %s %s: 0x%08X %s"
                           % (node, "from drive" if from_server else "from client", name, code,
                              _ABORT_CODES.get(code, "unknown abort code")), ref)
        if not from_server:
            if cs == 1:  # initiate download
                expedited, sized = command & 0x02, command & 0x01
                if expedited:
                    n = 4 - ((command >> 2) & 0x3) if sized else 4
                    return Decoded(node, "SDO", "node %d SDO write %s = %s"
                                   % (node, name, self.value_text(node, index, subindex, data[4:4 + n])), ref)
                size = struct.unpack_from("<I", data, 4)[0] if sized else None
                self._segments[(node, "down")] = ((index, subindex), bytearray())
                return Decoded(node, "SDO", "node %d SDO write %s, segmented%s"
                               % (node, name, ", %d bytes" % size if size is not None else ""), ref)
            if cs == 2:
                return Decoded(node, "SDO", "node %d SDO read %s" % (node, name), ref)
            if cs == 0:  # download segment
                return self._segment(node, "down", data, "write")
            if cs == 3:
                return Decoded(node, "SDO", "node %d SDO read segment request (toggle %d)"
                               % (node, (command >> 4) & 1), self._segment_ref(node, "up"))
            if cs in (5, 6):
                return Decoded(node, "SDO", "node %d SDO block %s request" % (node, "download" if cs == 6 else
                                                                              "upload"), ref)
            return Decoded(node, "SDO", "node %d SDO request with unknown command 0x%02X" % (node, command), ref)
        if cs == 2:  # initiate upload response
            expedited, sized = command & 0x02, command & 0x01
            if expedited:
                n = 4 - ((command >> 2) & 0x3) if sized else 4
                return Decoded(node, "SDO", "node %d SDO value %s = %s"
                               % (node, name, self.value_text(node, index, subindex, data[4:4 + n])), ref)
            size = struct.unpack_from("<I", data, 4)[0] if sized else None
            self._segments[(node, "up")] = ((index, subindex), bytearray())
            return Decoded(node, "SDO", "node %d SDO value %s follows in segments%s"
                           % (node, name, ", %d bytes" % size if size is not None else ""), ref)
        if cs == 3:
            return Decoded(node, "SDO", "node %d SDO write %s done" % (node, name), ref)
        if cs == 0:  # upload segment
            return self._segment(node, "up", data, "value")
        if cs == 1:
            return Decoded(node, "SDO", "node %d SDO write segment acknowledged (toggle %d)"
                           % (node, (command >> 4) & 1), self._segment_ref(node, "down"))
        if cs in (5, 6):
            return Decoded(node, "SDO", "node %d SDO block %s answer" % (node, "download" if cs == 5 else "upload"),
                           ref)
        return Decoded(node, "SDO", "node %d SDO answer with unknown command 0x%02X" % (node, command), ref)

    def _segment_ref(self, node: int, direction: str) -> Set[ObjectRef]:
        transfer = self._segments.get((node, direction))
        return {transfer[0]} if transfer else set()

    def _segment(self, node: int, direction: str, data: bytes, verb: str) -> Decoded:
        command = data[0]
        n = 7 - ((command >> 1) & 0x7)
        last = command & 0x01
        chunk = data[1:1 + n]
        transfer = self._segments.get((node, direction))
        if transfer is None:
            return Decoded(node, "SDO", "node %d SDO segment %s (no transfer started)%s"
                           % (node, _hex(chunk), ", last" if last else ""))
        (index, subindex), buffer = transfer
        buffer.extend(chunk)
        if not last:
            return Decoded(node, "SDO", "node %d SDO %s segment of %s: %s"
                           % (node, verb, self.object_name(node, index, subindex), _hex(chunk)), {(index, subindex)})
        del self._segments[(node, direction)]
        return Decoded(node, "SDO", "node %d SDO %s %s = %s (segmented)"
                       % (node, verb, self.object_name(node, index, subindex),
                          self.value_text(node, index, subindex, bytes(buffer))), {(index, subindex)})

    def set_pdo_map(self, node: int, kind: str, number: int, cob_id: int, entries: List[PdoEntry]) -> None:
        for cob, (n, k, _) in list(self.pdo_maps.items()):
            if n == node and k == "%s%d" % (kind, number):
                del self.pdo_maps[cob]
        self.pdo_maps[cob_id] = (node, "%s%d" % (kind, number), entries)


def _hex(data: bytes) -> str:
    return " ".join("%02X" % b for b in data)


def _od_value(od: ObjectDictionary, index: int, subindex: int) -> Optional[int]:
    try:
        obj = od[index]
        var = obj[subindex] if isinstance(obj, (ODRecord, ODArray)) else obj
    except (KeyError, IndexError, TypeError):
        return None
    value = var.value if var.value is not None else var.default
    return value if isinstance(value, int) else None


def _entries(raw_entries: Iterable[int]) -> List[PdoEntry]:
    return [PdoEntry(v >> 16, (v >> 8) & 0xFF, v & 0xFF) for v in raw_entries if v & 0xFF]


def pdo_maps_from_od(od: ObjectDictionary, node_id: int, receive: bool) -> Dict[int, Tuple[int, List[PdoEntry]]]:
    """PDO number -> (COB-ID, entries) of the valid PDOs in a DCF's dictionary
    (communication 0x1400/0x1800, mapping 0x1600/0x1A00 + n-1)."""
    comm, mapping = (0x1400, 0x1600) if receive else (0x1800, 0x1A00)
    maps = {}
    for n in range(4):
        cob = _od_value(od, comm + n, 1)
        count = _od_value(od, mapping + n, 0)
        if cob is None or count is None or cob & 0x80000000:
            continue
        values = [_od_value(od, mapping + n, s) for s in range(1, count + 1)]
        maps[n + 1] = (cob & 0x7FF, _entries(v for v in values if v is not None))
    return maps


def read_pdo_mapping(upload: Callable[[int, int], bytes], node: int, decoder: Decoder) -> List[str]:
    """Reads the 4 RPDOs and 4 TPDOs of ``node`` with SDO uploads
    (``upload(index, subindex) -> bytes``) into ``decoder``; returns one line
    per PDO saying what was found."""
    lines = []
    for kind, comm, mapping in (("RPDO", 0x1400, 0x1600), ("TPDO", 0x1800, 0x1A00)):
        for n in range(4):
            cob = int.from_bytes(upload(comm + n, 1)[:4], "little")
            if cob & 0x80000000:
                lines.append("node %d %s%d: not valid" % (node, kind, n + 1))
                continue
            count = upload(mapping + n, 0)[0]
            entries = _entries(int.from_bytes(upload(mapping + n, s)[:4], "little") for s in range(1, count + 1))
            decoder.set_pdo_map(node, kind, n + 1, cob & 0x7FF, entries)
            lines.append("node %d %s%d (COB-ID 0x%03X): %s" % (
                node, kind, n + 1, cob & 0x7FF,
                ", ".join(decoder.object_name(node, e.index, e.subindex) for e in entries) or "nothing mapped"))
    return lines


# --- filters ----------------------------------------------------------------

class Filter:
    """Keeps frames of the given nodes and touching the given objects (an
    empty set keeps all). Bus-wide frames (SYNC, TIME, NMT to all) pass the
    node filter only when no node is given; the object filter drops them."""

    def __init__(self, nodes: Sequence[int] = (), objects: Sequence[ObjectRef] = ()) -> None:
        self.nodes = set(nodes)
        self.objects = list(objects)

    def __call__(self, decoded: Decoded) -> bool:
        if self.nodes and decoded.node not in self.nodes:
            return False
        if self.objects:
            return any(o_index == index and o_sub in (-1, sub)
                       for index, sub in decoded.objects for o_index, o_sub in self.objects)
        return True


# --- output -------------------------------------------------------------------

def format_line(frame: can.Message, decoded: Decoded, start: float) -> str:
    ident = "%08X" % frame.arbitration_id if frame.is_extended_id else "%03X" % frame.arbitration_id
    payload = "R" if frame.is_remote_frame else _hex(bytes(frame.data))
    return "%10.6f  %s  [%d]  %-23s  %s" % (frame.timestamp - start, ident, frame.dlc, payload, decoded.text)
