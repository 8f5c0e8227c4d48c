#!/usr/bin/env python3
"""SYNC period jitter on SocketCAN beside the same kernel's timer floor,
at the same load (a benchmark).

Needs a SocketCAN interface (vcan0): run it where one exists, e.g. inside
user-mode Linux:

    tools/vcan_run.sh .venv/bin/python maxon_epos4_ros_canopen/benchmarks/sync_jitter.py \\
        [--seconds 10] [--hogs 2] [--rounds 1] [--overflow 0] [--plot F.png] [--json F.json]

For each load (idle, then ``--hogs`` busy-looping processes) and round:

* ``thread``: SyncProducer.start(period, kernel=False), python-can's sender thread;
* ``BCM``: SyncProducer.start(period), the kernel's broadcast manager;
* ``driver``: the shipped CSP example's layers (canopen_bus_layer.yaml,
  controller_2dof_csp.yaml, node_layer_2dof_csp.yaml) in a Driver on the
  interface, with two virtual EPOS4 in this process, after init: SYNC as
  the example sends it (``sync/kernel_timer`` default);

a second socket receives the SYNCs and the kernel's receive timestamps give
the periods. Beside each, for the same seconds, the timer floor: a C loop
compiled here at run time (what cyclictest measures: clock_nanosleep to an
absolute time every period, SCHED_FIFO where permitted), its wake-up
latency and its own periods' |period - T|. The ratio is SYNC p99 |period -
T| over the floor's p99 |period - T| in the same run. The kernel measured is
printed (release, and whether it is user-mode Linux). The hogs are
``yes > /dev/null`` processes.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from typing import Dict, List, Optional

import can

PKG = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
sys.path.insert(0, os.path.join(PKG, "src"))
from maxon_epos4_ros_canopen.driver.bus import SYNC_COB_ID, SyncProducer  # noqa: E402

HOG = ["yes"]  # stdout to /dev/null: one CPU hog each, as `yes > /dev/null`
MODES = ("floor", "BCM", "thread", "driver")
COLOURS = {"floor": "tab:green", "BCM": "tab:blue", "thread": "tab:orange", "driver": "tab:purple"}

# The timer floor: what cyclictest measures, as a C loop (no Python in the
# way), compiled at run time so the benchmark needs only a C compiler.
FLOOR_C = r"""
#define _GNU_SOURCE
#include <sched.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
int main(int argc, char **argv) {
    long period = atol(argv[1]), loops = atol(argv[2]);
    int prio = argc > 3 ? atoi(argv[3]) : 0;
    if (prio > 0) {
        struct sched_param p = {.sched_priority = prio};
        if (sched_setscheduler(0, SCHED_FIFO, &p) != 0) fprintf(stderr, "no SCHED_FIFO\n");
        else fprintf(stderr, "SCHED_FIFO %d\n", prio);
    }
    struct timespec next, now;
    clock_gettime(CLOCK_MONOTONIC, &next);
    for (long i = 0; i < loops; i++) {
        next.tv_nsec += period;
        while (next.tv_nsec >= 1000000000L) { next.tv_nsec -= 1000000000L; next.tv_sec++; }
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &next, NULL);
        clock_gettime(CLOCK_MONOTONIC, &now);
        printf("%ld\n", (now.tv_sec - next.tv_sec) * 1000000000L + (now.tv_nsec - next.tv_nsec));
    }
    return 0;
}
"""


def kernel() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            uml = "User Mode Linux" in f.read() or "UML" in platform.version()
    except OSError:
        uml = False
    return "Linux %s%s" % (platform.release(), ", user-mode Linux" if uml else "")


def compile_floor(workdir: str) -> str:
    src, exe = os.path.join(workdir, "timer_floor.c"), os.path.join(workdir, "timer_floor")
    with open(src, "w") as f:
        f.write(FLOOR_C)
    subprocess.run(["cc", "-O2", "-o", exe, src], check=True)
    return exe


def deviations(periods_ms: List[float], period: float) -> Dict:
    dev = sorted(abs(p - period * 1000.0) for p in periods_ms)
    if not dev:
        return {"periods": 0, "mean_ms": float("nan"), "p99_dev_ms": float("nan"), "max_dev_ms": float("nan")}
    return {"periods": len(periods_ms), "mean_ms": statistics.mean(periods_ms),
            "p99_dev_ms": dev[int(0.99 * (len(dev) - 1))], "max_dev_ms": dev[-1]}


class Floor:
    """The C timer loop in the background for ``seconds``."""

    def __init__(self, exe: str, period: float, seconds: float, priority: int) -> None:
        loops = max(2, int(seconds / period))
        self.proc = subprocess.Popen([exe, str(int(period * 1e9)), str(loops), str(priority)],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.period = period

    def result(self) -> Dict:
        out, err = self.proc.communicate()
        lat_ms = [int(x) / 1e6 for x in out.split()]
        periods = [self.period * 1000.0 + b - a for a, b in zip(lat_ms, lat_ms[1:])]
        r = deviations(periods, self.period)
        lat = sorted(lat_ms)
        r.update({"mode": "floor", "p99_latency_ms": lat[int(0.99 * (len(lat) - 1))] if lat else float("nan"),
                  "fifo": "SCHED_FIFO" in err, "periods_ms": periods})
        return r


def record(channel: str, seconds: float) -> List[float]:
    rx = can.Bus(interface="socketcan", channel=channel,
                 can_filters=[{"can_id": SYNC_COB_ID, "can_mask": 0x7FF, "extended": False}])
    stamps = []
    try:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            msg = rx.recv(0.5)
            if msg is not None and msg.arbitration_id == SYNC_COB_ID:
                stamps.append(msg.timestamp)
    finally:
        rx.shutdown()
    return [(b - a) * 1000.0 for a, b in zip(stamps, stamps[1:])]


def measure_producer(channel: str, kernel_timer: bool, period: float, seconds: float, overflow: int) -> Dict:
    tx = can.Bus(interface="socketcan", channel=channel)
    sync = SyncProducer(tx, overflow)
    try:
        sync.start(period, kernel=kernel_timer)
        periods = record(channel, seconds)
        timed = sync.kernel_timed
    finally:
        sync.stop()
        tx.shutdown()
    r = deviations(periods, period)
    r.update({"mode": "BCM" if timed else "thread", "periods_ms": periods})
    return r


def measure_driver(channel: str, seconds: float) -> Dict:
    """The shipped CSP example's driver (its three layers) on ``channel``."""
    import yaml
    from maxon_epos4_ros_canopen.config import load_config
    from maxon_epos4_ros_canopen.driver import Driver
    from maxon_epos4_ros_canopen.sim import NodeConfig, Simulator

    config = os.path.join(PKG, "config")
    params: Dict = {}
    for name in ("canopen_bus_layer.yaml", "controller_2dof_csp.yaml", "node_layer_2dof_csp.yaml"):
        with open(os.path.join(config, name)) as f:
            params.update(yaml.safe_load(f))
    params["bus"]["device"] = channel
    # the drives watch the master's heartbeat for 2 s: the hogs may starve
    # this process's heartbeat thread, and a stopped drive sends no TxPDOs
    params["defaults"]["dcf_overlay"]["1016sub1"] = "0x007F07D0"
    sim_bus = can.Bus(interface="socketcan", channel=channel)
    sim = Simulator(sim_bus, [NodeConfig(1, os.path.join(config, "epos4_node1.dcf")),
                              NodeConfig(2, os.path.join(config, "epos4_node2.dcf"))], tick=0.002).start()
    driver = Driver(load_config(params, "sync_jitter", lambda pkg: PKG))
    try:
        r = driver.init()
        if not r.success:
            raise RuntimeError("driver init: %s" % r.message)
        periods = record(channel, seconds)
        timed = driver.sync is not None and driver.sync.kernel_timed
        fifo = getattr(driver, "realtime", None)
    finally:
        driver.shutdown()
        driver.close()
        sim.stop()
        sim_bus.shutdown()
    out = deviations(periods, 0.010)
    out.update({"mode": "driver", "kernel_timed": timed, "cycle_fifo": bool(fifo and fifo.fifo),
                "periods_ms": periods})
    return out


def plot(path: str, results: List[Dict], loads: List[int], period: float, title: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(loads), figsize=(5 * len(loads), 4), squeeze=False)
    for ax, load in zip(axes[0], loads):
        for n, mode in enumerate(MODES):
            v = [r["p99_dev_ms"] for r in results if r["hogs"] == load and r["mode"] == mode]
            if not v:
                continue
            mid = statistics.median(v)
            ax.bar(n, mid, color=COLOURS[mode], label=mode, yerr=[[mid - min(v)], [max(v) - mid]], capsize=4)
        ax.set_xticks(range(len(MODES)))
        ax.set_xticklabels(MODES)
        ax.set_ylim(bottom=0)
        ax.set_ylabel("p99 |period - %g ms| (ms); bar: min-max over rounds" % (period * 1000))
        ax.set_title("%d hog(s)" % load)
        ax.legend()
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path)
    print("plot: %s" % path)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--channel", default="vcan0")
    ap.add_argument("--period", type=float, default=0.01, help="s (default %(default)s)")
    ap.add_argument("--seconds", type=float, default=10.0, help="per mode, load and round")
    ap.add_argument("--hogs", type=int, default=2, help="busy processes for the loaded runs")
    ap.add_argument("--rounds", type=int, default=1)
    ap.add_argument("--overflow", type=int, default=0, help="SYNC counter overflow (0: no counter)")
    ap.add_argument("--floor-priority", type=int, default=80,
                    help="SCHED_FIFO priority of the timer loop where permitted (0: normal)")
    ap.add_argument("--no-driver", action="store_true", help="leave out the shipped CSP driver")
    ap.add_argument("--plot", help="write a PNG here")
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args()
    results = []
    loads = [0, args.hogs] if args.hogs else [0]
    with tempfile.TemporaryDirectory() as tmp:
        exe = compile_floor(tmp)
        for k in range(args.rounds):
            for load in loads:
                hogs = [subprocess.Popen(HOG, stdout=subprocess.DEVNULL) for _ in range(load)]
                try:
                    time.sleep(0.2 if load else 0)
                    runs = [lambda: measure_producer(args.channel, False, args.period, args.seconds, args.overflow),
                            lambda: measure_producer(args.channel, True, args.period, args.seconds, args.overflow)]
                    if not args.no_driver:
                        runs.append(lambda: measure_driver(args.channel, args.seconds))
                    for run in runs:
                        floor = Floor(exe, args.period, args.seconds, args.floor_priority)
                        try:
                            r = run()
                        except Exception as e:  # a mode that cannot run is a line saying why
                            r = {"mode": "error", "error": str(e)}
                        f = floor.result()
                        for x in (r, f):
                            x.update({"hogs": load, "round": k + 1})
                        r["floor_p99_dev_ms"] = f["p99_dev_ms"]
                        results += [f, r]
                finally:
                    for h in hogs:
                        h.terminate()
                    for h in hogs:
                        h.wait()
    print("SYNC every %.3g ms on %s, %s, %d CPU(s), %.0f s per run, %d round(s), overflow %d"
          % (args.period * 1000, args.channel, kernel(), os.cpu_count() or 0, args.seconds, args.rounds,
             args.overflow))
    print("%-7s %5s %5s %8s %10s %12s %12s %14s %9s" % ("mode", "hogs", "round", "periods", "mean ms",
                                                      "p99 |dev| ms", "max |dev| ms", "floor p99 ms", "ratio"))
    for r in results:
        if r["mode"] == "error":
            print("error  %5d %5d  %s" % (r["hogs"], r["round"], r["error"]))
            continue
        if r["mode"] == "floor":
            print("%-7s %5d %5d %8d %10.4f %12.4f %12.4f %14s %9s   (wake-up latency p99 %.3f ms, %s)" % (
                "floor", r["hogs"], r["round"], r["periods"], r["mean_ms"], r["p99_dev_ms"], r["max_dev_ms"], "",
                "", r["p99_latency_ms"], "SCHED_FIFO" if r["fifo"] else "SCHED_OTHER"))
            continue
        ratio = r["p99_dev_ms"] / r["floor_p99_dev_ms"] if r["floor_p99_dev_ms"] > 0 else float("nan")
        print("%-7s %5d %5d %8d %10.4f %12.4f %12.4f %14.4f %9.2f" % (
            r["mode"], r["hogs"], r["round"], r["periods"], r["mean_ms"], r["p99_dev_ms"], r["max_dev_ms"],
            r["floor_p99_dev_ms"], ratio))
    print("ratio: SYNC p99 |period - T| / the timer floor's p99 |period - T| in the same seconds "
          "(target: at most 2 with two hogs)")
    if args.plot:
        plot(args.plot, [r for r in results if r["mode"] != "error"], loads, args.period,
             "SYNC beside the timer floor, %s" % kernel())
    if args.json:
        os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
        with open(args.json, "w") as f:
            json.dump({"period_ms": args.period * 1000, "kernel": kernel(),
                       "runs": [r for r in results if r["mode"] != "error"]}, f)
    return 0


if __name__ == "__main__":
    sys.exit(main())
