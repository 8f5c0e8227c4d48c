#!/usr/bin/env python3
"""How many CAN frames a SocketCAN socket keeps while its process does not
read, with the kernel's default receive buffer and with the one
can_device.enlarge_receive_buffer asks for (a benchmark; needs vcan0):

    tools/vcan_run.sh bash -c '. tools/env.sh && python3 maxon_epos4_ros_canopen/benchmarks/socket_receive_buffer.py'

Prints one line per buffer: the size the kernel granted, frames sent,
frames kept.
"""
from __future__ import annotations

import argparse
import os
import socket
import sys
import time

import can

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "src"))
from maxon_epos4_ros_canopen.can_device import enlarge_receive_buffer  # noqa: E402


def kept(channel: str, frames: int, enlarge: bool) -> tuple:
    reader = can.Bus(interface="socketcan", channel=channel)
    writer = can.Bus(interface="socketcan", channel=channel)
    try:
        granted = enlarge_receive_buffer(reader.socket) if enlarge else \
            reader.socket.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        for i in range(frames):  # the reader reads nothing meanwhile: a starved process
            writer.send(can.Message(arbitration_id=0x123, data=i.to_bytes(4, "little"), is_extended_id=False))
            if i % 100 == 99:
                time.sleep(0.01)  # let the sender's own queue drain
        count = 0
        while reader.recv(timeout=0.2) is not None:
            count += 1
        return granted, count
    finally:
        reader.shutdown()
        writer.shutdown()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--channel", default="vcan0")
    ap.add_argument("--frames", type=int, default=3000)
    args = ap.parse_args()
    for enlarge in (False, True):
        granted, count = kept(args.channel, args.frames, enlarge)
        print("%-8s receive buffer %9d bytes: %d frames sent, %d kept"
              % ("enlarged" if enlarge else "default", granted, args.frames, count))
    return 0


if __name__ == "__main__":
    sys.exit(main())
