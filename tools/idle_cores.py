#!/usr/bin/env python3
"""How many of this host's cores are idle now, read from /proc/stat over a
short window; with --shards, how many end-to-end shards that leaves room for.

    idle_cores.py [--window S] [--shards MAX]

Each shard is a user-mode Linux guest with one CPU and deadlines of
milliseconds (SYNC, heartbeats and their consumers). A guest that has to
share its core with other load misses them, so the suite starts no more
guests than there are idle cores, and at least one."""
from __future__ import annotations

import argparse
import os
import time
from typing import Sequence, Tuple


def cpu_times(stat_text: str) -> Tuple[int, int]:
    """(idle, total) jiffies of all cores from /proc/stat's "cpu" line;
    idle counts iowait too."""
    for line in stat_text.splitlines():
        fields = line.split()
        if fields and fields[0] == "cpu":
            values = [int(v) for v in fields[1:]]
            # user nice system idle iowait irq softirq steal (guest times are in user already)
            idle = values[3] + (values[4] if len(values) > 4 else 0)
            return idle, sum(values[:8])
    raise ValueError("no cpu line in /proc/stat")


def idle_cores(before: str, after: str, cores: int) -> float:
    """Cores idle between two readings of /proc/stat, 0..cores."""
    idle0, total0 = cpu_times(before)
    idle1, total1 = cpu_times(after)
    if total1 <= total0:
        return float(cores)
    return max(0.0, min(float(cores), cores * (idle1 - idle0) / (total1 - total0)))


def shards_for(idle: float, most: int) -> int:
    """Shards for ``idle`` idle cores: a core at least 3/4 idle takes one,
    never more than ``most`` and never fewer than one."""
    return max(1, min(most, int(idle + 0.25)))


def main(argv: Sequence[str] = ()) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--window", type=float, default=2.0, help="seconds to watch (default 2)")
    ap.add_argument("--shards", type=int, metavar="MAX", help="print the shard count, at most MAX")
    args = ap.parse_args(list(argv) or None)
    with open("/proc/stat") as f:
        before = f.read()
    time.sleep(args.window)
    with open("/proc/stat") as f:
        after = f.read()
    idle = idle_cores(before, after, os.cpu_count() or 1)
    print(shards_for(idle, args.shards) if args.shards else "%.2f" % idle)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
