#!/usr/bin/env python3
"""Time epos4_settings' backup against the virtual EPOS4 on the wall clock.

    PYTHONPATH=maxon_epos4_ros_canopen/src .venv/bin/python tools/bench_settings.py [--repeat N] [--dcf FILE]

The simulator and the tool share one process and python-can's ``virtual``
bus, each on real time (threads, blocking waits), as on a host: the
figure is the tool's own (its last stderr line: objects, SDO transfers and
seconds), the median and range of N backups. The unit tests run the same
backup on a stepped clock, where its duration is virtual time.
"""
from __future__ import annotations

import argparse
import io
import os
import re
import statistics
import sys

import can

from maxon_epos4_ros_canopen import settings
from maxon_epos4_ros_canopen.sim import NodeConfig, Simulator

NODE1 = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                     "maxon_epos4_ros_canopen", "config", "epos4_node1.dcf")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--dcf", default=NODE1, help="the drive's DCF, simulated and listed (default: %(default)s)")
    args = parser.parse_args()
    channel = "bench_settings_%d" % os.getpid()
    simbus = can.Bus(interface="virtual", channel=channel)
    sim = Simulator(simbus, [NodeConfig(1, args.dcf)]).start()
    seconds = []
    try:
        for _ in range(args.repeat):
            out, err = io.StringIO(), io.StringIO()
            code = settings.main(["backup", "virtual:" + channel, "1", "--dcf", args.dcf, "--listen", "0"], out, err)
            last = err.getvalue().strip().splitlines()[-1]
            print(last)
            found = re.search(r"in ([0-9.]+) s$", last)
            if code != 0 or found is None:
                return 1
            seconds.append(float(found.group(1)))
    finally:
        sim.stop()
        simbus.shutdown()
    print("backup: median %.2f s, %.2f to %.2f s over %d runs" % (statistics.median(seconds), min(seconds),
                                                                  max(seconds), len(seconds)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
