#!/usr/bin/env python3
"""Send random and malformed CAN frames (maxon_epos4_ros_canopen.fuzz).

Examples:
  tools/can_fuzz.py --channel vcan0 --count 100000 --rate 4000 --node 1 --node 2 --exclude 000#0200
  tools/can_fuzz.py --count 20 --seed 7 --dry-run          # print the frames, send nothing
  tools/can_fuzz.py --weights nmt=0,sdo_request=2 --cob-id 0A1 --cob-id 0B1

The same --seed and arguments give the same frames. Exit status: 0 when
every frame went out, 1 when some could not be sent (transmit queue full),
2 for bad arguments or an interface that cannot be opened.
"""
from __future__ import annotations

import argparse
import os
import sys
from typing import List, Optional

_SRC = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "maxon_epos4_ros_canopen", "src")
try:
    from maxon_epos4_ros_canopen import fuzz
except ImportError:  # run from a clone without the workspace sourced
    sys.path.insert(0, os.path.normpath(_SRC))
    from maxon_epos4_ros_canopen import fuzz


def _hex_id(text: str) -> int:
    try:
        return int(text, 16)
    except ValueError:
        raise argparse.ArgumentTypeError("%r is not a hexadecimal COB-ID" % text) from None


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="can_fuzz", description=__doc__.splitlines()[0],
                                     epilog="frame kinds: " + ", ".join(fuzz.KINDS))
    parser.add_argument("--interface", default="socketcan", help="python-can interface; default socketcan")
    parser.add_argument("--channel", default="vcan0", help="CAN channel; default vcan0")
    parser.add_argument("--count", type=int, default=10000, help="frames to send; default 10000")
    parser.add_argument("--rate", type=float, default=None,
                        help="at most this many frames/s (default: as fast as the bus takes them)")
    parser.add_argument("--seed", type=int, default=1, help="random seed; default 1")
    parser.add_argument("--node", type=int, action="append", default=[], metavar="ID",
                        help="CANopen node id to aim PDOs, EMCYs, heartbeats, SDO at (repeat)")
    parser.add_argument("--cob-id", type=_hex_id, action="append", default=[], metavar="HEX",
                        help="extra 11-bit id of the interface under test (repeat)")
    parser.add_argument("--weights", default="", metavar="KIND=W,...",
                        help="change the weight of frame kinds, e.g. nmt=0,sdo_request=2")
    parser.add_argument("--exclude", action="append", default=[], metavar="ID[-ID][x][#HEX]",
                        help="never send these frames, e.g. 000#0200 (NMT stop to all) (repeat)")
    parser.add_argument("--dry-run", action="store_true", help="print the frames instead of sending")
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.count < 0:
            raise ValueError("--count must be >= 0")
        fuzzer = fuzz.FrameFuzzer(args.seed, node_ids=args.node, cob_ids=args.cob_id,
                                  weights=fuzz.parse_weights(args.weights),
                                  exclude=[fuzz.Exclusion.parse(e) for e in args.exclude])
        if args.rate is not None and args.rate <= 0:
            raise ValueError("--rate must be > 0")
    except ValueError as exc:
        print("can_fuzz: %s" % exc, file=sys.stderr)
        return 2
    if args.dry_run:
        for msg in fuzzer.frames(args.count):
            print(fuzz.describe(msg))
        return 0
    import can
    try:
        bus = can.Bus(interface=args.interface, channel=args.channel)
    except Exception as exc:  # python-can raises several types for a missing interface
        print("can_fuzz: cannot open %s %s: %s" % (args.interface, args.channel, exc), file=sys.stderr)
        return 2
    try:
        report = fuzz.send(bus, fuzzer.frames(args.count), rate=args.rate)
    finally:
        bus.shutdown()
    kinds = ", ".join("%s %d" % (k, n) for k, n in fuzzer.counts.items() if n)
    print("can_fuzz: %s; %s" % (report.summary(), kinds))
    return 0 if report.dropped == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
