"""The end-to-end runner (tools/e2e_group.py): which rostest files share one
launch, what it starts again after a test killed a node, and that a failing
test names itself while the others of its group still run and report."""
import importlib.util
import os
import sys
from typing import List

import pytest
import roslaunch  # noqa: F401 (the runner reads .test files with roslaunch's own loader: ROS 1 needed)

_spec = importlib.util.spec_from_file_location(
    "e2e_group", os.path.join(os.path.dirname(__file__), "..", "..", "tools", "e2e_group.py"))
e2e_group = importlib.util.module_from_spec(_spec)
sys.modules["e2e_group"] = e2e_group  # dataclasses look their module up here
_spec.loader.exec_module(e2e_group)

LAUNCH = """<launch>
  <arg name="device" default="can0"/>
  <arg name="nodes" default="1"/>
  <param name="bus/device" value="$(arg device)"/>
  <node pkg="somepkg" type="sim_node" name="sim"><param name="nodes" value="$(arg nodes)"/></node>
  <node pkg="somepkg" type="driver_node" name="driver"/>
</launch>
"""


def _test_file(tmp_path, name, test_type, include_args="", params="", extra=""):
    launch = tmp_path / "fixture.launch"
    launch.write_text(LAUNCH)
    path = tmp_path / name
    path.write_text("""<launch>
  <arg name="device" default="vcan0"/>
  <include file="%s"><arg name="device" value="$(arg device)"/>%s</include>
  %s
  <test test-name="%s" pkg="somepkg" type="%s" time-limit="60">%s</test>
</launch>
""" % (launch, include_args, extra, os.path.splitext(name)[0], test_type, params))
    return str(path)


def _load(path):
    f = e2e_group.load_file(path, ["device:=vcan0"])
    f.pkg = "pkg"
    return f


def test_files_with_the_same_fixture_share_one_group_in_the_given_order(tmp_path):
    a = _load(_test_file(tmp_path, "a_loss_sigint.test", "loss_check", params='<param name="signal" value="SIGINT"/>'))
    b = _load(_test_file(tmp_path, "b_other_nodes.test", "check", include_args='<arg name="nodes" value="3"/>'))
    c = _load(_test_file(tmp_path, "c_loss_sigkill.test", "loss_check", params='<param name="signal" value="SIGKILL"/>'))
    d = _load(_test_file(tmp_path, "d_session.test", "session"))
    groups = e2e_group.plan_groups([a, b, c, d])
    # the tests' own parameters (~signal) do not split a group; a different node parameter does
    assert [[f.name for f in g.files] for g in groups] == [
        ["a_loss_sigint.test", "c_loss_sigkill.test", "d_session.test"], ["b_other_nodes.test"]]
    assert groups[0].name == "pkg.a_loss_sigint"


def test_a_param_command_runs_once_for_all_the_files_that_name_it(tmp_path):
    runs = tmp_path / "runs"
    script = tmp_path / "describe_robot"
    script.write_text("#!/bin/sh\necho run >> %s\necho \"<robot name='$1'/>\"\n" % runs)
    script.chmod(0o755)
    extra = '<param name="robot_description" command="%s arm"/>' % script
    a = _load(_test_file(tmp_path, "a.test", "check", extra=extra))
    b = _load(_test_file(tmp_path, "b.test", "check", extra=extra))
    other = '<param name="robot_description" command="%s leg"/>' % script
    c = _load(_test_file(tmp_path, "c.test", "check", extra=other))
    assert runs.read_text().count("run") == 2  # "arm" once, "leg" once
    values = [f.config.params["/robot_description"].value.strip() for f in (a, b, c)]
    assert values == ["<robot name='arm'/>", "<robot name='arm'/>", "<robot name='leg'/>"]
    assert len(e2e_group.plan_groups([a, b, c])) == 2


def test_an_extra_parameter_or_node_makes_its_own_group(tmp_path):
    a = _load(_test_file(tmp_path, "a.test", "check"))
    b = _load(_test_file(tmp_path, "b.test", "check", extra='<param name="/ns/constraints/goal_time" value="3.0"/>'))
    c = _load(_test_file(tmp_path, "c.test", "check", extra='<node pkg="somepkg" type="other" name="other"/>'))
    assert len(e2e_group.plan_groups([a, b, c])) == 3


def test_the_merged_launch_carries_every_test_and_its_private_parameters(tmp_path):
    a = _load(_test_file(tmp_path, "a.test", "loss_check", params='<param name="signal" value="SIGINT"/>'))
    b = _load(_test_file(tmp_path, "b.test", "loss_check", params='<param name="signal" value="SIGKILL"/>'))
    group = e2e_group.plan_groups([a, b])[0]
    config = e2e_group.merged_config(group)
    assert [t.test_name for t in config.tests] == ["a", "b"]
    assert config.params["/a/signal"].value == "SIGINT"
    assert config.params["/b/signal"].value == "SIGKILL"
    assert [n.name for n in config.nodes] == ["sim", "driver"]  # the fixture once


class FakeProc:
    def __init__(self, name):
        self.name = name
        self.alive = True
        self.exit_code = None

    def is_alive(self):
        return self.alive

    def end(self, code):
        self.alive = False
        self.exit_code = code


class FakeNode:
    def __init__(self, name):
        self.name = name
        self.namespace = "/"
        self.type = name


def _fixture(names):
    launched: List[str] = []
    procs = {}

    def launch(node):
        launched.append(node.name)
        procs[node.name] = FakeProc(node.name)
        return procs[node.name], True

    fixture = e2e_group.FixtureNodes([FakeNode(n) for n in names], launch)
    assert fixture.start() == []
    return fixture, launched, procs


def test_nothing_restarts_while_every_node_runs_or_ended_cleanly():
    fixture, launched, procs = _fixture(["sim", "driver", "spawner"])
    procs["spawner"].end(0)  # a set-up step that ran to its end
    assert fixture.restart_dead() == []
    assert launched == ["sim", "driver", "spawner"]


@pytest.mark.parametrize("code", [-9, -2, -15, 1])
def test_a_killed_node_restarts_alone_and_the_set_up_steps_run_again_after_it(code):
    fixture, launched, procs = _fixture(["sim", "driver", "spawner"])
    procs["spawner"].end(0)
    procs["driver"].end(code)  # SIGKILL, SIGINT, SIGTERM by a master-loss test, or a crash
    assert fixture.restart_dead() == ["/driver", "/spawner"]
    assert launched == ["sim", "driver", "spawner", "driver", "spawner"]
    assert procs["sim"].alive  # the simulator was never touched
    assert fixture.restart_dead() == []  # and once back, nothing more


def test_a_node_a_test_ends_with_status_0_restarts_when_the_test_said_it_ends_it():
    fixture, launched, procs = _fixture(["sim", "driver", "spawner"])
    procs["spawner"].end(0)
    procs["driver"].end(0)  # SIGINT: the driver's own shutdown, then exit status 0
    assert fixture.restart_dead() == []  # indistinguishable from a finished set-up step...
    assert fixture.restart_dead(killed=["/driver"]) == ["/driver", "/spawner"]  # ...unless the test said so
    assert launched == ["sim", "driver", "spawner", "driver", "spawner"]


def test_the_nodes_a_test_ends_are_read_from_its_private_parameter(tmp_path):
    f = _load(_test_file(tmp_path, "loss.test", "loss_check",
                         params='<param name="e2e_kills" value="/maxon/canopen_motor /other"/>'))
    assert f.kills == ["/maxon/canopen_motor", "/other"]
    assert _load(_test_file(tmp_path, "plain.test", "check")).kills == []


def test_a_node_that_failed_to_launch_is_tried_again():
    tries = []

    def launch(node):
        tries.append(node.name)
        return (FakeProc(node.name), True) if len(tries) > 1 else (node.name, False)

    fixture = e2e_group.FixtureNodes([FakeNode("driver")], launch)
    assert fixture.start() == ["/driver"]
    assert fixture.restart_dead() == ["/driver"]


def test_a_failing_test_names_itself_and_the_others_still_run_and_report():
    files = [e2e_group.RostestFile("pkg", "/x/%s.test" % n, "k") for n in ("a", "b", "c", "d")]
    reported = []

    def run_one(f):
        if f.name == "b.test":
            raise RuntimeError("test [b] timed out")
        if f.name == "c.test":
            return e2e_group.Outcome(f, status=1, message="test [c]: 0 errors, 1 failures")
        return e2e_group.Outcome(f)

    outcomes = e2e_group.run_tests_in_order(files, run_one, lambda previous: [], reported.append)
    assert [(o.file.name, o.status) for o in outcomes] == [("a.test", 0), ("b.test", 1), ("c.test", 1), ("d.test", 0)]
    assert "timed out" in outcomes[1].message
    assert reported == outcomes
    group = e2e_group.Group("k", files)
    assert e2e_group.manifest_line(outcomes[1], group).split()[:3] == ["pkg", "b.test", "1"]


def test_restarts_before_a_test_are_reported_with_it():
    files = [e2e_group.RostestFile("pkg", "/x/%s.test" % n, "k") for n in ("loss", "next")]
    restarts = iter([[], ["/maxon/canopen_motor", "/maxon/controller_spawner"]])
    previous = []

    def before_each(prev):
        previous.append(prev and prev.name)
        return next(restarts)

    outcomes = e2e_group.run_tests_in_order(files, lambda f: e2e_group.Outcome(f), before_each)
    assert outcomes[1].restarted == ["/maxon/canopen_motor", "/maxon/controller_spawner"]
    assert previous == [None, "loss.test"]  # what the test before declared it ends


def test_the_ran_record_is_junit_the_summary_reads(tmp_path):
    ok = tmp_path / "ok.xml"
    ok.write_text(e2e_group.junit_one_case("pkg.a", "test_ran", 1.5, None, "run_id[x] <&>"))
    bad = tmp_path / "bad.xml"
    bad.write_text(e2e_group.junit_one_case("pkg.b", "test_ran", 2.0, 'timed out "b"'))
    import xml.etree.ElementTree as ET
    assert ET.parse(str(ok)).getroot().find("testcase").find("failure") is None
    assert ET.parse(str(bad)).getroot().find("testcase").find("failure").get("message") == 'timed out "b"'


def test_a_file_that_needs_a_fresh_launch_heads_a_group(tmp_path):
    fresh = '<param name="e2e_fresh_launch" value="true"/>'
    a = _load(_test_file(tmp_path, "a_fuzz.test", "fuzz"))
    b = _load(_test_file(tmp_path, "b_from_start.test", "check", params=fresh))
    c = _load(_test_file(tmp_path, "c_real.test", "check", params=fresh))
    d = _load(_test_file(tmp_path, "d_more.test", "check"))
    assert (a.fresh, b.fresh, c.fresh, d.fresh) == (False, True, True, False)
    assert a.key == b.key == c.key == d.key
    groups = e2e_group.plan_groups([a, b, c, d])
    assert [[f.name for f in g.files] for g in groups] == [
        ["b_from_start.test", "a_fuzz.test", "d_more.test"], ["c_real.test"]]


def test_shards_keep_groups_whole_and_balance_their_time():
    def group(*names):
        return e2e_group.Group(names[0], [e2e_group.RostestFile("pkg", "/x/%s.test" % n, names[0]) for n in names])

    pvm, mani, csp, ppm, alone = group("p1", "p2", "p3"), group("m1", "m2"), group("c1"), group("d1"), group("h")
    seconds = {"p1.test": 100.0, "p2.test": 100.0, "p3.test": 100.0, "m1.test": 150.0, "m2.test": 50.0,
               "c1.test": 90.0, "d1.test": 60.0}  # h.test never timed: DEFAULT_FILE_SECONDS
    shards = e2e_group.assign_shards([pvm, mani, csp, ppm, alone], 2, seconds)
    assert [[g.key for g in s] for s in shards] == [["p1", "d1"], ["m1", "c1", "h"]]
    assert sorted(f.name for s in shards for g in s for f in g.files) == sorted(
        f.name for g in (pvm, mani, csp, ppm, alone) for f in g.files)


def test_seconds_from_an_earlier_manifest(tmp_path):
    m = tmp_path / "manifest"
    m.write_text("pkg a.test 0 12.5 pkg.a\npkg b.test 1 30.0\nbroken line\n")
    assert e2e_group.seconds_from_manifest(str(m)) == {"a.test": 12.5, "b.test": 30.0}
    assert e2e_group.seconds_from_manifest(str(tmp_path / "none")) == {}


def test_a_failed_case_is_named_with_the_line_that_says_what_failed(tmp_path):
    import rosunit.junitxml
    xml = tmp_path / "rosunit-faults.xml"
    xml.write_text("""<?xml version="1.0" encoding="utf-8"?>
<testsuite errors="1" failures="1" name="faults" tests="3" time="9.0">
  <testcase classname="faults.Faults" name="test_01_emcy" time="1.0"/>
  <testcase classname="faults.Faults" name="test_02_silent_node" time="1.0">
    <failure type="AssertionError">Traceback (most recent call last):
  File "faults.py", line 10, in test_02_silent_node
    self.assertTrue(ok)
AssertionError: False is not true : drive 2 never reported silent
</failure>
  </testcase>
  <testcase classname="faults.Faults" name="test_03_reboot" time="1.0">
    <error type="RuntimeError">no answer from node 2; session log:
  File "faults.py", line 20, in test_03_reboot
    self.fail("no answer")</error>
  </testcase>
</testsuite>
""")
    result = rosunit.junitxml.read(str(xml), "faults")
    assert e2e_group.failed_cases(result) == [
        "test_02_silent_node: AssertionError: False is not true : drive 2 never reported silent",
        "test_03_reboot: no answer from node 2; session log:",
    ]


def test_the_lines_that_say_what_failed_are_taken_from_the_tests_log(tmp_path):
    log = tmp_path / "pkg.faults.test.log"
    log.write_text("setting up\nfault_matrix: case=emcy detect_s=0.40\n"
                   "fault_matrix: case=reboot attempt=1 failed: drive 2 never rebooted\n"
                   "AssertionError: drive 2 never rebooted (attempt 1 of 3)\nbye\n")
    assert e2e_group.telling_lines(str(log)) == [
        "fault_matrix: case=reboot attempt=1 failed: drive 2 never rebooted",
        "AssertionError: drive 2 never rebooted (attempt 1 of 3)"]
    assert e2e_group.telling_lines(str(tmp_path / "missing.log")) == []


def test_a_test_client_runs_below_the_fixture_and_keeps_its_own_launch_prefix(tmp_path):
    plain = e2e_group.load_file(_test_file(tmp_path, "plain.test", "check"), []).config.tests[0]
    e2e_group.lower_client_priority(plain)
    assert plain.launch_prefix == "nice -n %d" % e2e_group.CLIENT_NICE
    e2e_group.lower_client_priority(plain)  # a test run again is not lowered twice
    assert plain.launch_prefix == "nice -n %d" % e2e_group.CLIENT_NICE

    path = _test_file(tmp_path, "prefixed.test", "check")
    with open(path) as f:
        text = f.read().replace('time-limit="60"', 'time-limit="60" launch-prefix="taskset -c 0"')
    with open(path, "w") as f:
        f.write(text)
    prefixed = e2e_group.load_file(path, []).config.tests[0]
    e2e_group.lower_client_priority(prefixed)
    assert prefixed.launch_prefix == "nice -n %d taskset -c 0" % e2e_group.CLIENT_NICE
    # the fixture's nodes are left as they are
    assert all(not n.launch_prefix for n in e2e_group.load_file(path, []).config.nodes)
