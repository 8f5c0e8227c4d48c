#!/usr/bin/env python3
"""Split one folder's test files into pytest processes of about equal time.

    pytest_shards.py --shards N [--times FILE.xml]... FILE...

Prints N lines, one per process: its files, space-separated (a line may be
empty when there are fewer files than processes). A file's time is the sum
of its test cases' times in the JUnit files of the last run (--times); a
file they do not name counts as the median of those they do (1 s when they
name none). The files go, longest first, each to the process with the least
time so far (ties: the lower number); equal times are taken in name order,
so the same times give the same split.

tools/run_tests.sh splits the largest unit-test folder this way: the files
of one folder stay in processes of their own, as its conftest.py and its
module names need.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import xml.etree.ElementTree as ET
from typing import Dict, List, Sequence


def file_times(xml_paths: Sequence[str], files: Sequence[str]) -> Dict[str, float]:
    """Seconds per file among ``files`` that the JUnit files name. pytest
    names a case's class after the file's path, dots for slashes
    (``pkg.test.unit.test_x`` or ``pkg.test.unit.test_x.TestClass``), the
    path relative to the folder pytest ran in (here: the current one)."""
    by_module = {os.path.splitext(os.path.relpath(f))[0].replace(os.sep, "."): f for f in files}
    times: Dict[str, float] = {}
    for path in xml_paths:
        try:
            root = ET.parse(path).getroot()
        except (ET.ParseError, OSError):
            continue  # no last run to go by: the median, or 1 s
        for case in root.iter("testcase"):
            parts = case.get("classname", "").split(".")
            for n in range(len(parts), 0, -1):
                f = by_module.get(".".join(parts[:n]))
                if f is not None:
                    try:
                        times[f] = times.get(f, 0.0) + float(case.get("time") or 0.0)
                    except ValueError:
                        pass
                    break
    return times


def shards(files: Sequence[str], times: Dict[str, float], count: int) -> List[List[str]]:
    """``files`` in ``count`` lists of about equal total time (greedy,
    longest first); each list in name order."""
    default = statistics.median(times.values()) if times else 1.0
    weight = {f: times.get(f, default) for f in files}
    out: List[List[str]] = [[] for _ in range(max(1, count))]
    load = [0.0] * len(out)
    for f in sorted(files, key=lambda f: (-weight[f], f)):
        i = min(range(len(out)), key=lambda i: (load[i], i))
        out[i].append(f)
        load[i] += weight[f]
    return [sorted(s) for s in out]


def main(argv: Sequence[str] = ()) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shards", type=int, required=True, help="how many processes")
    ap.add_argument("--times", action="append", default=[], help="JUnit XML of the last run")
    ap.add_argument("files", nargs="*")
    args = ap.parse_args(list(argv))
    if args.shards < 1:
        ap.error("--shards must be at least 1")
    for shard in shards(args.files, file_times(args.times, args.files), args.shards):
        print(" ".join(shard))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
