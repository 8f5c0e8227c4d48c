"""The command line of epos4_settings (its user's page: docs/epos4_settings.md)."""
from __future__ import annotations

import argparse
import os
import sys
from typing import Callable, Optional, Sequence, TextIO

import can

from ..can_device import CanDeviceError, open_device
from ..clock import REAL, Clock
from .commands import backup, diff, restore
from .dcf import PROG, SettingsError, load_file
from .session import Session

PACKAGE = "maxon_epos4_ros_canopen"
SHIPPED_DCF = os.path.join("config", "epos4_node1.dcf")  # in the package's folder
DEFAULT_LISTEN_S = 1.0
DEFAULT_SDO_TIMEOUT_S = 0.5


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG, description="Back up, compare and restore the settings of a maxon EPOS4 over CANopen "
                               "(docs/epos4_settings.md).")
    sub = parser.add_subparsers(dest="command")

    def common(p: argparse.ArgumentParser) -> None:
        p.add_argument("device", help="CAN adapter as bus/device takes it: can0, vcan0, pcan:PCAN_USBBUS1, "
                                      "virtual:NAME")
        p.add_argument("node", type=_node_id, help="node-ID of the drive (1..127)")
        p.add_argument("--bitrate", type=int, default=None, help="bit/s, for adapters that take one "
                                                                 "(default 1000000)")
        p.add_argument("--listen", type=float, default=DEFAULT_LISTEN_S, metavar="SECONDS",
                       help="listen this long for another master before starting (default %.1f)"
                       % DEFAULT_LISTEN_S)
        p.add_argument("--sdo-timeout", type=float, default=DEFAULT_SDO_TIMEOUT_S, metavar="SECONDS",
                       help="wait this long for each SDO answer (default %.1f)" % DEFAULT_SDO_TIMEOUT_S)

    p = sub.add_parser("backup", help="read every readable object into a DCF on stdout")
    common(p)
    p.add_argument("--dcf", default=None, help="DCF/EDS listing the objects (default: the "
                                                      "package's config/epos4_node1.dcf)")
    p = sub.add_parser("diff", help="list the settings that differ from FILE; exit 1 when any does")
    common(p)
    p.add_argument("file", help="DCF, e.g. a backup")
    p = sub.add_parser("restore", help="write FILE's settings that differ; --store saves them (0x1010)")
    common(p)
    p.add_argument("file", help="DCF, e.g. a backup")
    p.add_argument("--store", action="store_true", help="then write 0x1010 sub 1 'save': the settings "
                                                        "survive a power cycle")
    return parser


def shipped_dcf() -> str:
    """The package's own EPOS4 DCF: found by rospkg where ROS is set up, else
    beside this source folder."""
    try:
        import rospkg
        base = rospkg.RosPack().get_path(PACKAGE)
    except Exception:  # no ROS environment (or rospkg): a source checkout
        base = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
    return os.path.join(base, SHIPPED_DCF)


def _node_id(text: str) -> int:
    try:
        value = int(text, 0)
    except ValueError:
        raise argparse.ArgumentTypeError("node-ID %r is not a number" % text) from None
    if not 1 <= value <= 127:
        raise argparse.ArgumentTypeError("node-ID %d outside 1..127" % value)
    return value


def main(argv: Optional[Sequence[str]] = None, out: Optional[TextIO] = None, err: Optional[TextIO] = None,
         opener: Callable[[str, Optional[int]], can.BusABC] = open_device, clock: Clock = REAL) -> int:
    """The command line; ``opener(device, bitrate)`` opens the bus (tests wrap
    it); ``clock``: the time the listen window and the SDO waits run on."""
    out = sys.stdout if out is None else out
    err = sys.stderr if err is None else err
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse printed the usage
        return 2 if exc.code else 0
    if args.command is None:
        parser.print_usage(err)
        return 2
    bus = None
    session = None
    try:
        if args.listen < 0 or args.sdo_timeout <= 0:
            raise SettingsError("--listen must be >= 0 and --sdo-timeout > 0")
        path = args.file if args.command != "backup" else args.dcf or shipped_dcf()
        file = load_file(path, args.node)
        bus = opener(args.device, args.bitrate)
        session = Session(bus, args.device, args.node, file, args.sdo_timeout, args.listen, err, clock)
        if args.command == "backup":
            return backup(session, out, err)
        if args.command == "diff":
            return diff(session, out, err)
        return restore(session, out, err, args.store)
    except (SettingsError, CanDeviceError) as exc:
        err.write("%s: %s\n" % (PROG, exc))
        return 2
    except (can.CanError, OSError) as exc:  # the adapter failed while sending or receiving
        err.write("%s: CAN error on %s after %d SDO transfers: %s\n"
                  % (PROG, args.device, session.transfers if session else 0, exc))
        return 2
    except KeyboardInterrupt:
        err.write("\n%s: interrupted after %d SDO transfers%s\n"
                  % (PROG, session.transfers if session else 0,
                     ": the drive may hold part of the file's settings, and a PDO may be left invalid; "
                     "run restore again" if args.command == "restore" else ""))
        return 2
    finally:
        if session is not None:
            session.close()
        if bus is not None:
            bus.shutdown()

