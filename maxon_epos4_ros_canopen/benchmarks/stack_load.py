#!/usr/bin/env python3
"""How much of a CPU the driver and the virtual EPOS4 take between them on
a SocketCAN bus, and how often each of their threads is switched out (a
benchmark; needs vcan0):

    tools/vcan_run.sh .venv/bin/python maxon_epos4_ros_canopen/benchmarks/stack_load.py [--axes 2] [--seconds 8]

Two processes, as a user runs them: the virtual EPOS4 (the
``virtual_epos4`` command line) and a driver (Driver over the bus, init,
CSP, a new target for every axis every 10 ms cycle; no ROS). The figures:

* this machine's floor: a thread handoff (two threads passing a message
  back and forth through a queue: futex and GIL) and a process handoff (a
  pipe round trip), each one way, and a clock read;
* each thread's voluntary and involuntary context switches per SYNC
  (``/proc/PID/task/TID/status``), by thread name;
* the CPU the two processes take, read as the capacity a pure-Python loop
  loses beside them. Per-process CPU accounting is coarse in user-mode
  Linux, so capacity is what is compared;
* beside it, how the kernel splits CPU time between the simulator and the
  driver (``/proc/PID/stat``; sampled at the timer tick in user-mode Linux,
  so the split, not the total, is what it tells).

Where a system call or a context switch costs a hundred times what it
costs natively (user-mode Linux: every one is a ptrace round trip), the
switches per SYNC times the handoff cost is most of the stack's CPU.
Figures depend on the machine and its load: compare runs on one machine.
"""
from __future__ import annotations

import argparse
import json
import os
import queue
import subprocess
import sys
import threading
import time
from typing import Dict, Tuple

from cycle_cpu import DCF, HERE, PERIOD, UNITS, sine_targets, thread_label  # this folder's


def floor(rounds: int = 2000) -> Dict[str, float]:
    """One-way handoff costs and a clock read on this machine, in µs."""
    there, back = queue.SimpleQueue(), queue.SimpleQueue()

    def echo() -> None:
        for _ in range(rounds):
            back.put(there.get())
    t = threading.Thread(target=echo)
    t.start()
    t0 = time.perf_counter()
    for i in range(rounds):
        there.put(i)
        back.get()
    thread_rt = time.perf_counter() - t0
    t.join()
    r1, w1 = os.pipe()
    r2, w2 = os.pipe()
    pid = os.fork()
    if pid == 0:
        for _ in range(rounds):
            os.read(r1, 1)
            os.write(w2, b"x")
        os._exit(0)
    t0 = time.perf_counter()
    for _ in range(rounds):
        os.write(w1, b"x")
        os.read(r2, 1)
    process_rt = time.perf_counter() - t0
    os.waitpid(pid, 0)
    for fd in (r1, w1, r2, w2):
        os.close(fd)
    t0 = time.perf_counter()
    for _ in range(rounds):
        time.monotonic()
    clock = time.perf_counter() - t0
    return {"thread_handoff_us": thread_rt / rounds / 2 * 1e6, "process_handoff_us": process_rt / rounds / 2 * 1e6,
            "clock_read_us": clock / rounds * 1e6}


def capacity(seconds: float) -> float:
    """Iterations a second of a pure-Python loop: what this process gets of a CPU."""
    n = 0
    end = time.monotonic() + seconds
    while True:
        for _ in range(20000):
            n += 1
        if time.monotonic() > end:
            return n / seconds


def run_driver(channel: str, axes: int) -> None:
    """The driver process: init, CSP, a moving target every cycle, until killed.
    Prints one JSON line with its threads' names by native id once moving."""
    from maxon_epos4_ros_canopen.config import load_config
    from maxon_epos4_ros_canopen.driver import Driver

    defaults = dict(UNITS, eds_file=DCF, pdo_layout="compact", modes=["CSP"])
    # SCHED_FIFO off: a cycle thread above the simulator on the same CPU
    # would take the CPU the simulated drives need once its work nears the
    # period, and the figure is what the work costs, not who waits
    params = {"realtime": {"enabled": False}, "bus": {"device": channel}, "sync": {"interval_ms": PERIOD * 1000},
              "nodes": [{"id": i, "name": "j%d" % i} for i in range(1, axes + 1)], "defaults": defaults}
    driver = Driver(load_config(params, "stack_load"), state_timeout=30.0, sdo_timeout=5.0)
    names = list(driver.joints)
    for step, r in (("init", driver.init), ("switch to CSP", lambda: driver.switch_mode(names, 8))):
        result = r()
        if not result.success:
            print(json.dumps({"ok": False, "error": "%s: %s" % (step, result.message)}), flush=True)
            driver.close()
            return
    driver.add_cycle_callback(sine_targets(names))
    threads = {str(t.native_id): thread_label(t.name) for t in threading.enumerate() if t.native_id is not None}
    print(json.dumps({"ok": True, "threads": threads}), flush=True)
    threading.Event().wait()


def switches(pid: int) -> Dict[str, Tuple[int, int]]:
    """(voluntary, involuntary) context switches of each thread of ``pid``."""
    out = {}
    try:
        tids = os.listdir("/proc/%d/task" % pid)
    except OSError:
        return out
    for tid in tids:
        try:
            with open("/proc/%d/task/%s/status" % (pid, tid)) as f:
                fields = dict(line.split(":", 1) for line in f if "ctxt_switches" in line)
        except OSError:
            continue
        out[tid] = (int(fields["voluntary_ctxt_switches"]), int(fields["nonvoluntary_ctxt_switches"]))
    return out


def cpu_ticks(pid: int) -> int:
    """User plus system CPU time of process ``pid`` so far, in clock ticks."""
    try:
        with open("/proc/%d/stat" % pid) as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return 0
    return int(fields[11]) + int(fields[12])  # utime, stime (fields 14 and 15)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--axes", type=int, default=2)
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--channel", default="vcan0")
    ap.add_argument("--role", default="", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.role == "driver":
        run_driver(args.channel, args.axes)
        return 0
    costs = floor()
    print("this machine: thread handoff %.1f µs, process handoff %.1f µs, clock read %.2f µs" % (
        costs["thread_handoff_us"], costs["process_handoff_us"], costs["clock_read_us"]))
    alone = capacity(args.seconds)
    sim = subprocess.Popen([sys.executable, os.path.join(HERE, "..", "scripts", "virtual_epos4"),
                            "--interface", "socketcan", "--channel", args.channel]
                           + [a for i in range(1, args.axes + 1) for a in ("--node", "%d:%s" % (i, DCF))],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    driver = subprocess.Popen([sys.executable, os.path.abspath(__file__), "--role", "driver", "--channel",
                               args.channel, "--axes", str(args.axes)], stdout=subprocess.PIPE, text=True)
    try:
        line = driver.stdout.readline() if driver.stdout is not None else ""
        started = json.loads(line) if line.startswith("{") else {"ok": False, "error": "driver ended: %r" % line}
        if not started.get("ok"):
            print("the driver did not start: %s" % started.get("error"))
            return 1
        names: Dict[str, Dict[str, str]] = {"sim": {}, "driver": started["threads"]}
        time.sleep(1.0)  # settle: targets moving
        before = {"sim": switches(sim.pid), "driver": switches(driver.pid)}
        ticks0 = {"sim": cpu_ticks(sim.pid), "driver": cpu_ticks(driver.pid)}
        loaded = capacity(args.seconds)
        ticks = {"sim": cpu_ticks(sim.pid) - ticks0["sim"], "driver": cpu_ticks(driver.pid) - ticks0["driver"]}
        after = {"sim": switches(sim.pid), "driver": switches(driver.pid)}
    finally:
        for p in (driver, sim):
            p.terminate()
        for p in (driver, sim):
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
    syncs = args.seconds / PERIOD
    print("\n%d axes, compact CSP, SYNC every %g ms, %g s:" % (args.axes, PERIOD * 1000, args.seconds))
    print("  %-10s %-20s %10s %12s" % ("process", "thread", "vol/SYNC", "invol/SYNC"))
    total = 0.0
    for proc in ("driver", "sim"):
        for tid, (v1, i1) in sorted(after[proc].items()):
            v0, i0 = before[proc].get(tid, (v1, i1))
            vol, invol = (v1 - v0) / syncs, (i1 - i0) / syncs
            total += vol + invol
            if vol + invol >= 0.05:
                label = names[proc].get(tid, "loop" if proc == "sim" and tid == str(sim.pid) else "thread %s" % tid)
                print("  %-10s %-20s %10.2f %12.2f" % (proc, label, vol, invol))
    print("  context switches per SYNC, all threads: %.1f; at this machine's thread handoff: %.1f ms per %g ms" % (
        total, total * costs["thread_handoff_us"] / 1000.0, PERIOD * 1000))
    print("  CPU taken by driver and simulator: %.0f%% of one CPU (a loop's capacity %.3g/s alone, %.3g/s beside)"
          % (100.0 * (1.0 - loaded / alone), alone, loaded))
    hz = os.sysconf("SC_CLK_TCK")
    print("  the kernel's accounting: simulator %.0f%%, driver %.0f%% of one CPU" % (
        100.0 * ticks["sim"] / hz / args.seconds, 100.0 * ticks["driver"] / hz / args.seconds))
    return 0


if __name__ == "__main__":
    sys.exit(main())
