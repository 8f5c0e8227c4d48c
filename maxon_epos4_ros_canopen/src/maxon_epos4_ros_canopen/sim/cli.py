"""Command line: ``virtual_epos4 --interface socketcan --channel vcan0 --node 1:node1.dcf``."""
from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
from typing import List, Optional

import can

from .runner import Simulator, parse_node_spec


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="virtual_epos4",
        description="Simulate maxon EPOS4 drives (CANopen CiA 402) on a CAN interface.")
    parser.add_argument("--interface", default="socketcan",
                        help="python-can interface (socketcan, virtual, ...); default socketcan")
    parser.add_argument("--channel", default="vcan0", help="CAN channel; default vcan0")
    parser.add_argument("--node", action="append", default=[], metavar="ID:DCF[:MIN:MAX]",
                        help="node id and its DCF/EDS, optionally a hard stop in increments "
                             "(repeat for more nodes)")
    parser.add_argument("--tick", type=float, default=0.005,
                        help="simulation step in seconds between SYNCs; default 0.005")
    parser.add_argument("--verbose", "-v", action="store_true")
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="virtual_epos4: %(message)s")
    try:
        nodes = [parse_node_spec(spec) for spec in args.node]
        if not nodes:
            raise ValueError("give at least one --node ID:DCF")
        for cfg in nodes:
            if not os.path.isfile(cfg.dcf):
                raise ValueError("node %d: no such file %s" % (cfg.node_id, cfg.dcf))
        if not 0.0005 <= args.tick <= 0.1:
            raise ValueError("--tick must be between 0.0005 and 0.1 s")
    except ValueError as exc:
        print("virtual_epos4: %s" % exc, file=sys.stderr)
        return 2
    try:
        bus = can.Bus(interface=args.interface, channel=args.channel)
    except Exception as exc:  # python-can raises several types for a missing interface
        print("virtual_epos4: cannot open %s %s: %s" % (args.interface, args.channel, exc),
              file=sys.stderr)
        return 1
    try:
        sim = Simulator(bus, nodes, tick=args.tick)
    except Exception as exc:  # a DCF canopen cannot read
        print("virtual_epos4: %s" % exc, file=sys.stderr)
        bus.shutdown()
        return 1
    signal.signal(signal.SIGTERM, lambda *_: sim._stop.set())
    logging.info("serving nodes %s on %s %s", sorted(sim.nodes), args.interface, args.channel)
    try:
        sim.run()
    except KeyboardInterrupt:
        pass
    finally:
        bus.shutdown()
    return 0
