#!/usr/bin/env python3
"""What reading one CAN frame costs the driver's receive thread, and so how
many frames a second it can take before a backlog builds in its socket (a
benchmark; needs vcan0):

    tools/vcan_run.sh bash -c '. tools/env.sh && python3 maxon_epos4_ros_canopen/benchmarks/receive_cost.py'

A sender fills the reader's socket with --frames TPDO-sized frames first;
then each way of reading drains it and prints frames/s and time per frame:

* the clock reads (wall, monotonic) and a select() that finds the socket
  empty, each alone: on hosts where they are system calls (user-mode
  Linux) they cost more than the rest of a frame;
* python-can's recv() alone;
* the driver's receive path: canopen's notifier and Network with the
  driver's ReceiveClock first and its TpdoReceiver subscribed, as
  Link.open (driver/link.py) builds them.

Figures depend on the machine and its load: compare runs on one machine.
"""
from __future__ import annotations

import argparse
import os
import select
import sys
import time
from typing import Callable, Tuple

import can
import canopen

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "src"))
from maxon_epos4_ros_canopen.can_device import enlarge_receive_buffer  # noqa: E402
from maxon_epos4_ros_canopen.driver.bus import ReceiveClock, unread_frames  # noqa: E402
from maxon_epos4_ros_canopen.driver.pdo import TpdoReceiver  # noqa: E402

TPDO = 0x181


def fill(channel: str, frames: int) -> None:
    writer = can.Bus(interface="socketcan", channel=channel)
    try:
        for i in range(frames):
            while True:
                try:
                    writer.send(can.Message(arbitration_id=TPDO, data=i.to_bytes(6, "little"),
                                            is_extended_id=False))
                    break
                except can.CanError:  # the sender's own queue is full: let it drain
                    time.sleep(0.001)
    finally:
        writer.shutdown()


def per_call(fn: Callable[[], object], calls: int) -> float:
    start = time.perf_counter()
    for _ in range(calls):
        fn()
    return (time.perf_counter() - start) / calls


def python_can_recv(reader: can.BusABC) -> Tuple[int, float]:
    """Frames read, and the monotonic time the last was read."""
    count, last = 0, time.monotonic()
    while reader.recv(timeout=0.2) is not None:
        count, last = count + 1, time.monotonic()
    return count, last


def driver_path(reader: can.BusABC) -> Tuple[int, float]:
    network = canopen.Network(reader)
    clock = ReceiveClock(unread_frames(reader))
    network.listeners.insert(0, clock)
    receiver = TpdoReceiver({TPDO: 6}, clock.times)
    network.subscribe(TPDO, receiver.on_frame)
    network.connect()
    try:
        # drained once the socket is empty and nothing more was read for a while
        while clock.unread_before(time.monotonic()) or time.monotonic() - clock.progress[0] < 0.3:
            time.sleep(0.05)
    finally:
        network.disconnect()
    frame = receiver.slots[TPDO]
    return (int.from_bytes(frame[0], "little") + 1 if frame else 0), clock.progress[0]


def drain(channel: str, frames: int, read: Callable[[can.BusABC], Tuple[int, float]]) -> Tuple[int, float]:
    """Frames read, and frames per second until the last one was read."""
    reader = can.Bus(interface="socketcan", channel=channel)
    try:
        enlarge_receive_buffer(reader.socket)
        fill(channel, frames)
        start = time.monotonic()
        count, last = read(reader)
        return count, count / max(last - start, 1e-6)
    finally:
        reader.shutdown()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--channel", default="vcan0")
    parser.add_argument("--frames", type=int, default=5000)
    args = parser.parse_args()
    probe = can.Bus(interface="socketcan", channel=args.channel)
    try:
        print("time.time()       %7.1f us per call" % (per_call(time.time, 5000) * 1e6))
        print("time.monotonic()  %7.1f us per call" % (per_call(time.monotonic, 5000) * 1e6))
        print("select(), empty   %7.1f us per call"
              % (per_call(lambda: select.select([probe.socket], [], [], 0.0), 5000) * 1e6))
    finally:
        probe.shutdown()
    for name, read in (("python-can recv()", python_can_recv), ("driver receive path", driver_path)):
        count, rate = drain(args.channel, args.frames, read)
        print("%-20s %d frames read: %6.0f frames/s, %6.1f us per frame" % (name, count, rate, 1e6 / rate))
    return 0


if __name__ == "__main__":
    sys.exit(main())
