#!/usr/bin/env python3
"""Summarise the test suite from its JUnit files: the fast pytest suite and
the end-to-end rostest suite (see tools/e2e_suite.sh for the layout).

    testreport.py --pytest FILE.xml --e2e RESULTS_DIR [--e2e-expected N]

Prints the failed tests, a count per suite and, last, the closing line
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
from typing import List, Optional, Tuple


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


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pytest", action="append", default=[], help="pytest JUnit XML file")
    ap.add_argument("--e2e", help="end-to-end results folder (tools/e2e_suite.sh)")
    ap.add_argument("--e2e-expected", type=int, help="number of rostest files that should have run")
    args = ap.parse_args(argv)

    total = Tally()
    for path in args.pytest:
        t = tally_junit(path, "pytest")
        print("fast suite (pytest) %s: %d passed, %d failed, %d skipped" % (
            os.path.basename(path), t.passed, t.failed, t.skipped))
        total.add(t)
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
