#!/usr/bin/env python3
"""A soak run: 8 drives in CSP for a long time, memory and SYNC gaps (a
benchmark, not a test).

    .venv/bin/python maxon_epos4_ros_canopen/benchmarks/soak.py [--seconds 3600] [--axes 8]
        [--every 10] [--plot soak.png] [--json soak.json]

The driver (compact CSP layout, velocity every 5th SYNC, 10 ms SYNC,
master heartbeat 20 Hz, as the shipped CSP example) and the virtual EPOS4
in this process on a python-can virtual channel; every cycle a new target
position for every axis (a slow sine). First half: CSP only. Second half:
``halt`` then ``recover`` every ``--every`` s (and back to CSP).

Every ``--every`` s the process's RSS (VmRSS; the simulator is in this
process too) is sampled. The driver's bus takes every SYNC's send time
(monotonic) and lists each gap over 3 periods with its time and its
cause: at every SYNC it also takes what the kernel counts (GapWitness):
each thread's time on a CPU and waiting for one
(/proc/self/task/*/schedstat), the time the hypervisor ran other guests
on this machine's CPUs (steal, /proc/stat) and the wall clock's offset
from the monotonic one. A gap is explained from the difference between
the SYNCs around it, next to a halt/recover under way and a garbage
collection (gc.callbacks). Prints the RSS samples, the RSS growth
per hour in each phase (least squares over the samples after the first
minute of the phase), the gaps with their causes, and the object types
whose count grew most over the halt/recover phase.
"""
from __future__ import annotations

import argparse
import gc
import json
import math
import os
import sys
import threading
import time
from array import array
from collections import Counter
from typing import Dict, List, NamedTuple, Optional, Tuple

import can

PKG = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
sys.path.insert(0, os.path.join(PKG, "src"))
from maxon_epos4_ros_canopen.config import load_config  # noqa: E402
from maxon_epos4_ros_canopen.driver import Driver  # noqa: E402
from maxon_epos4_ros_canopen.sim import NodeConfig, Simulator  # noqa: E402

DCF = os.path.join(PKG, "config", "epos4_node1.dcf")
PERIOD = 0.010
SYNC_ID = 0x080
GAP_PERIODS = 3


def rss_kb() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    return 0


def slope_kb_per_h(samples: List[Tuple[float, int]]) -> float:
    """Least-squares slope of (s, kB) samples, in kB per hour (NaN: too few)."""
    if len(samples) < 3:
        return math.nan
    n = len(samples)
    mt = sum(t for t, _ in samples) / n
    mr = sum(r for _, r in samples) / n
    var = sum((t - mt) ** 2 for t, _ in samples)
    return 3600.0 * sum((t - mt) * (r - mr) for t, r in samples) / var if var else math.nan


CYCLE_THREAD = "epos4_driver_cycle"  # the name the driver's clock gives the cycle thread
_NS = 1e-9


class Sample(NamedTuple):
    """What the kernel had counted at one SYNC (see GapWitness)."""
    steal_s: float                         # every CPU's steal time, summed
    wall_offset_s: float                   # time.time() - time.monotonic()
    threads: Dict[int, Tuple[int, int]]    # native thread id -> (ns on a CPU, ns runnable waiting for one)


class GapWitness:
    """Takes a Sample at every SYNC and explains a gap from the two around
    it. Linux counts, per thread, the time it ran and the time it was
    runnable but waited for a CPU (schedstat); what is left of a gap is
    time the thread was blocked (a lock, the GIL, a sleep). The hypervisor's
    steal time says the whole virtual machine did not run. The wall
    clock's offset tells a step of the clock the frames are stamped with.

    The files stay open and are read with pread, so a sample costs a few
    system calls, not an open and close per thread."""

    def __init__(self) -> None:
        self._fds: Dict[int, int] = {}
        self._stat = os.open("/proc/stat", os.O_RDONLY)
        self._hz = float(os.sysconf("SC_CLK_TCK"))
        self.names: Dict[int, str] = {}

    def sample(self) -> Sample:
        threads = {}
        for name in os.listdir("/proc/self/task"):
            tid = int(name)
            fd = self._fds.get(tid)
            try:
                if fd is None:
                    fd = self._fds[tid] = os.open("/proc/self/task/%d/schedstat" % tid, os.O_RDONLY)
                on_cpu, waiting, _ = os.pread(fd, 128, 0).split()
            except (OSError, ValueError):  # the thread ended meanwhile
                if fd is not None:
                    os.close(self._fds.pop(tid))
                continue
            threads[tid] = (int(on_cpu), int(waiting))
        for tid in [t for t in self._fds if t not in threads]:
            os.close(self._fds.pop(tid))
        cpu = os.pread(self._stat, 256, 0).split(b"\n", 1)[0].split()
        steal = int(cpu[8]) / self._hz if len(cpu) > 8 else 0.0
        return Sample(steal, time.time() - time.monotonic(), threads)

    def name_threads(self) -> None:
        """Thread names by native id (threads that started since the last call)."""
        for t in threading.enumerate():
            if t.native_id is not None:
                self.names[t.native_id] = t.name

    def explain(self, before: Sample, after: Sample, gap_s: float, period_s: float) -> Dict:
        """The causes of one gap: what the cycle thread did in it, and what
        took the time it did not get."""
        late = gap_s - period_s
        per_thread = {}
        for tid, (on_cpu, waiting) in after.threads.items():
            on0, wait0 = before.threads.get(tid, (0, 0))
            per_thread[tid] = ((on_cpu - on0) * _NS, (waiting - wait0) * _NS)
        cycle = [tid for tid, name in self.names.items() if name == CYCLE_THREAD and tid in per_thread]
        ran, waited = per_thread[cycle[0]] if cycle else (0.0, 0.0)
        steal = after.steal_s - before.steal_s
        step = after.wall_offset_s - before.wall_offset_s
        causes = []
        if steal >= late / 2:
            causes.append("hypervisor steal %.0f ms" % (steal * 1e3))
        if waited >= late / 2:
            causes.append("cycle thread runnable, waiting for a CPU %.0f ms" % (waited * 1e3))
        if ran >= late / 2:
            causes.append("cycle thread ran %.0f ms" % (ran * 1e3))
        if not causes:
            # The cycle thread was blocked: on the GIL or a lock, held by a
            # thread that ran or, runnable, waited for a CPU meanwhile.
            others = sorted(((on + wait, on, wait, tid) for tid, (on, wait) in per_thread.items()
                             if tid not in cycle), reverse=True)[:2]
            causes.append("cycle thread blocked %.0f ms; meanwhile %s; steal %.0f ms" % (
                (gap_s - ran - waited) * 1e3, ", ".join("%s ran %.0f ms, waited for a CPU %.0f ms" % (
                    self.names.get(tid, str(tid)), on * 1e3, wait * 1e3) for total, on, wait, tid in others
                    if total > 0) or "no thread of this process ran or waited for a CPU", steal * 1e3))
        return {"cause": "; ".join(causes), "cycle_ran_ms": ran * 1e3, "cycle_waited_ms": waited * 1e3,
                "steal_ms": steal * 1e3, "clock_step_ms": step * 1e3}

    def close(self) -> None:
        for fd in self._fds.values():
            os.close(fd)
        self._fds.clear()
        os.close(self._stat)


class SyncRecorder(can.BusABC):
    """The driver's bus, recording each SYNC as it is sent: the thread that
    sends it (the cycle) takes the time and a GapWitness sample right
    there, so the two samples around a gap bracket exactly that gap (a
    listener thread would take them whenever it got the GIL after the
    frames). Periods are monotonic; a wall clock that steps (the frames'
    stamps are wall time) is counted apart, as it moves no drive.

    What it keeps is allocated up front (the longest period of each
    second, a bounded list of gaps), so the recording does not add to the
    RSS it measures: a list of every SYNC's time would grow by some
    11 MB/h."""

    MAX_GAPS = 10000
    MAX_EXPLAINED = 1000  # gaps explained in full (a dict each); the rest are counted

    def __init__(self, channel: str, seconds: float) -> None:
        self.inner = can.Bus(interface="virtual", channel=channel)
        self.channel_info = self.inner.channel_info
        self.t0 = 0.0                     # monotonic start; 0: not recording yet
        self.count = 0
        self.longest = array("d", bytes(8 * (int(seconds) + 60)))   # per second since t0
        self.gaps = array("d", bytes(16 * self.MAX_GAPS))          # (end time, period) pairs
        self.n_gaps = 0
        self.wall_steps = 0               # SYNC periods whose wall time differed by over 1 ms
        self.witness = GapWitness()
        self.causes: List[Dict] = []      # GapWitness.explain of the first MAX_EXPLAINED gaps
        self._last: Optional[Sample] = None
        self._last_t = 0.0
        super().__init__(channel=channel)

    def send(self, msg: can.Message, timeout: Optional[float] = None) -> None:
        if msg.arbitration_id == SYNC_ID and self.t0:
            self._record()
        self.inner.send(msg, timeout)

    def _record(self) -> None:
        witness = self.witness
        t = time.monotonic()
        now = witness.sample()
        if any(tid not in witness.names for tid in now.threads):
            witness.name_threads()
        last = self._last
        if last is not None:
            period = t - self._last_t
            k = int(t - self.t0)
            if k < len(self.longest) and period > self.longest[k]:
                self.longest[k] = period
            if abs(now.wall_offset_s - last.wall_offset_s) > 0.001:
                self.wall_steps += 1
            if period > GAP_PERIODS * PERIOD and self.n_gaps < self.MAX_GAPS:
                self.gaps[2 * self.n_gaps], self.gaps[2 * self.n_gaps + 1] = t - self.t0, period
                self.n_gaps += 1
                if len(self.causes) < self.MAX_EXPLAINED:
                    self.causes.append(witness.explain(last, now, period, PERIOD))
        self._last, self._last_t = now, t
        self.count += 1

    def _recv_internal(self, timeout: Optional[float]):
        return self.inner.recv(timeout), False

    def shutdown(self) -> None:
        self.inner.shutdown()
        self.witness.close()
        super().shutdown()


class GcTimes:
    """(start, end) monotonic times of each garbage collection."""

    def __init__(self) -> None:
        self.spans: List[Tuple[float, float, int]] = []
        self._start = 0.0
        gc.callbacks.append(self._cb)

    def _cb(self, phase: str, info: Dict) -> None:
        if phase == "start":
            self._start = time.monotonic()
        else:
            self.spans.append((self._start, time.monotonic(), info.get("generation", -1)))

    def close(self) -> None:
        gc.callbacks.remove(self._cb)


GAP_KINDS = (("hypervisor steal", "hypervisor steal"),
             ("waiting for a CPU", "cycle thread waited for a CPU"), ("cycle thread ran", "cycle thread ran"),
             ("blocked", "cycle thread blocked (GIL or lock)"), ("halt+recover", "during halt+recover"),
             ("gc gen", "during a garbage collection"))


def gap_kinds(gap: Dict) -> List[str]:
    """The kinds of cause a gap's explanation names (GAP_KINDS)."""
    text = " ".join(gap["during"])
    return [kind for marker, kind in GAP_KINDS if marker in text]


def type_counts() -> Counter:
    gc.collect()
    return Counter(type(o).__name__ for o in gc.get_objects())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=3600.0, help="whole run (default %(default)s: 1 h)")
    ap.add_argument("--axes", type=int, default=8)
    ap.add_argument("--every", type=float, default=10.0, help="s between RSS samples and halt/recover pairs")
    ap.add_argument("--plot", help="write a PNG here")
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args()

    channel = "soak_%d" % os.getpid()
    sim_bus = can.Bus(interface="virtual", channel=channel)
    sim = Simulator(sim_bus, [NodeConfig(i, DCF) for i in range(1, args.axes + 1)], tick=0.005).start()
    params = {
        "bus": {"device": "virtual:" + channel}, "sync": {"interval_ms": PERIOD * 1000},
        "heartbeat": {"rate": 20, "msg": "77f#05"},
        "nodes": [{"id": i, "name": "j%d" % i} for i in range(1, args.axes + 1)],
        "defaults": {"eds_file": DCF, "modes": ["CSP"], "pdo_layout": "compact", "readings_every": 5,
                     "pos_to_device": "rint(pos*3200/(2*pi))", "pos_from_device": "obj6064*2*pi/3200",
                     "vel_to_device": "rint(vel)", "vel_from_device": "obj606C",
                     # the drives watch the master's heartbeat for 2 s (a loaded host
                     # may hold the heartbeat thread back longer than 150 ms)
                     "dcf_overlay": {"1016sub1": "0x007F07D0", "2000": "$NODEID+0"}}}
    recorder = SyncRecorder(channel, args.seconds)
    driver = Driver(load_config(params, "soak"), bus=recorder)
    names = list(driver.joints)
    gcs = GcTimes()
    busy: List[Tuple[float, float, str]] = []   # (start, end, what) of halt/recover pairs
    samples = int(args.seconds / args.every) + 2
    rss_at, rss_kb_ = array("d", bytes(8 * samples)), array("q", bytes(8 * samples))
    rss_phase = array("b", bytes(samples))
    n_rss = 0
    failures: List[str] = []
    counts_before: Optional[Counter] = None
    counts_after: Optional[Counter] = None
    try:
        r = driver.init()
        if not r.success:
            print("init failed: %s" % r.message)
            return 1
        r = driver.switch_mode(names, 8)
        if not r.success:
            print("switch to CSP failed: %s" % r.message)
            return 1
        t0_mono = recorder.t0 = time.monotonic()

        def trajectory(d) -> None:
            target = 0.5 * math.sin(0.5 * (time.monotonic() - t0_mono))
            for name in names:
                d.set_command(name, "position", target)
        driver.add_cycle_callback(trajectory)
        half = args.seconds / 2.0
        next_sample = 0.0
        phase = 1
        while True:
            now = time.monotonic() - t0_mono
            if now >= args.seconds:
                break
            if phase == 1 and now >= half:
                phase = 2
                counts_before = type_counts()
            if now >= next_sample and n_rss < samples:
                rss_at[n_rss], rss_kb_[n_rss], rss_phase[n_rss] = now, rss_kb(), phase
                print("%7.0f s  phase %d  RSS %d kB  overruns %d" % (now, phase, rss_kb_[n_rss], driver.overruns),
                      flush=True)
                n_rss += 1
                next_sample += args.every
                if phase == 2:
                    start = time.monotonic()
                    for step in ("halt", "recover"):
                        res = getattr(driver, step)()
                        if not res.success:
                            failures.append("%.0f s %s: %s" % (now, step, res.message))
                    res = driver.switch_mode(names, 8)
                    if not res.success:
                        failures.append("%.0f s switch to CSP: %s" % (now, res.message))
                    busy.append((start, time.monotonic(), "halt+recover"))
            time.sleep(max(0.0, min(1.0, next_sample - (time.monotonic() - t0_mono))))
        counts_after = type_counts() if counts_before is not None else None
    finally:
        gcs.close()
        driver.shutdown()
        driver.close()
        recorder.shutdown()
        sim.stop()
        sim_bus.shutdown()

    rss = [(rss_at[i], rss_kb_[i], rss_phase[i]) for i in range(n_rss)]
    periods = [(p, k + 1.0) for k, p in enumerate(recorder.longest) if p > 0]  # longest of each second
    gaps = []
    for i in range(recorder.n_gaps):
        at, p = recorder.gaps[2 * i], recorder.gaps[2 * i + 1]
        start, end = t0_mono + at - p, t0_mono + at
        why = [w for s, e, w in busy if s <= end and e >= start]
        why += ["gc gen %d %.0f ms" % (g, (e - s) * 1000) for s, e, g in gcs.spans if s <= end and e >= start]
        gap = {"at_s": at, "gap_ms": p * 1000, "during": why}
        if i < len(recorder.causes):
            gap.update(recorder.causes[i])
            why.append(gap["cause"])
        gaps.append(gap)
    print("\nsoak: %d axes, %.0f s (%.0f s CSP, then %.0f s with halt+recover every %.0f s), %d SYNCs, "
          "host %s" % (args.axes, args.seconds, half, args.seconds - half, args.every, recorder.count,
                       os.uname().release))
    growth = {}
    for ph in (1, 2):
        samples = [(t, kb) for t, kb, p in rss if p == ph]
        after_minute = [(t, kb) for t, kb in samples if samples and t >= samples[0][0] + 60.0]
        growth[ph] = slope_kb_per_h(after_minute)
        if samples:
            print("phase %d RSS: %d kB at %.0f s, %d kB at %.0f s, growth %.0f kB/h (least squares after its "
                  "first minute; target <= 100 kB/h)" % (ph, samples[0][1], samples[0][0], samples[-1][1],
                                                          samples[-1][0], growth[ph]))
    print("SYNC gaps over %d periods (%.0f ms): %d, %d of them with a cause the kernel counted"
          % (GAP_PERIODS, GAP_PERIODS * PERIOD * 1000, len(gaps), sum("cause" in g for g in gaps)))
    print("wall clock steps over 1 ms between two SYNCs (no gap on the bus: periods are monotonic): %d"
          % recorder.wall_steps)
    kinds = Counter(kind for g in gaps for kind in gap_kinds(g))
    if kinds:
        print("  by cause (a gap may have several): %s" % ", ".join("%s %d" % kv for kv in kinds.most_common()))
    for phase_name, lo, hi in (("CSP", 0.0, half), ("halt+recover", half, math.inf)):
        in_phase = [g for g in gaps if lo <= g["at_s"] < hi]
        print("  %s phase: %d gaps, %d after its first 10 s" % (phase_name, len(in_phase),
                                                                sum(g["at_s"] >= lo + 10 for g in in_phase)))
    shown = sorted(gaps, key=lambda g: -g["gap_ms"])[:20]
    if shown:
        print("  the %d longest:" % len(shown))
    for g in sorted(shown, key=lambda g: g["at_s"]):
        print("  at %8.3f s: %7.1f ms  %s" % (g["at_s"], g["gap_ms"], ", ".join(g["during"]) or "-"))
    if periods:
        longest = max(p for p, _ in periods)
        print("longest SYNC period %.1f ms; %d halt+recover pairs, %d failed steps"
              % (longest * 1000, len(busy), len(failures)))
    for f in failures[:10]:
        print("  failed: %s" % f)
    if counts_before is not None and counts_after is not None and busy:
        diff = (counts_after - counts_before).most_common(6)
        print("object types grown over the halt/recover phase (%d pairs): %s"
              % (len(busy), ", ".join("%s +%d" % kv for kv in diff) or "none"))
    if args.plot:
        plot(args.plot, rss, periods, gaps, half, args.every)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"rss": rss, "gaps": gaps, "growth_kb_per_h": growth, "failures": failures,
                       "syncs": recorder.count}, f)
    return 0


def plot(path: str, rss: List[Tuple[float, int, int]], periods: List[Tuple[float, float]],
         gaps: List[Dict], half: float, every: float) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    colours = {1: "tab:blue", 2: "tab:orange"}
    labels = {1: "CSP", 2: "CSP, halt+recover every %g s" % every}
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    first = rss[0][1] if rss else 0
    for ph in (1, 2):
        pts = [(t, kb - first) for t, kb, p in rss if p == ph]
        if pts:
            ax1.plot([t for t, _ in pts], [m for _, m in pts], "o-", ms=3, color=colours[ph], label=labels[ph])
    ax1.set_ylabel("RSS - %d kB (kB)\naxis not from 0" % first)
    ax1.legend()
    for ph in (1, 2):
        pts = [(at, p * 1000) for p, at in periods if (at < half) == (ph == 1)]
        ax2.plot([t for t, _ in pts], [v for _, v in pts], ".", ms=2, color=colours[ph], label=labels[ph])
    ax2.set_title("longest SYNC period of each second", fontsize="small")
    ax2.axhline(GAP_PERIODS * PERIOD * 1000, color="tab:red", ls="--", lw=0.8, label="3 periods")
    if gaps:
        ax2.plot([g["at_s"] for g in gaps], [g["gap_ms"] for g in gaps], "x", color="tab:red", label="gaps")
    ax2.set_ylim(bottom=0)
    ax2.set_xlim(left=0)
    ax2.set_xlabel("s since start")
    ax2.set_ylabel("SYNC period (ms), axis from 0")
    ax2.legend()
    fig.tight_layout()
    fig.savefig(path)
    print("plot: %s" % path)


if __name__ == "__main__":
    sys.exit(main())
