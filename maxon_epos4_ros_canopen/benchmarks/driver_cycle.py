#!/usr/bin/env python3
"""CPU cost of the driver's per-SYNC cycle and of its TPDO reception, per axis.

Runs N simulated EPOS4 nodes and the driver in one process on python-can's
virtual bus, CSP mode with a moving target set by a cycle callback (the
trajectory path), and prints, per axis count:

* cycle CPU: CPU time of the cycle thread per cycle (time.thread_time, so
  time spent waiting for the GIL held by the simulator is not counted);
* receive CPU: CPU time of the driver's CAN notifier thread per cycle (from
  /proc, clock ticks: coarse, meaningful over the whole run).

``--compare REV`` runs the same measurement on the driver of git revision
REV (checked out into a temporary worktree) in a subprocess right after,
and prints the ratio now/REV for each axis count. With ``--repeat N`` both
drivers run in subprocesses, N rounds alternating which goes first, and the
medians are printed: the ratio of one round swings with the machine's load,
the median of several much less.

    PYTHONPATH=maxon_epos4_ros_canopen/src .venv/bin/python \\
        maxon_epos4_ros_canopen/benchmarks/driver_cycle.py [--compare REV [--repeat N]] [--seconds S] [AXES ...]
"""
import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time

import can

from maxon_epos4_ros_canopen.config import load_config
from maxon_epos4_ros_canopen.driver import Driver
from maxon_epos4_ros_canopen.sim.runner import NodeConfig, Simulator

HERE = os.path.dirname(os.path.abspath(__file__))
DCF = os.path.join(HERE, "..", "config", "epos4_node1.dcf")
REPO = os.path.normpath(os.path.join(HERE, "..", ".."))
TICK = os.sysconf("SC_CLK_TCK")


def thread_cpu(native_id: int) -> float:
    """CPU seconds of one thread of this process, from /proc."""
    with open("/proc/self/task/%d/stat" % native_id) as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK


def run(axes: int, seconds: float) -> dict:
    channel = "bench_cycle_%d_%d" % (axes, os.getpid())
    sim_bus = can.Bus(interface="virtual", channel=channel)
    sim = Simulator(sim_bus, [NodeConfig(i, DCF) for i in range(1, axes + 1)]).start()
    params = {"bus": {"device": "virtual:" + channel}, "sync": {"interval_ms": 10},
              "nodes": [{"id": i, "name": "j%d" % i, "eds_file": DCF} for i in range(1, axes + 1)],
              "defaults": {"pos_to_device": "rint(pos*3200/(2*pi))", "pos_from_device": "obj6064*2*pi/3200",
                           "vel_to_device": "rint(vel)", "vel_from_device": "obj606C",
                           "eff_to_device": "rint(eff)", "eff_from_device": "0"}}
    driver = Driver(load_config(params, "benchmark"))
    cpu = []
    # the object whose cycle() the cycle thread runs (the driver itself before it was split)
    cycler = getattr(driver, "_cycle", driver)
    inner = cycler.cycle

    def timed() -> None:
        t0 = time.thread_time()
        inner()
        cpu.append(time.thread_time() - t0)
    cycler.cycle = timed
    try:
        r = driver.init()
        assert r.success, r.message
        names = list(driver.joints)
        r = driver.switch_mode(names, 8)
        assert r.success, r.message
        t_start = time.monotonic()

        def trajectory(d: Driver) -> None:
            t = time.monotonic() - t_start
            for name in names:
                d.set_command(name, "position", 0.5 * t)
        driver.add_cycle_callback(trajectory)
        notifier = [t for t in driver.network.notifier._readers if isinstance(t, threading.Thread)][0]
        time.sleep(0.5)
        del cpu[:]
        rx0 = thread_cpu(notifier.native_id)
        time.sleep(seconds)
        rx = thread_cpu(notifier.native_id) - rx0
        samples = sorted(cpu)
        return {"axes": axes, "cycles": len(samples), "cycle_us": statistics.mean(samples) * 1e6,
                "cycle_p99_us": samples[int(0.99 * (len(samples) - 1))] * 1e6,
                "receive_us": rx / max(1, len(samples)) * 1e6, "overruns": driver.overruns}
    finally:
        driver.close()
        sim.stop()
        sim_bus.shutdown()


def show(label: str, res: dict) -> None:
    n = res["axes"]
    print("%-10s axes %3d: %5d cycles, cycle CPU %7.0f us (%5.1f us/axis, p99 %6.0f us), "
          "receive CPU %6.0f us (%5.1f us/axis), overruns %d" % (
              label, n, res["cycles"], res["cycle_us"], res["cycle_us"] / n, res["cycle_p99_us"],
              res["receive_us"], res["receive_us"] / n, res["overruns"]))


def measure(src: str, axes: list, seconds: float) -> list:
    """This measurement in a subprocess, on the driver under ``src``."""
    env = dict(os.environ, PYTHONPATH=src)
    out = subprocess.run([sys.executable, os.path.abspath(__file__), "--json", "--seconds", str(seconds)]
                         + [str(a) for a in axes], env=env, check=True, stdout=subprocess.PIPE).stdout
    return json.loads(out.decode().strip().splitlines()[-1])


def compare(rev: str, axes: list, seconds: float, repeat: int = 0) -> list:
    """The same measurement on the driver of git revision rev; with repeat,
    [(now, rev)] for each of ``repeat`` rounds, alternating the order."""
    with tempfile.TemporaryDirectory() as tmp:
        tree = os.path.join(tmp, "tree")
        subprocess.run(["git", "-C", REPO, "worktree", "add", "--detach", tree, rev], check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            old_src = os.path.join(tree, "maxon_epos4_ros_canopen", "src")
            if not repeat:
                return measure(old_src, axes, seconds)
            now_src = os.path.join(REPO, "maxon_epos4_ros_canopen", "src")
            rounds = []
            for k in range(repeat):
                if k % 2 == 0:
                    now = measure(now_src, axes, seconds)
                    old = measure(old_src, axes, seconds)
                else:
                    old = measure(old_src, axes, seconds)
                    now = measure(now_src, axes, seconds)
                rounds.append((now, old))
                print("round %d/%d: cycle CPU now/%s %s" % (k + 1, repeat, rev[:10], ", ".join(
                    "%d axes %.2f" % (n["axes"], n["cycle_us"] / o["cycle_us"]) for n, o in zip(now, old))),
                    flush=True)
            return rounds
        finally:
            subprocess.run(["git", "-C", REPO, "worktree", "remove", "--force", tree], check=False)


def show_rounds(rev: str, rounds: list) -> None:
    """Medians over the rounds: each driver's cycle and receive CPU, and the
    median of the per-round ratios."""
    med = statistics.median
    print("median of %d rounds (cycle CPU us now / %s, ratio; receive ratio; cycle + receive ratio):"
          % (len(rounds), rev[:10]))
    for i, first in enumerate(rounds[0][0]):
        now = [r[0][i] for r in rounds]
        old = [r[1][i] for r in rounds]
        ratio = med([n["cycle_us"] / o["cycle_us"] for n, o in zip(now, old)])
        rx = med([n["receive_us"] / o["receive_us"] for n, o in zip(now, old) if o["receive_us"]] or [float("nan")])
        both = med([(n["cycle_us"] + n["receive_us"]) / (o["cycle_us"] + o["receive_us"]) for n, o in zip(now, old)])
        print("  axes %3d: cycle CPU %7.0f / %7.0f us, ratio %.2f (rounds %s); receive %.2f; cycle + receive %.2f"
              % (first["axes"], med([n["cycle_us"] for n in now]), med([o["cycle_us"] for o in old]), ratio,
                 " ".join("%.2f" % (n["cycle_us"] / o["cycle_us"]) for n, o in zip(now, old)), rx, both))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("axes", nargs="*", type=int, default=[1, 8, 32])
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--compare", metavar="REV", help="also measure the driver of this git revision")
    parser.add_argument("--repeat", type=int, default=0, metavar="N",
                        help="with --compare: N rounds, both drivers in subprocesses, order alternating; medians")
    parser.add_argument("--json", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.compare and args.repeat > 0:
        show_rounds(args.compare, compare(args.compare, args.axes, args.seconds, args.repeat))
        return 0
    results = [run(n, args.seconds) for n in args.axes]
    if args.json:
        print(json.dumps(results))
        return 0
    for res in results:
        show("now", res)
    if args.compare:
        before = compare(args.compare, args.axes, args.seconds)
        for res in before:
            show(args.compare[:10], res)
        print("ratio now/%s:" % args.compare)
        for now, old in zip(results, before):
            print("  axes %3d: cycle CPU %.2f, receive CPU %.2f, cycle + receive %.2f" % (
                now["axes"], now["cycle_us"] / old["cycle_us"],
                now["receive_us"] / old["receive_us"] if old["receive_us"] else float("nan"),
                (now["cycle_us"] + now["receive_us"]) / (old["cycle_us"] + old["receive_us"])))
    return 0


if __name__ == "__main__":
    sys.exit(main())
