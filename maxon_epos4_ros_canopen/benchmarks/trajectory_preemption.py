#!/usr/bin/env python3
"""Cycle stall and target steps when a long goal preempts a moving one (a benchmark, not a test).

The CSP example's driver and JointTrajectoryController run against two
virtual EPOS4 on a python-can virtual channel in this process. Joint 1
moves on a line at --speed rad/s; then a goal of --points points (1 ms
apart, the same line on) preempts it from another thread, as the action
server would. A listener on the bus records the SYNC frames and each
period's 0x607A of node 1.

    .venv/bin/python maxon_epos4_ros_canopen/benchmarks/trajectory_preemption.py [--points 10000] [--rounds 5]

Prints, per round and as the worst over the rounds: how long submit()
took (the goal's validation and build); the longest time between two
SYNCs in the second before the preemption (baseline) and from the
submit to 0.5 s after it returned (the stall); and the largest 0x607A step
between consecutive SYNC periods in the same two spans (inc; the line
moves speed * 83200 / 2 pi inc per second, 26.5 inc per 10 ms at 0.2 rad/s).
"""
from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from pathlib import Path

PKG = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(PKG / "src"), str(PKG / "test" / "unit")]  # the core, and csp_rig shared with the tests

from csp_rig import JOINTS, SYNC_COB_ID, CspRig, target_mapping, targets_per_sync, wait  # noqa: E402

from maxon_epos4_ros_canopen.trajectory import TrajectoryPoint  # noqa: E402

INC_PER_RAD = 83200 / (2 * math.pi)


def one_round(points: int, speed: float) -> dict:
    rig = CspRig()
    try:
        ctrl = rig.start()
        mapping = target_mapping(rig.sim, 1)
        ctrl.submit("line", JOINTS, [TrajectoryPoint((30 * speed, 0.0), (), (), 30.0)], 0.0)
        time.sleep(1.0)
        rig.listener.flush(5.0)
        rig.listener.take()
        time.sleep(1.0)
        stamp = ctrl.clock()
        start = ctrl.query_state(stamp).positions
        goal = [TrajectoryPoint((start[0] + speed * t, 0.0), (), (), t)
                for t in (0.001 * (i + 1) for i in range(points))]
        took = []

        def submit() -> None:
            t0 = time.perf_counter()
            ctrl.submit("long", JOINTS, goal, stamp)
            took.append(time.perf_counter() - t0)
        submitted_at = time.time()  # the virtual bus stamps frames with the wall clock
        worker = threading.Thread(target=submit)
        worker.start()
        worker.join()
        returned_at = time.time()
        time.sleep(0.5)
        rig.listener.flush(5.0)
        frames = rig.listener.take()
    finally:
        rig.close()
    syncs = [f.timestamp for f in frames if f.arbitration_id == SYNC_COB_ID]
    periods = targets_per_sync(frames, *mapping)
    gaps_before = [b - a for a, b in zip(syncs, syncs[1:]) if b < submitted_at]
    after = returned_at + 0.5
    gaps_after = [b - a for a, b in zip(syncs, syncs[1:]) if b >= submitted_at and a < after]
    # periods[i] closes with SYNC i + 1
    steps = [(syncs[i + 2], y[-1] - x[-1]) for i, (x, y) in enumerate(zip(periods, periods[1:])) if x and y]
    return {
        "submit_ms": took[0] * 1000,
        "gap_before_ms": max(gaps_before) * 1000,
        "gap_after_ms": max(gaps_after) * 1000,
        "step_before": max(abs(s) for t, s in steps if t < submitted_at),
        "step_after": max(abs(s) for t, s in steps if submitted_at <= t < after),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=10000)
    ap.add_argument("--speed", type=float, default=0.2, help="rad/s of joint 1")
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    rows = []
    print("round  submit_ms  max_sync_gap_ms(before/after)  max_step_inc(before/after)")
    for k in range(args.rounds):
        r = one_round(args.points, args.speed)
        rows.append(r)
        print("%5d  %9.1f  %14.1f / %-14.1f %9d / %d" % (k + 1, r["submit_ms"], r["gap_before_ms"],
                                                         r["gap_after_ms"], r["step_before"], r["step_after"]))
    worst = {key: max(r[key] for r in rows) for key in rows[0]}
    print("worst  %9.1f  %14.1f / %-14.1f %9d / %d" % (worst["submit_ms"], worst["gap_before_ms"],
                                                       worst["gap_after_ms"], worst["step_before"],
                                                       worst["step_after"]))
    print("(%d points, %.2f rad/s: %.1f inc per 10 ms SYNC period)" % (args.points, args.speed,
                                                                       args.speed * INC_PER_RAD * 0.01))
    return 0


if __name__ == "__main__":
    sys.exit(main())
