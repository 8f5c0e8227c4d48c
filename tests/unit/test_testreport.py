"""The harness's summary must never let a test that did not run, or a
rostest that crashed, count as passed."""
import importlib.util
import os
import sys

import pytest

_spec = importlib.util.spec_from_file_location(
    "testreport", os.path.join(os.path.dirname(__file__), "..", "..", "tools", "testreport.py"))
testreport = importlib.util.module_from_spec(_spec)
sys.modules["testreport"] = testreport  # dataclasses look their module up here
_spec.loader.exec_module(testreport)

PASS2 = ('<testsuite tests="2" failures="0" errors="0"><testcase classname="A" name="a"/>'
         '<testcase classname="A" name="b"/></testsuite>')
FAIL1 = ('<testsuite tests="2" failures="1" errors="0"><testcase classname="A" name="a"/>'
         '<testcase classname="A" name="b"><failure message="boom">trace</failure></testcase></testsuite>')
TOP_OK = '<testsuite tests="1" failures="0" errors="0"><testcase classname="rostest" name="testx"/></testsuite>'
TOP_ERR = ('<testsuite tests="1" failures="0" errors="1"><testcase classname="rostest" name="testx">'
           '<error message="test [x] did not generate test results"/></testcase></testsuite>')


def _e2e(tmp_path, files):
    """files: list of (test_file, exit status, rosunit xml or None, rostest xml or None)."""
    lines = []
    for name, rc, unit, top in files:
        d = tmp_path / "xml" / ("pkg." + name) / "pkg"
        d.mkdir(parents=True)
        if unit is not None:
            (d / "rosunit-x.xml").write_text(unit)
        if top is not None:
            (d / ("rostest-" + name + ".xml")).write_text(top)
        lines.append("pkg %s %d 1.0\n" % (name, rc))
    (tmp_path / "manifest").write_text("".join(lines))
    return str(tmp_path)


def test_passing_rostest_counts_its_unit_cases(tmp_path):
    t = testreport.tally_e2e(_e2e(tmp_path, [("a.test", 0, PASS2, TOP_OK)]), expected=1)
    assert (t.passed, t.failed) == (2, 0)


def test_failing_case_is_counted_once(tmp_path):
    t = testreport.tally_e2e(_e2e(tmp_path, [("a.test", 1, FAIL1, TOP_OK)]), expected=1)
    assert (t.passed, t.failed) == (1, 1)
    assert any("boom" in f for f in t.failures)


def test_rostest_that_crashed_before_writing_results_fails(tmp_path):
    t = testreport.tally_e2e(_e2e(tmp_path, [("a.test", 1, None, TOP_ERR)]), expected=1)
    assert (t.passed, t.failed) == (0, 1)


def test_nonzero_exit_without_any_xml_fails(tmp_path):
    t = testreport.tally_e2e(_e2e(tmp_path, [("a.test", 124, None, None)]), expected=1)
    assert t.failed == 1 and "exit status 124" in t.failures[0]


def test_test_files_that_did_not_run_fail(tmp_path):
    t = testreport.tally_e2e(_e2e(tmp_path, [("a.test", 0, PASS2, TOP_OK)]), expected=3)
    assert (t.passed, t.failed) == (2, 2)


def test_missing_pytest_results_fail(tmp_path):
    t = testreport.tally_junit(str(tmp_path / "nothing.xml"), "pytest")
    assert t.failed == 1


def test_closing_line_and_exit_status(tmp_path, capsys):
    ok = tmp_path / "ok.xml"
    ok.write_text(PASS2)
    assert testreport.main(["--pytest", str(ok)]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == "2 passed, 0 failed"
    bad = tmp_path / "bad.xml"
    bad.write_text(FAIL1)
    assert testreport.main(["--pytest", str(bad)]) == 1
    assert capsys.readouterr().out.splitlines()[-1] == "1 passed, 1 failed"


@pytest.mark.parametrize("content", ["<testsuite", "not xml at all"])
def test_unreadable_results_fail(tmp_path, content):
    p = tmp_path / "r.xml"
    p.write_text(content)
    t = testreport.tally_junit(str(p), "pytest")
    assert t.failed == 1 and t.passed == 0


def _timed(cases):
    return "<testsuite>%s</testsuite>" % "".join(
        '<testcase classname="%s" name="%s" time="%s"/>' % c for c in cases)


def test_the_slowest_files_and_tests_with_their_seconds(tmp_path, capsys):
    fast = tmp_path / "pytest.xml"
    fast.write_text(_timed([("pkg.test.unit.test_a.TestX", "t1", "3.0"), ("pkg.test.unit.test_a", "t2", "4.0"),
                            ("test_b", "t3", "0.5"), ("test_c", "t4", "bad")]))
    e2e = tmp_path / "e2e"
    d = e2e / "xml" / "pkg.slow.test" / "pkg"
    d.mkdir(parents=True)
    (d / "rosunit-slow.xml").write_text(_timed([("__main__.Session", "test_01_init", "20.5"),
                                               ("__main__.Session", "test_02_move", "1.0")]))
    (e2e / "manifest").write_text("pkg slow.test 0 95.2 pkg.group\npkg quick.test 0 12.0 pkg.group\n")
    files, tests = testreport.timings([str(fast)], str(e2e))
    assert files == [("e2e pkg/slow.test", 95.2), ("e2e pkg/quick.test", 12.0), ("pytest test_a.py", 7.0),
                     ("pytest test_b.py", 0.5)]
    assert tests[0] == ("e2e pkg/slow.test: test_01_init", 20.5)
    assert tests[1] == ("pytest pkg.test.unit.test_a.t2", 4.0)
    assert len(tests) == 5  # the case without a readable time is left out
    testreport.print_slowest([str(fast)], str(e2e), count=2)
    out = capsys.readouterr().out
    assert "the 2 slowest files:\n      95.2 s  e2e pkg/slow.test\n      12.0 s  e2e pkg/quick.test\n" in out
    assert "the 2 slowest tests:\n      20.5 s  e2e pkg/slow.test: test_01_init\n" in out
