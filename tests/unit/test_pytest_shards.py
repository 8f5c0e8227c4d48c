"""The fast suite's split of a folder into pytest processes
(tools/pytest_shards.py): every file in exactly one process, the processes
about equal by the last run's times, the same split for the same times."""
import importlib.util
import os
import sys

_spec = importlib.util.spec_from_file_location(
    "pytest_shards", os.path.join(os.path.dirname(__file__), "..", "..", "tools", "pytest_shards.py"))
pytest_shards = importlib.util.module_from_spec(_spec)
sys.modules["pytest_shards"] = pytest_shards
_spec.loader.exec_module(pytest_shards)

FILES = ["pkg/test/unit/test_%s.py" % name for name in ("a", "b", "c", "d", "e", "new")]
JUNIT = ('<testsuites><testsuite>'
         '<testcase classname="pkg.test.unit.test_a" name="x" time="40.0"/>'
         '<testcase classname="pkg.test.unit.test_b" name="x" time="10.0"/>'
         '<testcase classname="pkg.test.unit.test_b.TestGroup" name="y" time="10.0"/>'
         '<testcase classname="pkg.test.unit.test_c" name="x" time="15.0"/>'
         '<testcase classname="pkg.test.unit.test_d" name="x" time="5.0"/>'
         '<testcase classname="pkg.test.unit.test_e" name="x" time="bad"/>'
         '<testcase classname="other.test.unit.test_a" name="x" time="99.0"/>'
         '</testsuite></testsuites>')


def test_times_per_file_from_the_last_run(tmp_path, monkeypatch):
    (tmp_path / "last.xml").write_text(JUNIT)
    monkeypatch.chdir(tmp_path)
    times = pytest_shards.file_times([str(tmp_path / "last.xml"), str(tmp_path / "missing.xml")], FILES)
    # a class's cases count for its file; another package's module of the same name does not
    assert times == {FILES[0]: 40.0, FILES[1]: 20.0, FILES[2]: 15.0, FILES[3]: 5.0}


def test_each_file_in_one_process_and_the_processes_balanced():
    times = {FILES[0]: 40.0, FILES[1]: 20.0, FILES[2]: 15.0, FILES[3]: 5.0}
    split = pytest_shards.shards(FILES, times, 2)
    assert sorted(f for share in split for f in share) == sorted(FILES)
    # test_e and test_new count as the median (17.5 s): a 40, b 20, e and new 17.5, c 15, d 5
    # go to 0, 1, 1, 1 (37.5 < 40), 0, and d to 0 (55 = 55, the lower number)
    assert split == [[FILES[0], FILES[2], FILES[3]], [FILES[1], FILES[4], FILES[5]]]
    assert pytest_shards.shards(list(reversed(FILES)), dict(times), 2) == split


def test_without_times_the_files_are_dealt_out_evenly_and_no_process_is_invented():
    assert pytest_shards.shards(FILES[:3], {}, 2) == [[FILES[0], FILES[2]], [FILES[1]]]
    assert pytest_shards.shards(FILES[:1], {}, 3) == [[FILES[0]], [], []]


def test_command_line_prints_one_line_per_process(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert pytest_shards.main(["--shards", "2"] + FILES[:3]) == 0
    assert capsys.readouterr().out == "%s %s\n%s\n" % (FILES[0], FILES[2], FILES[1])


def test_a_fresh_clone_balances_by_the_seed_and_the_last_run_overrides_it(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    seed = tmp_path / "seed.json"
    seed.write_text('{"pytest38": {"%s": 50.0, "./%s": 30.0, "%s": 99.0}, "pytest": {"%s": 1.0}}'
                    % (FILES[4], FILES[5], FILES[0], FILES[4]))
    # the seed's entry of the kind asked for, matched by normalised path
    assert pytest_shards.seed_times(str(seed), "pytest38", FILES[4:]) == {FILES[4]: 50.0, FILES[5]: 30.0}
    assert pytest_shards.seed_times(str(tmp_path / "none.json"), "pytest38", FILES) == {}
    # fresh: a 99, e 50, new 30 from the seed, b c d the median (50):
    # a, b, c, d, e, new go to 0, 1, 1, 0, 1, 0
    args = ["--shards", "2", "--seed", str(seed), "--kind", "pytest38"]
    assert pytest_shards.main(args + FILES) == 0
    assert capsys.readouterr().out == "%s %s %s\n%s %s %s\n" % (FILES[0], FILES[3], FILES[5],
                                                              FILES[1], FILES[2], FILES[4])
    # the last run names a (40), b (20), c (15), d (5): it wins over the seed's 99 for a
    (tmp_path / "last.xml").write_text(JUNIT)
    assert pytest_shards.main(args + ["--times", str(tmp_path / "last.xml")] + FILES) == 0
    # e 50, a 40, new 30, b 20, c 15, d 5 go to 0, 1, 1, 0, 0 (a tie: the lower), 1
    assert capsys.readouterr().out == "%s %s %s\n%s %s %s\n" % (FILES[1], FILES[2], FILES[4],
                                                              FILES[0], FILES[3], FILES[5])


def test_the_seed_is_written_from_a_runs_junit_files(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "pkg" / "test" / "unit").mkdir(parents=True)
    for f in FILES:
        (tmp_path / f).write_text("")
    (tmp_path / "pytest-pkg_test_unit_1.xml").write_text(JUNIT)
    (tmp_path / "pytest38-pkg_test_unit.xml").write_text(JUNIT.replace('time="40.0"', 'time="60.0"'))
    assert pytest_shards.main(["--write-seed", "seed.json", "pytest-pkg_test_unit_1.xml",
                               "pytest38-pkg_test_unit.xml"]) == 0
    seed = pytest_shards.seed_times("seed.json", "pytest38", FILES)
    assert seed == {FILES[0]: 60.0, FILES[1]: 20.0, FILES[2]: 15.0, FILES[3]: 5.0}
    assert pytest_shards.seed_times("seed.json", "pytest", FILES)[FILES[0]] == 40.0
