#!/usr/bin/env python3
"""Summarise the test suite from its JUnit files: the fast pytest suite and
the end-to-end rostest suite (see tools/e2e_suite.sh for the layout).

    testreport.py --pytest FILE.xml --e2e RESULTS_DIR [--e2e-expected N]

Prints the 10 slowest files and the 10 slowest test cases with their
seconds, the failed tests, a count per suite and, last, the closing line
"N passed, N failed". Exit status 0 only when nothing failed and every
expected suite ran.

A rostest file counts its unit test cases (rosunit-*.xml). A file whose
rostest run failed without any failing unit case (a test node that crashed
before writing results, a launch error, a timeout) counts as one failure
at least, so nothing that did not run can pass silently.
"""
from __future__ import annotations

import argparse
import glob
import os
import sys
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple


@dataclass
class Tally:
    passed: int = 0
    failed: int = 0
    skipped: int = 0
    failures: List[str] = field(default_factory=list)

    def add(self, other: "Tally") -> None:
        self.passed += other.passed
        self.failed += other.failed
        self.skipped += other.skipped
        self.failures.extend(other.failures)


def _cases(path: str) -> List[Tuple[str, str]]:
    """(name, outcome) of every testcase in a JUnit file; outcome is one of
    passed, failed, skipped. An unreadable file is one failed case."""
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as exc:
        return [(os.path.basename(path), "failed: unreadable results (%s)" % exc)]
    out = []
    for case in root.iter("testcase"):
        name = "%s.%s" % (case.get("classname", ""), case.get("name", ""))
        if case.find("failure") is not None or case.find("error") is not None:
            bad = case.find("failure")
            if bad is None:
                bad = case.find("error")
            text = (bad.get("message") or bad.text or "").strip()
            out.append((name, "failed: %s" % text.splitlines()[0][:300] if text else "failed"))
        elif case.find("skipped") is not None:
            out.append((name, "skipped"))
        else:
            out.append((name, "passed"))
    # A suite-level error with no testcase (collection error) is a failure.
    if not out:
        suites = [root] if root.tag == "testsuite" else list(root.iter("testsuite"))
        for s in suites:
            n_bad = int(s.get("errors", 0) or 0) + int(s.get("failures", 0) or 0)
            for i in range(n_bad):
                out.append(("%s#%d" % (s.get("name", "suite"), i), "failed: suite error"))
    return out


def tally_junit(path: str, label: str) -> Tally:
    t = Tally()
    if not os.path.exists(path):
        t.failed += 1
        t.failures.append("%s: no results file %s (the suite did not run)" % (label, path))
        return t
    for name, outcome in _cases(path):
        if outcome == "passed":
            t.passed += 1
        elif outcome == "skipped":
            t.skipped += 1
        else:
            t.failed += 1
            t.failures.append("%s: %s %s" % (label, name, outcome))
    return t


def tally_e2e(results: str, expected: Optional[int] = None) -> Tally:
    t = Tally()
    manifest = os.path.join(results, "manifest")
    entries = []
    if os.path.exists(manifest):
        with open(manifest) as f:
            entries = [line.split() for line in f if line.strip()]
    if expected is not None and len(entries) < expected:
        t.failed += expected - len(entries)
        t.failures.append("e2e: %d of %d rostest files did not run" % (expected - len(entries), expected))
    for entry in entries:
        pkg, test_file, rc = entry[0], entry[1], int(entry[2])
        label = "e2e %s/%s" % (pkg, test_file)
        xml_dir = os.path.join(results, "xml", "%s.%s" % (pkg, test_file))
        unit = Tally()
        for path in sorted(glob.glob(os.path.join(xml_dir, "**", "rosunit-*.xml"), recursive=True)):
            unit.add(tally_junit(path, label))
        top = Tally()
        for path in sorted(glob.glob(os.path.join(xml_dir, "**", "rostest-*.xml"), recursive=True)):
            top.add(tally_junit(path, label))
        t.passed += unit.passed
        t.skipped += unit.skipped
        t.failed += unit.failed
        t.failures.extend(unit.failures)
        if unit.failed == 0 and (rc != 0 or top.failed > 0 or unit.passed == 0):
            t.failed += max(1, top.failed)
            reason = "exit status %d" % rc if rc else "no passing test case"
            t.failures.append("%s: rostest failed (%s)%s" % (
                label, reason, "".join("\n    " + f for f in top.failures)))
    return t


def python38_line(paths: List[str], absent: bool) -> Tally:
    """The ROS-free unit tests under Python 3.8 (ROS Noetic's), on a line of their own."""
    t = Tally()
    for path in paths:
        t.add(tally_junit(path, "pytest (Python 3.8)"))
    if paths:
        print("ROS-free unit tests under Python 3.8: %d passed, %d failed, %d skipped" % (
            t.passed, t.failed, t.skipped))
    elif absent:
        print("ROS-free unit tests under Python 3.8: not run (no Python 3.8 interpreter)")
    return t


# --- the slowest files and tests ---------------------------------------------

def _case_times(path: str) -> List[Tuple[str, str, float]]:
    """(file, test, seconds) of every testcase with a time in a JUnit file."""
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError):
        return []
    out = []
    for case in root.iter("testcase"):
        try:
            secs = float(case.get("time") or "")
        except ValueError:
            continue
        classname = case.get("classname", "")
        # pytest: "pkg.test.unit.test_x.TestClass" or "test_x"; the file is the test_* part
        parts = classname.split(".")
        module = next((p for p in parts if p.startswith("test_")), classname)
        out.append((module + ".py" if module.startswith("test_") else module,
                    "%s.%s" % (classname, case.get("name", "")), secs))
    return out


def timings(pytest_files: Sequence[str], e2e: Optional[str]) -> Tuple[List[Tuple[str, float]],
                                                                      List[Tuple[str, float]]]:
    """(file, seconds) and (test, seconds) of both suites. A pytest file's
    seconds are the sum of its cases; a rostest file's are its wall time in
    the manifest (start-up included); its cases are "<file>: <case>"."""
    files: Dict[str, float] = {}
    tests: List[Tuple[str, float]] = []
    for path in pytest_files:
        for module, case, secs in _case_times(path):
            files["pytest " + module] = files.get("pytest " + module, 0.0) + secs
            tests.append(("pytest " + case, secs))
    if e2e:
        for pkg, test_file, secs in _manifest_times(e2e):
            label = "e2e %s/%s" % (pkg, test_file)
            files[label] = secs
            xml_dir = os.path.join(e2e, "xml", "%s.%s" % (pkg, test_file))
            for path in sorted(glob.glob(os.path.join(xml_dir, "**", "rosunit-*.xml"), recursive=True)):
                for _, case, case_secs in _case_times(path):
                    tests.append(("%s: %s" % (label, case.split(".")[-1]), case_secs))
    by_time = lambda item: (-item[1], item[0])  # noqa: E731
    return sorted(files.items(), key=by_time), sorted(tests, key=by_time)


def _manifest_times(results: str) -> List[Tuple[str, str, float]]:
    manifest = os.path.join(results, "manifest")
    if not os.path.exists(manifest):
        return []
    out = []
    with open(manifest) as f:
        for line in f:
            entry = line.split()
            if len(entry) >= 4:
                try:
                    out.append((entry[0], entry[1], float(entry[3])))
                except ValueError:
                    pass
    return out


def print_slowest(pytest_files: Sequence[str], e2e: Optional[str], count: int = 10) -> None:
    files, tests = timings(pytest_files, e2e)
    for title, rows in (("files", files), ("tests", tests)):
        if not rows:
            continue
        print("the %d slowest %s:" % (min(count, len(rows)), title))
        for name, secs in rows[:count]:
            print("  %8.1f s  %s" % (secs, name))


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pytest", action="append", default=[], help="pytest JUnit XML file")
    ap.add_argument("--e2e", help="end-to-end results folder (tools/e2e_suite.sh)")
    ap.add_argument("--e2e-expected", type=int, help="number of rostest files that should have run")
    ap.add_argument("--pytest38", action="append", default=[],
                    help="JUnit XML file of the ROS-free unit tests run under Python 3.8")
    ap.add_argument("--python38-absent", action="store_true",
                    help="no Python 3.8 environment: say so on the Python 3.8 line")
    args = ap.parse_args(argv)

    print_slowest(args.pytest, args.e2e)
    total = Tally()
    for path in args.pytest:
        t = tally_junit(path, "pytest")
        print("fast suite (pytest) %s: %d passed, %d failed, %d skipped" % (
            os.path.basename(path), t.passed, t.failed, t.skipped))
        total.add(t)
    total.add(python38_line(args.pytest38, args.python38_absent))
    if args.e2e:
        t = tally_e2e(args.e2e, args.e2e_expected)
        print("end-to-end suite (rostest on vcan0): %d passed, %d failed" % (t.passed, t.failed))
        total.add(t)
    for f in total.failures:
        print("FAILED " + f)
    print("%d passed, %d failed" % (total.passed, total.failed))
    return 0 if total.failed == 0 and (total.passed > 0) else 1


if __name__ == "__main__":
    sys.exit(main())
