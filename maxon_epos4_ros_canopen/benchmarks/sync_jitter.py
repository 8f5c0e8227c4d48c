#!/usr/bin/env python3
"""SYNC period jitter on SocketCAN: python-can's sender thread against the
kernel's broadcast manager (BCM), idle and with CPU hogs (a benchmark).

Needs a SocketCAN interface (vcan0): run it where one exists, e.g. inside
user-mode Linux:

    tools/vcan_run.sh .venv/bin/python maxon_epos4_ros_canopen/benchmarks/sync_jitter.py \\
        [--seconds 10] [--hogs 2] [--overflow 0] [--json .results/bench/sync_jitter.json]

SyncProducer.start(period) is run with kernel=False (thread) and kernel=True
(BCM); a second socket receives the SYNCs and the kernel's receive
timestamps give the periods. Prints, per mode and load, the periods' mean
and standard deviation and the 99th percentile and maximum of
|period - nominal|. The hogs are busy-looping child processes.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

import can

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "src"))
from maxon_epos4_ros_canopen.driver.bus import SYNC_COB_ID, SyncProducer  # noqa: E402

HOG = "while True: pass"


def measure(channel: str, kernel: bool, period: float, seconds: float, overflow: int) -> dict:
    tx = can.Bus(interface="socketcan", channel=channel)
    rx = can.Bus(interface="socketcan", channel=channel,
                 can_filters=[{"can_id": SYNC_COB_ID, "can_mask": 0x7FF, "extended": False}])
    sync = SyncProducer(tx, overflow)
    stamps, counters = [], []
    try:
        sync.start(period, kernel=kernel)
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            msg = rx.recv(0.5)
            if msg is not None and msg.arbitration_id == SYNC_COB_ID:
                stamps.append(msg.timestamp)
                counters.append(msg.data[0] if msg.dlc else 0)
        kernel_timed = sync.kernel_timed
    finally:
        sync.stop()
        tx.shutdown()
        rx.shutdown()
    periods = [(b - a) * 1000.0 for a, b in zip(stamps, stamps[1:])]
    dev = sorted(abs(p - period * 1000.0) for p in periods)
    counter_ok = all(b == a % overflow + 1 for a, b in zip(counters, counters[1:])) if overflow else True
    return {"mode": "BCM" if kernel_timed else "thread", "periods": len(periods),
            "mean_ms": statistics.mean(periods), "std_ms": statistics.pstdev(periods),
            "p99_dev_ms": dev[int(0.99 * (len(dev) - 1))], "max_dev_ms": dev[-1],
            "counter_sequence_ok": counter_ok, "periods_ms": periods}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--channel", default="vcan0")
    ap.add_argument("--period", type=float, default=0.01, help="s (default %(default)s)")
    ap.add_argument("--seconds", type=float, default=10.0, help="per mode and load")
    ap.add_argument("--hogs", type=int, default=2, help="busy processes for the loaded runs")
    ap.add_argument("--overflow", type=int, default=0, help="SYNC counter overflow (0: no counter)")
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args()
    results = []
    for load in (0, args.hogs):
        hogs = [subprocess.Popen([sys.executable, "-c", HOG]) for _ in range(load)]
        try:
            time.sleep(0.2 if load else 0)
            for kernel in (False, True):
                r = measure(args.channel, kernel, args.period, args.seconds, args.overflow)
                r["hogs"] = load
                results.append(r)
        finally:
            for h in hogs:
                h.terminate()
            for h in hogs:
                h.wait()
    print("SYNC every %.3g ms on %s, %d CPU(s), %.0f s per run, overflow %d"
          % (args.period * 1000, args.channel, os.cpu_count() or 0, args.seconds, args.overflow))
    print("%-7s %5s %8s %10s %9s %12s %12s %8s" % ("mode", "hogs", "periods", "mean ms", "std ms",
                                                   "p99 |dev| ms", "max |dev| ms", "counter"))
    for r in results:
        print("%-7s %5d %8d %10.4f %9.4f %12.4f %12.4f %8s" % (
            r["mode"], r["hogs"], r["periods"], r["mean_ms"], r["std_ms"], r["p99_dev_ms"], r["max_dev_ms"],
            "ok" if r["counter_sequence_ok"] else "WRONG"))
    if args.json:
        os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
        with open(args.json, "w") as f:
            json.dump({"period_ms": args.period * 1000, "runs": results}, f)
    return 0


if __name__ == "__main__":
    sys.exit(main())
