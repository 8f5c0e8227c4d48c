#!/usr/bin/env python3
"""Split one folder's test files into pytest processes of about equal time.

    pytest_shards.py --shards N [--times FILE.xml]... [--seed SEED.json --kind KIND] FILE...
    pytest_shards.py --write-seed SEED.json RESULT.xml...

Prints N lines, one per process: its files, space-separated (a line may be
empty when there are fewer files than processes). A file's time is the sum
of its test cases' times in the JUnit files of the last run (--times); a
file they do not name takes its seconds from the seed (--seed, the entry of
KIND: pytest or pytest38), and a file neither names counts as the median of
the others (1 s when none is known). The files go, longest first, each to
the process with the least time so far (ties: the lower number); equal
times are taken in name order, so the same times give the same split.

The seed (tools/pytest_times.json) is what a fresh clone, which has no last
run, balances by; ``--write-seed`` makes it from a run's
``.results/pytest[38]-*.xml``, run in the repository's root. Its figures
only balance processes: an old seed costs time, never a test.

tools/run_tests.sh splits the largest unit-test folder this way: the files
of one folder stay in processes of their own, as its conftest.py and its
module names need.
"""
from __future__ import annotations

import argparse
import glob
import json
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


def seed_times(seed_path: str, kind: str, files: Sequence[str]) -> Dict[str, float]:
    """Seconds per file among ``files`` in the seed's entry for ``kind``
    (none when the seed is missing or unreadable)."""
    try:
        with open(seed_path) as f:
            entry = json.load(f).get(kind, {})
    except (OSError, ValueError, AttributeError):
        return {}
    wanted = {os.path.normpath(f): f for f in files}
    out: Dict[str, float] = {}
    for name, seconds in entry.items():
        f = wanted.get(os.path.normpath(name))
        if f is not None and isinstance(seconds, (int, float)):
            out[f] = float(seconds)
    return out


def write_seed(seed_path: str, xml_paths: Sequence[str]) -> Dict[str, Dict[str, float]]:
    """The seed from a run's JUnit files ``<kind>-<name>.xml``: per kind,
    seconds per test file of the repository (found from the current
    folder), rounded to 0.1 s."""
    files = sorted(glob.glob(os.path.join("*", "test", "unit", "test_*.py"))
                   + glob.glob(os.path.join("tests", "unit", "test_*.py")))
    seed: Dict[str, Dict[str, float]] = {}
    for path in xml_paths:
        kind = os.path.basename(path).split("-", 1)[0]
        for f, seconds in file_times([path], files).items():
            entry = seed.setdefault(kind, {})
            entry[f] = round(entry.get(f, 0.0) + seconds, 1)
    seed = {kind: dict(sorted(entry.items())) for kind, entry in sorted(seed.items())}
    with open(seed_path, "w") as out:
        json.dump(seed, out, indent=1)
        out.write("\n")
    return seed


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
    ap.add_argument("--shards", type=int, help="how many processes")
    ap.add_argument("--times", action="append", default=[], help="JUnit XML of the last run")
    ap.add_argument("--seed", help="seconds per file for those the last run does not name (JSON)")
    ap.add_argument("--kind", default="pytest", help="the seed's entry: pytest or pytest38")
    ap.add_argument("--write-seed", metavar="SEED", help="write the seed from the JUnit files given as FILEs")
    ap.add_argument("files", nargs="*")
    args = ap.parse_args(list(argv))
    if args.write_seed:
        write_seed(args.write_seed, args.files)
        return 0
    if args.shards is None or args.shards < 1:
        ap.error("--shards must be at least 1")
    times = seed_times(args.seed, args.kind, args.files) if args.seed else {}
    times.update(file_times(args.times, args.files))
    for shard in shards(args.files, times, args.shards):
        print(" ".join(shard))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
