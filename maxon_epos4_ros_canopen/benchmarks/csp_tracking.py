#!/usr/bin/env python3
"""Tracking error and SYNC jitter of a 10 s CSP trajectory (a benchmark, not a test).

The CSP example's driver and JointTrajectoryController run against two
virtual EPOS4 on a python-can virtual channel in this process. Every cycle
records the commanded (trajectory) and measured (0x6064 via TPDO) joint
positions; a listener on the bus timestamps the SYNC frames.

    .venv/bin/python maxon_epos4_ros_canopen/benchmarks/csp_tracking.py [--plot out.png] [--seconds 10]

Prints: SYNC period mean/std/min/max and the share of periods more than
2 ms off; tracking error (commanded - measured) per joint, RMS and max; and
the commanded-position change between consecutive SYNCs. The PNG (commanded
vs actual, and the error) needs matplotlib; without it a CSV is written.
The simulator follows its target within one interpolation period, so the
error shown is the controller + bus + simulator lag, not a real motor's.
"""
from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from pathlib import Path

PKG = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(PKG / "src"), str(PKG / "test" / "unit")]  # the core, and csp_rig shared with the tests

from csp_rig import JOINTS, CspRig  # noqa: E402

from maxon_epos4_ros_canopen.trajectory import TrajectoryPoint  # noqa: E402


def sine_points(seconds: float, step: float = 0.1):
    """Both joints through sines (0.6 rad at 0.25 Hz, 0.3 rad at 0.5 Hz),
    points every 0.1 s with velocities (cubic segments), within 1.1 rad/s."""
    points = []
    n = int(round(seconds / step))
    for k in range(1, n + 1):
        t = k * step
        w1, w2 = 2 * math.pi * 0.25, 2 * math.pi * 0.5
        # amplitude eases in over the first and out over the last second
        # (raised cosine: position and velocity stay continuous)
        edge = min(t, seconds - t, 1.0)
        fade = 0.5 * (1.0 - math.cos(math.pi * edge))
        dfade = 0.5 * math.pi * math.sin(math.pi * edge) * (1.0 if t < seconds - t else -1.0)
        pos = (0.6 * math.sin(w1 * t) * fade, 0.3 * math.sin(w2 * t) * fade)
        vel = (0.6 * (w1 * math.cos(w1 * t) * fade + math.sin(w1 * t) * dfade),
               0.3 * (w2 * math.cos(w2 * t) * fade + math.sin(w2 * t) * dfade))
        if k == n:
            vel = (0.0, 0.0)
        points.append(TrajectoryPoint(pos, vel, (), t))
    return points


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--plot", default="csp_tracking.png", help="PNG file (default: %(default)s)")
    args = ap.parse_args()

    log = []

    def record(ctrl) -> None:
        if ctrl.last_cycle is not None and ctrl.last_actual is not None:
            log.append((time.monotonic(), ctrl.last_cycle.desired.positions, ctrl.last_actual.positions))

    def no_path_tolerance(params) -> None:
        # this measures tracking: a large error must not abort the goal
        for joint in JOINTS:
            params["joint_trajectory_controller"]["constraints"][joint]["trajectory"] = 0.0

    rig = CspRig(adjust=no_path_tolerance, cycle_hook=record)
    try:
        ctrl = rig.start()
        rig.listener.take()
        t0 = time.monotonic()
        ctrl.submit("bench", JOINTS, sine_points(args.seconds), 0.0)
        while not rig.outcomes and time.monotonic() - t0 < args.seconds + 5:
            time.sleep(0.05)
        t1 = time.monotonic()
        sync_stamps = [t for t, f in zip(rig.listener.arrivals, rig.listener.frames) if f.arbitration_id == 0x80]
    except RuntimeError as exc:
        print(exc)
        return 1
    finally:
        rig.close()
    done = rig.outcomes

    print("goal: %s" % (done[0] if done else "no result"))
    stamps = [s for s in sync_stamps if t0 <= s <= t1]
    periods = [(b - a) * 1000 for a, b in zip(stamps, stamps[1:])]
    if len(periods) > 2:
        off = sum(1 for p in periods if abs(p - 10.0) > 2.0)
        print("SYNC period over %d periods: mean %.3f ms, std %.3f ms, min %.3f ms, max %.3f ms, "
              "%.1f%% more than 2 ms off 10 ms" % (len(periods), statistics.mean(periods),
                                                     statistics.pstdev(periods), min(periods), max(periods),
                                                     100.0 * off / len(periods)))
    run = [(t, d, a) for t, d, a in log if t0 <= t <= t1]
    # The drive reaches a target one cycle after it is sent: compare the
    # measured position with the previous cycle's command as well.
    for j, name in enumerate(JOINTS):
        err = [d[j] - a[j] for _, d, a in run]
        lagged = [run[k - 1][1][j] - run[k][2][j] for k in range(1, len(run))]
        steps = [abs(run[k][1][j] - run[k - 1][1][j]) for k in range(1, len(run))]
        print("%s: tracking error rms %.5f rad, max %.5f rad; vs previous command rms %.5f, max %.5f; "
              "largest command step %.5f rad/cycle"
              % (name, math.sqrt(statistics.mean(e * e for e in err)), max(abs(e) for e in err),
                 math.sqrt(statistics.mean(e * e for e in lagged)), max(abs(e) for e in lagged), max(steps)))
    write_plot(run, t0, args.plot)
    return 0


def write_plot(run, t0: float, path: str) -> None:
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        csv = os.path.splitext(path)[0] + ".csv"
        with open(csv, "w") as f:
            f.write("t," + ",".join("%s_cmd,%s_act" % (j, j) for j in JOINTS) + "\n")
            for t, d, a in run:
                f.write("%.4f,%s\n" % (t - t0, ",".join("%.6f,%.6f" % (d[j], a[j]) for j in range(len(JOINTS)))))
        print("matplotlib not installed: wrote %s instead of a PNG" % csv)
        return
    times = [t - t0 for t, _, _ in run]
    fig, axes = plt.subplots(2, 1, figsize=(10, 7), sharex=True)
    for j, name in enumerate(JOINTS):
        axes[0].plot(times, [d[j] for _, d, _ in run], label="%s commanded" % name)
        axes[0].plot(times, [a[j] for _, _, a in run], "--", label="%s actual" % name)
        axes[1].plot(times, [(d[j] - a[j]) * 1000 for _, d, a in run], label=name)
    axes[0].set_ylabel("position (rad)")
    axes[0].legend(loc="upper right", fontsize="small")
    axes[1].set_ylabel("commanded - actual (mrad)")
    axes[1].set_xlabel("time (s)")
    axes[1].legend(loc="upper right", fontsize="small")
    fig.suptitle("CSP trajectory on two virtual EPOS4, SYNC 10 ms")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    print("plot: %s" % path)


if __name__ == "__main__":
    sys.exit(main())
