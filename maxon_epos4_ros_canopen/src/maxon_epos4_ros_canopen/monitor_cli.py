"""The canopen_monitor command around the decoder of monitor.py: the
bus-load line (bits counted like can-utils' canbusload), candump's log format
(``candump_line`` writes what ``--record`` keeps, ``parse_candump_line``
reads what ``--log`` replays), the arguments and the live session.
"""
from __future__ import annotations

import re
from typing import Dict, Optional, Sequence, Tuple

import can
import canopen
from canopen.objectdictionary import ObjectDictionary

from .monitor import Decoder, Filter, format_line, parse_object, read_pdo_mapping
from .objects import load_dictionary

__all__ = ["frame_bits", "BusLoad", "candump_line", "parse_candump_line", "USAGE", "default_dictionary", "main"]


# --- bus load -----------------------------------------------------------------

def frame_bits(frame: can.Message) -> int:
    """Bits on the wire without stuffing, as canbusload counts them: 47 + 8
    per data byte for 11-bit identifiers, 67 + 8 per byte for 29-bit ones."""
    data_bits = 0 if frame.is_remote_frame else 8 * min(len(frame.data), 8)
    return (67 if frame.is_extended_id else 47) + data_bits


class BusLoad:
    """Frames and bits per interval; ``line()`` says them like canbusload."""

    def __init__(self, device: str, bitrate: int) -> None:
        self.device = device
        self.bitrate = bitrate
        self.frames = 0
        self.bits = 0

    def add(self, frame: can.Message) -> None:
        self.frames += 1
        self.bits += frame_bits(frame)

    def line(self, seconds: float) -> str:
        seconds = max(seconds, 1e-6)
        load = 100.0 * self.bits / (self.bitrate * seconds)
        text = "%s  %d frames/s  %d bit/s  %d%% of %d bit/s %s" % (
            self.device, round(self.frames / seconds), round(self.bits / seconds), round(load), self.bitrate,
            _bar(load))
        self.frames = self.bits = 0
        return text


def _bar(percent: float) -> str:
    n = max(0, min(20, int(percent / 5)))
    return "|" + "X" * n + "." * (20 - n) + "|"


# --- candump's log format -----------------------------------------------------

def candump_line(frame: can.Message, device: str) -> str:
    """``(1700000000.123456) can0 181#0102`` as ``candump -l`` writes it."""
    if frame.is_extended_id:
        ident = "%08X" % frame.arbitration_id
    else:
        ident = "%03X" % frame.arbitration_id
    if frame.is_remote_frame:
        payload = "R" + (str(frame.dlc) if frame.dlc else "")
    else:
        payload = bytes(frame.data).hex().upper()
    return "(%.6f) %s %s#%s" % (frame.timestamp, device, ident, payload)


_CANDUMP = re.compile(r"\((\d+(?:\.\d+)?)\)\s+(\S+)\s+([0-9A-Fa-f]{1,8})#(R\d?|[0-9A-Fa-f]*)\s*$")


def parse_candump_line(line: str) -> Tuple[can.Message, str]:
    """The message and device of one ``candump -l`` line; ValueError otherwise."""
    m = _CANDUMP.match(line.strip())
    if not m or (not m.group(4).startswith("R") and len(m.group(4)) % 2):
        raise ValueError("not a candump log line: %r" % line.strip())
    ident = m.group(3)
    remote = m.group(4).startswith("R")
    data = b"" if remote else bytes.fromhex(m.group(4))
    if len(data) > 8:
        raise ValueError("more than 8 data bytes: %r" % line.strip())
    return can.Message(timestamp=float(m.group(1)), arbitration_id=int(ident, 16), is_extended_id=len(ident) > 3,
                       is_remote_frame=remote, dlc=int(m.group(4)[1:] or 0) if remote else len(data),
                       data=data), m.group(2)


# --- the command ------------------------------------------------------------------

USAGE = """canopen_monitor [DEVICE] [--dcf ID:FILE ...] [--node ID ...] [--object OBJ ...]
                [--read-mapping ID ...] [--record FILE] [--bitrate BIT/S] [--load-interval S]
                [--log FILE]"""


def _arguments(argv: Sequence[str]):
    import argparse
    parser = argparse.ArgumentParser(
        prog="canopen_monitor", usage=USAGE,
        description="Print every CANopen frame on a bus decoded: NMT, SYNC, heartbeats, EMCY with EPOS4 error "
                    "names, SDO requests and answers with object names and values, PDOs as their mapped "
                    "objects; and a bus-load line.")
    parser.add_argument("device", nargs="?", default="can0",
                        help="can0 (SocketCAN) or INTERFACE:CHANNEL (pcan:PCAN_USBBUS1, ixxat:0, kvaser:0, "
                             "slcan:/dev/ttyACM0); default can0")
    parser.add_argument("--dcf", action="append", default=[], metavar="ID:FILE",
                        help="a node's DCF/EDS: object names, types and its PDO mapping (repeatable)")
    parser.add_argument("--node", action="append", default=[], type=int, metavar="ID",
                        help="show only frames of this node (repeatable)")
    parser.add_argument("--object", action="append", default=[], metavar="OBJ",
                        help="show only frames touching this object: 6041, 1A00sub1 (repeatable)")
    parser.add_argument("--read-mapping", action="append", default=[], type=int, metavar="ID",
                        help="read this node's PDO mapping from the drive by SDO at start (sends frames)")
    parser.add_argument("--record", metavar="FILE", help="write every frame to FILE in candump's log format")
    parser.add_argument("--bitrate", type=int, default=None,
                        help="bus bit rate for the load line, and for adapters opened with one; default 1000000")
    parser.add_argument("--load-interval", type=float, default=1.0, metavar="S",
                        help="seconds between bus-load lines; 0: none (default 1)")
    parser.add_argument("--log", metavar="FILE", help="decode a candump log file (candump -l) instead of a bus")
    return parser.parse_args(list(argv))


def _dictionaries(specs: Sequence[str]) -> Dict[int, ObjectDictionary]:
    result = {}
    for spec in specs:
        node_text, sep, path = spec.partition(":")
        if not sep or not node_text.isdigit() or not 1 <= int(node_text) <= 127 or not path:
            raise ValueError("--dcf %r: expected ID:FILE with ID 1..127" % spec)
        try:
            result[int(node_text)] = load_dictionary(path, int(node_text))
        except Exception as exc:  # canopen raises several types for unreadable files
            raise ValueError("--dcf %r: cannot read %s: %s" % (spec, path, exc)) from None
    return result


def default_dictionary() -> Optional[ObjectDictionary]:
    """The EPOS4 dictionary shipped in this package's config/, for names of nodes without --dcf."""
    import os
    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "config", "epos4_node1.dcf")
    try:
        return load_dictionary(path, 1) if os.path.exists(path) else None
    except Exception:
        return None


def main(argv: Sequence[str], out=None, stop=None) -> int:
    """The command; ``stop`` (a threading.Event) ends a live session like Ctrl-C does."""
    import sys
    import time
    out = out or sys.stdout
    try:
        args = _arguments(argv)
        objects = [parse_object(o) for o in args.object]
        decoder = Decoder(_dictionaries(args.dcf), default_dictionary())
    except ValueError as exc:
        print("canopen_monitor: %s" % exc, file=sys.stderr)
        return 2
    keep = Filter(args.node, objects)
    bitrate = args.bitrate or 1000000
    if args.log:
        return _replay(args.log, decoder, keep, out)

    from .can_device import CanDeviceError, open_device
    try:
        bus = open_device(args.device, args.bitrate)
    except CanDeviceError as exc:
        print("canopen_monitor: %s" % exc, file=sys.stderr)
        return 1
    record = open(args.record, "w", buffering=1) if args.record else None
    reader = can.BufferedReader()
    network = canopen.Network(bus)
    notifier = can.Notifier(bus, [reader] + list(network.listeners), 0.2)
    load = BusLoad(args.device, bitrate)
    start = time.time()
    try:
        for node in args.read_mapping:
            remote = canopen.RemoteNode(node, ObjectDictionary())
            network.add_node(remote)
            try:
                for line in read_pdo_mapping(remote.sdo.upload, node, decoder):
                    print(line, file=out)
            except Exception as exc:  # no answer, abort: keep monitoring with what is known
                print("node %d: could not read the PDO mapping: %s" % (node, exc), file=out)
        last_load = time.monotonic()
        while stop is None or not stop.is_set():
            frame = reader.get_message(0.2)
            if frame is not None:
                load.add(frame)
                if record is not None:
                    record.write(candump_line(frame, args.device) + "\n")
                decoded = decoder.decode(frame)
                if keep(decoded):
                    print(format_line(frame, decoded, start), file=out, flush=True)
            now = time.monotonic()
            if args.load_interval > 0 and now - last_load >= args.load_interval:
                print(load.line(now - last_load), file=out, flush=True)
                last_load = now
    except KeyboardInterrupt:
        pass
    finally:
        notifier.stop()
        bus.shutdown()
        if record is not None:
            record.close()
    return 0


def _replay(path: str, decoder: Decoder, keep: Filter, out) -> int:
    import sys
    start = None
    try:
        stream = open(path)
    except OSError as exc:
        print("canopen_monitor: %s" % exc, file=sys.stderr)
        return 1
    with stream:
        for number, line in enumerate(stream, 1):
            if not line.strip():
                continue
            try:
                frame, _ = parse_candump_line(line)
            except ValueError as exc:
                print("%s:%d: %s" % (path, number, exc), file=out)
                continue
            start = frame.timestamp if start is None else start
            decoded = decoder.decode(frame)
            if keep(decoded):
                print(format_line(frame, decoded, start), file=out)
    return 0
