#!/usr/bin/env python3
"""Generate the project's own EPOS4 DCF files (maxon_epos4_ros_canopen/config/).

Usage: tools/make_epos4_dcf.py [--out DIR] [--check]

The table below lists the EPOS4 objects the driver and the virtual EPOS4 use,
with data type, access, firmware default (maxon EPOS4 Firmware
Specification, object dictionary chapter) and the value this project
configures (ParameterValue).  Motor data describe an EC 90 flat with a
MILE encoder of 800 counts per turn, the hardware of maxon's ROS examples.
PDO mapping is the one the EPOS Studio CANopen wizard produces for the ROS
examples.  ``--check`` only verifies that the files on disk are up to date.
"""
from __future__ import annotations

import argparse
import os
import sys
from typing import Dict, List, Optional, Tuple

BOOLEAN, INT8, INT16, INT32, UINT8, UINT16, UINT32, VSTRING = 0x1, 0x2, 0x3, 0x4, 0x5, 0x6, 0x7, 0x9

# (index, subindex or None for a plain variable, name, type, access, default,
#  pdo mappable, low limit, high limit); value columns are strings as in a DCF.
Entry = Tuple[int, Optional[int], str, int, str, str, bool, Optional[str], Optional[str]]


def _v(index: int, name: str, dtype: int, access: str, default: str, pdo: bool = False,
       low: Optional[str] = None, high: Optional[str] = None) -> Entry:
    return (index, None, name, dtype, access, default, pdo, low, high)


def _s(index: int, sub: int, name: str, dtype: int, access: str, default: str, pdo: bool = False,
       low: Optional[str] = None, high: Optional[str] = None) -> Entry:
    return (index, sub, name, dtype, access, default, pdo, low, high)


def _pdo_objects() -> List[Entry]:
    rows: List[Entry] = []
    for n in range(4):
        rows.append(_s(0x1400 + n, 0, "Highest sub-index supported", UINT8, "ro", "2"))
        rows.append(_s(0x1400 + n, 1, "COB-ID used by RxPDO %d" % (n + 1), UINT32, "rw",
                       "$NODEID+0x%08X" % (0x200 + 0x100 * n)))
        rows.append(_s(0x1400 + n, 2, "Transmission type RxPDO %d" % (n + 1), UINT8, "rw", "255"))
    for n in range(4):
        rows.append(_s(0x1600 + n, 0, "Number of mapped objects in RxPDO %d" % (n + 1), UINT8, "rw", "0"))
        for k in range(1, 9):
            rows.append(_s(0x1600 + n, k, "Mapped object %d in RxPDO %d" % (k, n + 1), UINT32, "rw", "0x00000000"))
    for n in range(4):
        rows.append(_s(0x1800 + n, 0, "Highest sub-index supported", UINT8, "ro", "3"))
        rows.append(_s(0x1800 + n, 1, "COB-ID used by TxPDO %d" % (n + 1), UINT32, "rw",
                       "$NODEID+0x%08X" % (0x180 + 0x100 * n)))
        rows.append(_s(0x1800 + n, 2, "Transmission type TxPDO %d" % (n + 1), UINT8, "rw", "255"))
        rows.append(_s(0x1800 + n, 3, "Inhibit time TxPDO %d" % (n + 1), UINT16, "rw", "10"))
    for n in range(4):
        rows.append(_s(0x1A00 + n, 0, "Number of mapped objects in TxPDO %d" % (n + 1), UINT8, "rw", "0"))
        for k in range(1, 9):
            rows.append(_s(0x1A00 + n, k, "Mapped object %d in TxPDO %d" % (k, n + 1), UINT32, "rw", "0x00000000"))
    return rows


OBJECTS: List[Entry] = [
    _v(0x1000, "Device type", UINT32, "ro", "0x00020192"),
    _v(0x1001, "Error register", UINT8, "ro", "0x00", True),
    _s(0x1003, 0, "Number of errors", UINT8, "rw", "0"),
    *[_s(0x1003, k, "Error history %d" % k, UINT32, "ro", "0x00000000") for k in range(1, 6)],
    _v(0x1005, "COB-ID SYNC", UINT32, "rw", "0x00000080"),
    _v(0x1008, "Manufacturer device name", VSTRING, "const", "EPOS4"),
    _s(0x1010, 0, "Highest sub-index supported", UINT8, "ro", "1"),
    _s(0x1010, 1, "Save all parameters", UINT32, "rw", "0x00000001"),
    _s(0x1011, 0, "Highest sub-index supported", UINT8, "ro", "1"),
    _s(0x1011, 1, "Restore all default parameters", UINT32, "rw", "0x00000001"),
    _v(0x1014, "COB-ID EMCY", UINT32, "ro", "$NODEID+0x00000080"),
    _s(0x1016, 0, "Highest sub-index supported", UINT8, "ro", "2"),
    _s(0x1016, 1, "Consumer 1 heartbeat time", UINT32, "rw", "0x00000000"),
    _s(0x1016, 2, "Consumer 2 heartbeat time", UINT32, "rw", "0x00000000"),
    _v(0x1017, "Producer heartbeat time", UINT16, "rw", "0"),
    _s(0x1018, 0, "Highest sub-index supported", UINT8, "ro", "4"),
    _s(0x1018, 1, "Vendor ID", UINT32, "ro", "0x000000FB"),
    _s(0x1018, 2, "Product code", UINT32, "ro", "0x65520000"),
    _s(0x1018, 3, "Revision number", UINT32, "ro", "0x01700000"),
    _s(0x1018, 4, "Serial number", UINT32, "ro", "0x00000000"),
    _s(0x1029, 0, "Highest sub-index supported", UINT8, "ro", "1"),
    _s(0x1029, 1, "Communication error", UINT8, "rw", "0"),
    _s(0x1200, 0, "Highest sub-index supported", UINT8, "ro", "2"),
    _s(0x1200, 1, "COB-ID client to server", UINT32, "ro", "$NODEID+0x00000600"),
    _s(0x1200, 2, "COB-ID server to client", UINT32, "ro", "$NODEID+0x00000580"),
    *_pdo_objects(),
    _v(0x2000, "Node-ID", UINT8, "rw", "1"),
    _s(0x2200, 0, "Highest sub-index supported", UINT8, "ro", "2"),
    _s(0x2200, 1, "Power supply voltage", UINT16, "ro", "240"),
    _s(0x2200, 2, "Internal valid logic supply", BOOLEAN, "ro", "1"),
    _s(0x3000, 0, "Highest sub-index supported", UINT8, "ro", "6"),
    _s(0x3000, 5, "Main sensor resolution", UINT32, "ro", "2000"),
    _s(0x3000, 6, "Max system speed", UINT32, "ro", "100000"),
    _s(0x3001, 0, "Highest sub-index supported", UINT8, "ro", "5"),
    _s(0x3001, 1, "Nominal current", UINT32, "rww", "15000", True),
    _s(0x3001, 2, "Output current limit", UINT32, "rww", "30000", True),
    _s(0x3001, 3, "Number of pole pairs", UINT8, "rw", "1"),
    _s(0x3001, 4, "Thermal time constant winding", UINT16, "rw", "40"),
    _s(0x3001, 5, "Torque constant", UINT32, "rw", "0"),
    _s(0x3010, 0, "Highest sub-index supported", UINT8, "ro", "2"),
    _s(0x3010, 1, "Digital incremental encoder 1 number of pulses", UINT32, "rw", "500"),
    _s(0x3010, 2, "Digital incremental encoder 1 type", UINT16, "rw", "0x0001"),
    _v(0x30B0, "Home position", INT32, "rww", "0", True),
    _v(0x30B1, "Home offset move distance", INT32, "rw", "0"),
    _v(0x30B2, "Current threshold for homing mode", UINT16, "rww", "500", True, "0", "30000"),
    _v(0x30D0, "Current demand value", INT32, "ro", "0", True),
    _s(0x30D1, 0, "Highest sub-index supported", UINT8, "ro", "2"),
    _s(0x30D1, 1, "Current actual value averaged", INT32, "ro", "0", True),
    _s(0x30D1, 2, "Current actual value", INT32, "ro", "0", True),
    _s(0x30D2, 0, "Highest sub-index supported", UINT8, "ro", "1"),
    _s(0x30D2, 1, "Torque actual value averaged", INT16, "ro", "0", True),
    _s(0x30D3, 0, "Highest sub-index supported", UINT8, "ro", "1"),
    _s(0x30D3, 1, "Velocity actual value averaged", INT32, "ro", "0", True),
    _v(0x6007, "Abort connection option code", INT16, "rw", "3", False, "0", "3"),
    _v(0x603F, "Error code", UINT16, "ro", "0x0000", True),
    _v(0x6040, "Controlword", UINT16, "rww", "0x0000", True),
    _v(0x6041, "Statusword", UINT16, "ro", "0x0000", True),
    _v(0x605A, "Quick stop option code", INT16, "rw", "6", False, "0", "6"),
    _v(0x605B, "Shutdown option code", INT16, "rw", "0", False, "0", "1"),
    _v(0x605C, "Disable operation option code", INT16, "rw", "1", False, "0", "1"),
    _v(0x605E, "Fault reaction option code", INT16, "rw", "2", False, "0", "2"),
    _v(0x6060, "Modes of operation", INT8, "rww", "0", True, "-128", "10"),
    _v(0x6061, "Modes of operation display", INT8, "ro", "0", True),
    _v(0x6062, "Position demand value", INT32, "ro", "0", True),
    _v(0x6064, "Position actual value", INT32, "ro", "0", True),
    _v(0x6065, "Following error window", UINT32, "rww", "2000", True),
    _v(0x6066, "Following error time out", UINT16, "rww", "0", True),
    _v(0x6067, "Position window", UINT32, "rww", "4294967295", True),
    _v(0x6068, "Position window time", UINT16, "rww", "0", True),
    _v(0x606B, "Velocity demand value", INT32, "ro", "0", True),
    _v(0x606C, "Velocity actual value", INT32, "ro", "0", True),
    _v(0x6071, "Target torque", INT16, "rww", "0", True, "-32768", "32767"),
    _v(0x6076, "Motor rated torque", UINT32, "rw", "0"),
    _v(0x6077, "Torque actual value", INT16, "ro", "0", True),
    _v(0x607A, "Target position", INT32, "rww", "0", True),
    _s(0x607D, 0, "Highest sub-index supported", UINT8, "const", "2"),
    _s(0x607D, 1, "Min position limit", INT32, "rww", "-2147483648", True),
    _s(0x607D, 2, "Max position limit", INT32, "rww", "2147483647", True),
    _v(0x607F, "Max profile velocity", UINT32, "rww", "50000", True, "1", "50000"),
    _v(0x6080, "Max motor speed", UINT32, "rww", "50000", True, "1", "50000"),
    _v(0x6081, "Profile velocity", UINT32, "rww", "1000", True, "1", "50000"),
    _v(0x6083, "Profile acceleration", UINT32, "rww", "10000", True, "1", "4294967295"),
    _v(0x6084, "Profile deceleration", UINT32, "rww", "10000", True, "1", "4294967295"),
    _v(0x6085, "Quick stop deceleration", UINT32, "rww", "10000", True, "1", "4294967295"),
    _v(0x6086, "Motion profile type", INT16, "rww", "0", True, "0", "0"),
    _v(0x6098, "Homing method", INT8, "rww", "7", True, "-4", "37"),
    _s(0x6099, 0, "Highest sub-index supported", UINT8, "const", "2"),
    _s(0x6099, 1, "Speed for switch search", UINT32, "rww", "100", True, "1", "50000"),
    _s(0x6099, 2, "Speed for zero search", UINT32, "rww", "10", True, "1", "50000"),
    _v(0x609A, "Homing acceleration", UINT32, "rww", "1000", True, "1", "4294967295"),
    _v(0x60B1, "Velocity offset", INT32, "rww", "0", True),
    _v(0x60B2, "Torque offset", INT16, "rww", "0", True),
    _s(0x60C2, 0, "Highest sub-index supported", UINT8, "const", "2"),
    _s(0x60C2, 1, "Interpolation time period value", UINT8, "rww", "0", True, "0", "100"),
    _s(0x60C2, 2, "Interpolation time index", INT8, "rww", "-3", True, "-3", "-3"),
    _v(0x60C5, "Max acceleration", UINT32, "rww", "4294967295", True, "1", "4294967295"),
    _v(0x60F4, "Following error actual value", INT32, "ro", "0", True),
    _v(0x60FD, "Digital inputs", UINT32, "ro", "0x00000000", True),
    _v(0x60FF, "Target velocity", INT32, "rww", "0", True),
    _v(0x6402, "Motor type", UINT16, "rw", "10"),
    _v(0x6502, "Supported drive modes", UINT32, "ro", "0x000003A5", True),
]

# What this project configures (ParameterValue) where it differs from the
# firmware default.  Keys are (index, subindex or 0).
COMMON: Dict[Tuple[int, int], str] = {
    # PDO mapping of the EPOS Studio CANopen wizard for the ROS examples.
    (0x1600, 0): "2", (0x1600, 1): "0x60400010", (0x1600, 2): "0x60FF0020",
    (0x1601, 0): "2", (0x1601, 1): "0x607A0020", (0x1601, 2): "0x60810020",
    (0x1602, 0): "2", (0x1602, 1): "0x60830020", (0x1602, 2): "0x60840020",
    (0x1603, 0): "2", (0x1603, 1): "0x60710010", (0x1603, 2): "0x60600008",
    (0x1A00, 0): "2", (0x1A00, 1): "0x60410010", (0x1A00, 2): "0x60610008",
    (0x1A01, 0): "2", (0x1A01, 1): "0x606B0020", (0x1A01, 2): "0x606C0020",
    (0x1A02, 0): "2", (0x1A02, 1): "0x60640020", (0x1A02, 2): "0x30D30120",
    (0x1A03, 0): "0",
    **{(0x1400 + n, 2): "1" for n in range(4)},
    **{(0x1800 + n, 2): "1" for n in range(4)},
    # EC 90 flat (nominal current, peak limit, torque constant in uNm/A,
    # rated torque in uNm), MILE encoder 800 counts -> 3200 increments/turn.
    (0x3000, 5): "3200", (0x3000, 6): "5000",
    (0x3001, 1): "4760", (0x3001, 2): "9520", (0x3001, 3): "12",
    (0x3001, 4): "460", (0x3001, 5): "107746", (0x6076, 0): "512871",
    (0x3010, 1): "800", (0x3010, 2): "0x0000", (0x6402, 0): "11",
    (0x6060, 0): "1", (0x6061, 0): "1", (0x6041, 0): "0x0040",
    (0x6065, 0): "20000", (0x6067, 0): "100", (0x6068, 0): "10",
    (0x607F, 0): "5000", (0x6080, 0): "5000", (0x6081, 0): "1000",
    (0x60C5, 0): "100000",
    # CSP: the master sends a target every 10 ms.
    (0x60C2, 1): "10",
    # 0 = no homing required (CiA 402), as the seeds set it for the PPM, PVM
    # and CSP examples: the driver homes at init only where 0x6098 != 0.
    (0x6098, 0): "0",
}

VARIANTS: Dict[str, Tuple[int, Dict[Tuple[int, int], str]]] = {
    "epos4_node1.dcf": (1, {}),
    "epos4_node2.dcf": (2, {}),
    # Homing against a mechanical stop: -3 = current threshold, positive speed.
    "epos4_node1_hm.dcf": (1, {(0x6098, 0): "-3", (0x30B2, 0): "1500",
                               (0x30B1, 0): "1000", (0x30B0, 0): "0",
                               (0x6099, 1): "300", (0x6099, 2): "30",
                               (0x609A, 0): "5000"}),
}

_FILE_HEADER = """; Generated by tools/make_epos4_dcf.py; edit the generator, not this file.

[FileInfo]
FileName={name}
FileVersion=1
FileRevision=0
Description=maxon EPOS4 for maxon_epos4_ros_canopen (node {node_id})
EDSVersion=4.0
CreatedBy=maxon_epos4_ros1 tools/make_epos4_dcf.py

[DeviceInfo]
VendorName=maxon motor ag
VendorNumber=0x000000FB
ProductName=EPOS4
ProductNumber=0x65520000
RevisionNumber=0x01700000
BaudRate_1000=1
BaudRate_500=1
BaudRate_250=1
SimpleBootUpSlave=1
Granularity=8
NrOfRXPDO=4
NrOfTXPDO=4
LSS_Supported=0

[DeviceComissioning]
NodeID={node_id}
NodeName=EPOS4
Baudrate=1000
"""


def _section_name(index: int, sub: Optional[int]) -> str:
    return "%04X" % index if sub is None else "%04Xsub%X" % (index, sub)


def _object_lines(name: str, entry: Entry, value: str) -> List[str]:
    index, sub, pname, dtype, access, default, pdo, low, high = entry
    lines = ["[%s]" % _section_name(index, sub), "ParameterName=%s" % pname,
             "ObjectType=0x7", "DataType=0x%X" % dtype, "AccessType=%s" % access,
             "DefaultValue=%s" % default]
    if low is not None:
        lines += ["LowLimit=%s" % low, "HighLimit=%s" % high]
    lines += ["PDOMapping=%d" % int(pdo), "ParameterValue=%s" % value, ""]
    return lines


_RECORD_NAMES = {
    0x1003: ("Pre-defined error field", 0x8), 0x1010: ("Store parameters", 0x8),
    0x1011: ("Restore default parameters", 0x8), 0x1016: ("Consumer heartbeat time", 0x8),
    0x1029: ("Error behavior", 0x8),
    0x1018: ("Identity object", 0x9), 0x1200: ("SDO server parameter", 0x9),
    0x2200: ("Power supply", 0x9), 0x3000: ("Axis configuration", 0x9),
    0x3001: ("Motor data", 0x9), 0x3010: ("Digital incremental encoder 1", 0x9),
    0x30D1: ("Current actual values", 0x8), 0x30D2: ("Torque actual values", 0x8),
    0x30D3: ("Velocity actual values", 0x8), 0x607D: ("Software position limit", 0x8),
    0x6099: ("Homing speeds", 0x8), 0x60C2: ("Interpolation time period", 0x9),
}


def _record_name(index: int) -> Tuple[str, int]:
    if index in _RECORD_NAMES:
        return _RECORD_NAMES[index]
    kind = {0x14: "Receive PDO %d parameter", 0x16: "Receive PDO %d mapping",
            0x18: "Transmit PDO %d parameter", 0x1A: "Transmit PDO %d mapping"}[index >> 8]
    return kind % ((index & 0xFF) + 1), 0x9


def render(filename: str, node_id: int, overrides: Dict[Tuple[int, int], str]) -> str:
    values = dict(COMMON)
    values.update(overrides)
    values[(0x2000, 0)] = str(node_id)
    groups: Dict[int, List[Entry]] = {}
    for entry in OBJECTS:
        groups.setdefault(entry[0], []).append(entry)
    mandatory = [i for i in (0x1000, 0x1001, 0x1018) if i in groups]
    optional = [i for i in groups if i < 0x2000 and i not in mandatory or i >= 0x6000]
    manufacturer = [i for i in groups if 0x2000 <= i < 0x6000]
    out = [_FILE_HEADER.format(name=filename, node_id=node_id)]
    for title, indices in (("MandatoryObjects", mandatory), ("OptionalObjects", optional),
                           ("ManufacturerObjects", manufacturer)):
        out.append("[%s]" % title)
        out.append("SupportedObjects=%d" % len(indices))
        out += ["%d=0x%04X" % (n + 1, i) for n, i in enumerate(indices)]
        out.append("")
        for index in indices:
            entries = groups[index]
            if entries[0][1] is not None:
                name, otype = _record_name(index)
                out += ["[%04X]" % index, "SubNumber=%d" % len(entries),
                        "ParameterName=%s" % name, "ObjectType=0x%X" % otype, ""]
            for entry in entries:
                value = values.get((index, entry[1] or 0), entry[5])
                out += _object_lines(filename, entry, value)
    return "\n".join(out)


def main(argv: Optional[List[str]] = None) -> int:
    here = os.path.dirname(os.path.abspath(__file__))
    default_out = os.path.join(here, "..", "maxon_epos4_ros_canopen", "config")
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=default_out, help="output folder")
    parser.add_argument("--check", action="store_true", help="fail if a file on disk differs")
    args = parser.parse_args(argv)
    stale = []
    for filename, (node_id, overrides) in VARIANTS.items():
        text = render(filename, node_id, overrides)
        path = os.path.join(args.out, filename)
        if args.check:
            try:
                with open(path) as f:
                    if f.read() != text:
                        stale.append(path)
            except OSError:
                stale.append(path)
            continue
        with open(path, "w") as f:
            f.write(text)
        print("wrote %s" % os.path.normpath(path))
    if stale:
        print("out of date (run tools/make_epos4_dcf.py): %s" % ", ".join(stale), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
