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
