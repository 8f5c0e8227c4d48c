#!/usr/bin/env python3
"""Run rostest files that share a fixture against one master and one launch.

    e2e_group.py RESULTS_DIR FILE.test [FILE.test ...] [--arg device:=vcan0]

rostest starts a master and every node of a .test file for each <test> in
it. In user-mode Linux a node needs 10-40 s to start, and most of the suite's
files start the same launch file, so this runner:

- loads every file with roslaunch's own loader and groups the files whose
  fixture (every node and parameter that is not a <test> or the test's own
  parameters) is identical, in the order the files were given;
- per group, starts one master and the fixture once, then runs the files'
  tests one after the other against it, each with its own time limit;
- before each test, restarts the fixture nodes that died with an error or a
  signal, and those the previous test said it ends (private parameter
  e2e_kills: a master-loss test ends the driver, which exits with status 0
  after SIGINT or SIGTERM), and then runs once more the nodes that had
  ended by themselves with status 0 (one-shot set-up steps such as the
  controller spawner, which act on the restarted node);
- runs each test client below the fixture's priority (CLIENT_NICE);
- writes each file's results where rostest would (RESULTS_DIR/xml/<pkg>.<file>:
  the test's rosunit-*.xml and a rostest-*.xml saying whether it ran) and one
  manifest line per file "<pkg> <file> <status> <seconds> <group>", so a test
  that fails names itself and the group's other tests still run and report.

The grouping and the restart rule are plain functions (plan_groups,
FixtureNodes) with unit tests in tests/unit/test_e2e_group.py.
"""
from __future__ import annotations

import argparse
import copy
import glob
import os
import shutil
import sys
import time
import traceback
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, Iterable, List, Optional, Sequence, Tuple
from xml.sax.saxutils import escape, quoteattr


# --- grouping (no ROS needed to test it) ---------------------------------------

FRESH_LAUNCH_PARAM = "e2e_fresh_launch"
# A test that ends fixture nodes on purpose names them here (space-separated
# node names): a node ended by SIGINT or SIGTERM exits with status 0, like a
# set-up step that finished, and only the test knows it meant to end it.
KILLS_PARAM = "e2e_kills"
# Inside the guest the fixture (the simulated drives, the driver, the master)
# is the real-time part: its SYNC, heartbeats and TxPDOs are what the tests
# judge. The test clients only command and observe it, and each start of a
# client or command-line tool costs seconds of CPU in user-mode Linux. They
# run at a lower priority, so that their work waits for the fixture's, not
# the other way round.
CLIENT_NICE = 5


@dataclass
class RostestFile:
    """One .test file: its package, path, fixture key and loaded config.
    `fresh`: its test needs the fixture as it starts (it checks what the
    nodes do before anything commanded them), so it runs first in a group."""
    pkg: str
    path: str
    key: str
    config: Any = None
    fresh: bool = False
    kills: List[str] = field(default_factory=list)

    @property
    def name(self) -> str:
        return os.path.basename(self.path)


@dataclass
class Group:
    key: str
    files: List[RostestFile] = field(default_factory=list)

    @property
    def name(self) -> str:
        first = self.files[0]
        return "%s.%s" % (first.pkg, os.path.splitext(first.name)[0])


def plan_groups(files: Sequence[RostestFile]) -> List[Group]:
    """Files with the same fixture key in one group, groups in the order of
    their first file, files in a group in the order given. A file that needs
    a fresh launch heads a group: the first such file of a key heads the
    group that also takes the key's other files; each further one gets a
    group (and a launch) of its own."""
    by_key: Dict[str, List[RostestFile]] = {}
    for f in files:
        by_key.setdefault(f.key, []).append(f)
    groups = []
    for key, members in by_key.items():
        heads = [f for f in members if f.fresh]
        rest = [f for f in members if not f.fresh]
        groups.append(Group(key, heads[:1] + rest))
        groups.extend(Group(key, [h]) for h in heads[1:])
    return groups


DEFAULT_FILE_SECONDS = 90.0  # a file's weight when no earlier run timed it


def assign_shards(groups: Sequence[Group], count: int, seconds: Dict[str, float]) -> List[List[Group]]:
    """Groups in `count` shards of about equal time (longest first into the
    shard with the least so far); `seconds` maps a file name to its time in
    an earlier run. Each shard keeps the groups' order."""
    weight = {id(g): sum(seconds.get(f.name, DEFAULT_FILE_SECONDS) for f in g.files) for g in groups}
    load = [0.0] * count
    chosen: Dict[int, int] = {}
    for g in sorted(groups, key=lambda g: -weight[id(g)]):
        i = load.index(min(load))
        chosen[id(g)] = i
        load[i] += weight[id(g)]
    return [[g for g in groups if chosen[id(g)] == i] for i in range(count)]


def seconds_from_manifest(path: Optional[str]) -> Dict[str, float]:
    """file name -> seconds from a manifest of an earlier run (none: {})."""
    out: Dict[str, float] = {}
    if not path or not os.path.exists(path):
        return out
    with open(path) as f:
        for line in f:
            entry = line.split()
            try:
                out[entry[1]] = float(entry[3])
            except (IndexError, ValueError):
                continue
    return out


def _node_key(node: Any) -> Tuple:
    return (node.package, node.type, node.name, node.namespace, node.args, tuple(sorted(node.remap_args)),
            tuple(sorted(node.env_args)), node.respawn, node.required, node.output, node.cwd,
            node.launch_prefix)


def _test_params(config: Any, name: str) -> List[Any]:
    return [p.value for ns in private_namespaces(config) for k, p in config.params.items() if k == ns + name]


def lower_client_priority(test: Any, nice: int = CLIENT_NICE) -> None:
    """Start the <test> node (and the tools it runs) at niceness ``nice``,
    before any launch-prefix of its own; once, however often it runs."""
    prefix = "nice -n %d" % nice
    own = (test.launch_prefix or "").strip()
    if not own.startswith(prefix):
        test.launch_prefix = (prefix + " " + own).strip()


def wants_fresh_launch(config: Any) -> bool:
    """A test with the private parameter e2e_fresh_launch set true."""
    return any(v is True or str(v).lower() == "true" for v in _test_params(config, FRESH_LAUNCH_PARAM))


def nodes_killed(config: Any) -> List[str]:
    """The fixture nodes a test says it ends (private parameter e2e_kills)."""
    return [name for v in _test_params(config, KILLS_PARAM) for name in str(v).split()]


def private_namespaces(config: Any) -> List[str]:
    """The namespaces of the config's <test> nodes: their private parameters."""
    out = []
    for t in config.tests:
        name = t.name or t.test_name
        out.append((t.namespace or "/").rstrip("/") + "/" + name + "/")
    return out


def fixture_key(config: Any) -> str:
    """What a launch starts and sets, without its tests and their private
    parameters: equal keys mean one launch serves all."""
    private = private_namespaces(config)
    params = sorted((k, repr(p.value)) for k, p in config.params.items()
                    if k != "/run_id" and not any(k.startswith(ns) for ns in private))
    nodes = [_node_key(n) for n in config.nodes]
    executables = [(e.command, tuple(e.args), e.phase) for e in config.executables]
    return repr((nodes, params, executables, sorted(config.clear_params)))


# --- restart of killed fixture nodes -----------------------------------------

class FixtureNodes:
    """The fixture's processes, launched in launch order, and the rule for
    bringing them back between tests: every node that ended with an error or
    a signal, and every node the last test said it ends (whatever its exit
    status), starts again; when one did, the nodes that had ended by
    themselves with status 0 (set-up steps such as the controller spawner,
    which act on the restarted node) run again after it, in launch order."""

    def __init__(self, nodes: Sequence[Any], launch: Callable[[Any], Any]) -> None:
        self._nodes = list(nodes)
        self._launch = launch
        self._procs: List[Any] = []
        self.restarts: List[str] = []

    def start(self) -> List[str]:
        """Launch every node; the names of those that failed to start."""
        failed = []
        for node in self._nodes:
            proc, ok = self._launch(node)
            self._procs.append(proc if ok else None)
            if not ok:
                failed.append(_node_name(node))
        return failed

    @staticmethod
    def _ended(proc: Any) -> bool:
        return proc is None or not proc.is_alive()

    def restart_dead(self, killed: Sequence[str] = ()) -> List[str]:
        """Bring back what a test killed (``killed``: the node names it said
        it ends); the names restarted, in order."""
        died = [i for i, p in enumerate(self._procs) if self._ended(p)
                and (not _clean_exit(p) or _node_name(self._nodes[i]) in killed)]
        if not died:
            return []
        one_shot = [i for i, p in enumerate(self._procs) if self._ended(p) and i not in died]
        names = []
        for i in sorted(died + one_shot):
            proc, ok = self._launch(self._nodes[i])
            self._procs[i] = proc if ok else None
            names.append(_node_name(self._nodes[i]))
        self.restarts.extend(names)
        return names


def _clean_exit(proc: Any) -> bool:
    return proc is not None and getattr(proc, "exit_code", None) == 0


def _node_name(node: Any) -> str:
    return (node.namespace or "/").rstrip("/") + "/" + str(node.name or node.type)


# --- results ---------------------------------------------------------------------

@dataclass
class Outcome:
    """What happened to one test file in its group."""
    file: RostestFile
    seconds: float = 0.0
    status: int = 0          # 0 ran and wrote results; 1 failed to run or run badly
    message: str = ""
    restarted: List[str] = field(default_factory=list)


def junit_one_case(suite: str, case: str, seconds: float, failure: Optional[str], system_out: str = "") -> str:
    fail = "" if failure is None else '\n    <failure message=%s type=""/>' % quoteattr(failure)
    return ('<?xml version="1.0" encoding="utf-8"?>\n'
            '<testsuite name=%s tests="1" failures="%d" errors="0" time="%.1f">\n'
            '  <testcase classname=%s name=%s time="%.1f">%s\n  </testcase>\n'
            '  <system-out>%s</system-out>\n</testsuite>\n') % (
        quoteattr(suite), 0 if failure is None else 1, seconds, quoteattr(suite), quoteattr(case), seconds,
        fail, escape(system_out))


def failed_cases(result: Any, limit: int = 300) -> List[str]:
    """Each failed test case of a rosunit result with the line of its
    failure text that says what failed: CI shows only part of a run's
    output, so the FAIL line itself has to say which assertion failed."""
    lines = []
    for case in getattr(result, "test_case_results", []):
        for kind, items in (("failure", case.failures), ("error", case.errors)):
            for item in items:
                text = [ln.strip() for ln in (item.text or "").splitlines() if ln.strip()]
                # rostest puts the message first and the traceback after it;
                # a plain traceback ends with the message
                said = (text[-1] if text[0].startswith("Traceback") else text[0]) if text else kind
                lines.append("%s: %s" % (case.name.rsplit("/", 1)[-1], said[:limit]))
    return lines


TELLING = ("failed", "Error", "error:", "Unsafe", "timed out")


def telling_lines(log_path: str, count: int = 12, width: int = 300) -> List[str]:
    """The last lines of a failed test's own log that say what went wrong;
    printed under its FAIL line, which the suite's filter lets through."""
    try:
        with open(log_path, errors="replace") as src:
            lines = [ln.rstrip() for ln in src if any(word in ln for word in TELLING)]
    except OSError:
        return []
    return [ln[:width] for ln in lines[-count:]]


def run_tests_in_order(files: Sequence[RostestFile], run_one: Callable[[RostestFile], Outcome],
                       before_each: Callable[[Optional[RostestFile]], List[str]],
                       report: Callable[[Outcome], None] = lambda out: None) -> List[Outcome]:
    """Each file's test in turn, each outcome reported as soon as it is known;
    an exception in one is that file's failure and never stops the others.
    ``before_each(previous file or None)`` restores the fixture first."""
    outcomes = []
    previous: Optional[RostestFile] = None
    for f in files:
        t0 = time.time()
        try:
            restarted = before_each(previous)
            out = run_one(f)
            out.restarted = restarted
        except Exception as exc:  # the next file still runs and reports
            out = Outcome(f, status=1, message="%s: %s" % (type(exc).__name__, exc))
            traceback.print_exc()
        out.seconds = time.time() - t0
        outcomes.append(out)
        previous = f
        report(out)
    return outcomes


def manifest_line(out: Outcome, group: Group) -> str:
    return "%s %s %d %.1f %s\n" % (out.file.pkg, out.file.name, out.status, out.seconds, group.name)


# --- the ROS part ----------------------------------------------------------------

# roslaunch runs a <param command="..."> afresh for every file it loads:
# roscore.xml's two `rosversion` parameters and each robot's xacro. In
# user-mode Linux each is a Python start of a second or two, 66 of them for
# the suite's files, and each shard loads every file to plan its groups.
# Within one run of this runner a command's output does not change, so each
# distinct command runs once (a command that fails is tried again).
_COMMAND_OUTPUTS: Dict[Tuple[str, str], Any] = {}


def _loader() -> Any:
    """roslaunch's XML loader, running each distinct param command once."""
    import roslaunch.xmlloader

    class OnceLoader(roslaunch.xmlloader.XmlLoader):
        def param_value(self, verbose, name, ptype, value, textfile, binfile, command):
            if command is None:
                return super().param_value(verbose, name, ptype, value, textfile, binfile, command)
            key = (str(ptype), str(command))
            if key not in _COMMAND_OUTPUTS:
                _COMMAND_OUTPUTS[key] = super().param_value(verbose, name, ptype, value, textfile, binfile, command)
            return copy.deepcopy(_COMMAND_OUTPUTS[key])

    return OnceLoader()


def load_file(path: str, launch_args: Sequence[str]) -> RostestFile:
    import roslaunch.config
    import rospkg
    config = roslaunch.config.load_config_default([(path, list(launch_args))], None, loader=_loader())
    pkg = rospkg.get_package_name(path) or os.path.basename(os.path.dirname(os.path.dirname(os.path.dirname(
        os.path.abspath(path)))))
    return RostestFile(pkg, path, fixture_key(config), config, wants_fresh_launch(config), nodes_killed(config))


def merged_config(group: Group) -> Any:
    """The first file's config with every other file's tests and their
    private parameters added."""
    base = group.files[0].config
    for f in group.files[1:]:
        private = private_namespaces(f.config)
        for k, p in f.config.params.items():
            if any(k.startswith(ns) for ns in private):
                base.add_param(p, verbose=False)
        for t in f.config.tests:
            base.tests.append(t)
    return base


def run_group(group: Group, results: str, report: Callable[[Outcome], None]) -> List[Outcome]:
    import rospkg
    from roslaunch.launch import RLTestTimeoutException
    from rostest.rostest_parent import ROSTestLaunchParent
    import rosunit
    import rosunit.junitxml

    tests_of = {f.path: list(f.config.tests) for f in group.files}  # before the merge adds to the first
    config = merged_config(group)
    parent = ROSTestLaunchParent(config, [f.path for f in group.files])
    parent.setUp()  # a master of its own on a free port, and the launch runner
    runner = parent.runner
    log_dir = rospkg.get_log_dir()
    try:
        runner._setup()  # parameters (rostest's launch() does this, then starts the nodes)
        fixture = FixtureNodes(config.nodes, runner.launch_node)
        failed = fixture.start()
        print("group %s: master %s, run_id %s, fixture %s%s" % (
            group.name, config.master.uri, parent.run_id, ", ".join(_node_name(n) for n in config.nodes) or "none",
            "; FAILED TO START: " + ", ".join(failed) if failed else ""), flush=True)

        def before_each(previous: Optional[RostestFile]) -> List[str]:
            runner.spin_once()
            names = fixture.restart_dead(previous.kills if previous is not None else ())
            if names:
                print("group %s: restarted %s" % (group.name, ", ".join(names)), flush=True)
            return names

        def run_one(f: RostestFile) -> Outcome:
            xml_base = os.path.join(results, "xml", "%s.%s" % (f.pkg, f.name))
            shutil.rmtree(xml_base, ignore_errors=True)
            problems = []
            started = time.time()
            env = {"ROS_TEST_RESULTS_DIR": xml_base}
            if failed:
                problems.append("fixture nodes %s failed to launch" % failed)
            for test in tests_of[f.path]:
                result_file = rosunit.xml_results_file(f.pkg, test.test_name, False, env=env)
                os.makedirs(os.path.dirname(result_file), exist_ok=True)
                test.args = "%s --gtest_output=xml:%s" % (test.args, result_file)
                print("group %s: test %s (%s)" % (group.name, test.test_name, f.name), flush=True)
                lower_client_priority(test)
                try:
                    runner.run_test(test)
                except RLTestTimeoutException as exc:
                    problems.append(str(exc))
                    runner.pm.kill_process(test.process_name)
                except Exception as exc:
                    problems.append("%s: %s" % (type(exc).__name__, exc))
                if not os.path.isfile(result_file):
                    problems.append("test [%s] did not write results" % test.test_name)
                    continue
                r = rosunit.junitxml.read(result_file, test.test_name)
                if r.num_errors or r.num_failures:
                    problems.append("test [%s]: %d errors, %d failures" % (test.test_name, r.num_errors,
                                                                            r.num_failures))
                    problems.extend("test [%s] %s" % (test.test_name, c) for c in failed_cases(r))
            secs = time.time() - started
            outname = os.path.splitext(f.name)[0]
            top = rosunit.xml_results_file(f.pkg, outname, True, env=env)
            os.makedirs(os.path.dirname(top), exist_ok=True)
            ran_badly = [p for p in problems if not p.startswith("test [") or "did not write" in p]
            with open(top, "w") as out:
                out.write(junit_one_case(
                    "%s.%s" % (f.pkg, outname), "test_ran", secs,
                    "; ".join(ran_badly) if ran_badly else None,
                    "run_id[%s] group[%s]" % (parent.run_id, group.name)))
            _copy_test_logs(log_dir, parent.run_id, tests_of[f.path],
                            os.path.join(results, "logs", "%s.%s.log" % (f.pkg, f.name)), problems)
            return Outcome(f, status=1 if problems else 0, message="; ".join(problems))

        return run_tests_in_order(group.files, run_one, before_each, report)
    finally:
        parent.tearDown()


def _copy_test_logs(log_dir: Optional[str], run_id: str, tests: Iterable[Any], dest: str,
                    problems: Sequence[str]) -> None:
    """The test node's own output (roslaunch keeps it in the run's log folder)."""
    os.makedirs(os.path.dirname(dest), exist_ok=True)
    with open(dest, "w") as out:
        for p in problems:
            out.write("e2e_group: %s\n" % p)
        if not log_dir:
            return
        for test in tests:
            for path in sorted(glob.glob(os.path.join(log_dir, run_id, "%s-*.log" % (test.process_name or "")))):
                with open(path, errors="replace") as src:
                    out.write("--- %s\n" % os.path.basename(path))
                    out.write(src.read())


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results")
    ap.add_argument("files", nargs="+")
    ap.add_argument("--arg", action="append", default=[], help="launch argument NAME:=VALUE for every file")
    ap.add_argument("--plan", action="store_true", help="print the groups and stop")
    ap.add_argument("--shard", default="1/1", help="I/N: run only the I-th of N shards of about equal time")
    ap.add_argument("--times", help="manifest of an earlier run: the files' seconds, to balance the shards")
    ap.add_argument("--manifest", help="manifest file (default RESULTS/manifest)")
    args = ap.parse_args(argv)
    shard, shards = (int(x) for x in args.shard.split("/"))

    import roslaunch.core
    roslaunch.core.add_printlog_handler(lambda msg: None)
    os.makedirs(os.path.join(args.results, "xml"), exist_ok=True)
    manifest = args.manifest or os.path.join(args.results, "manifest")
    loaded, broken = [], []
    for path in args.files:
        try:
            loaded.append(load_file(path, args.arg))
        except Exception as exc:  # a broken file fails alone
            broken.append((path, exc))
            print("cannot load %s: %s" % (path, exc), flush=True)
    groups = plan_groups(loaded)
    if shards > 1:
        groups = assign_shards(groups, shards, seconds_from_manifest(args.times))[shard - 1]
        broken = broken if shard == 1 else []
        print("--- shard %d of %d: %d files" % (shard, shards, sum(len(g.files) for g in groups)), flush=True)
    print("--- %d rostest files in %d groups" % (sum(len(g.files) for g in groups) + len(broken), len(groups)),
          flush=True)
    for g in groups:
        print("    %s: %s" % (g.name, " ".join(f.name for f in g.files)), flush=True)
    if args.plan:
        return 0
    for path, exc in broken:
        pkg = os.path.basename(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(path)))))
        with open(manifest, "a") as m:
            m.write("%s %s 1 0.0 unloadable\n" % (pkg, os.path.basename(path)))
        print("FAIL  %s: cannot load: %s" % (path, exc), flush=True)
    for g in groups:
        t0 = time.time()

        def report(out: Outcome, g: Group = g) -> None:
            with open(manifest, "a") as m:
                m.write(manifest_line(out, g))
            restarted = " (restarted first: %s)" % ", ".join(out.restarted) if out.restarted else ""
            if out.status == 0:
                print("ok    %s/%s (%.1fs)%s" % (out.file.pkg, out.file.name, out.seconds, restarted), flush=True)
            else:
                print("FAIL  %s/%s (%.1fs)%s: %s" % (out.file.pkg, out.file.name, out.seconds, restarted,
                                                    out.message), flush=True)
                log = os.path.join(args.results, "logs", "%s.%s.log" % (out.file.pkg, out.file.name))
                for line in telling_lines(log):
                    print("FAIL    | %s" % line, flush=True)

        done: List[Outcome] = []
        try:
            run_group(g, args.results, lambda out: (done.append(out), report(out)))
        except Exception as exc:  # the group's files that did not run still report
            traceback.print_exc()
            ran = {out.file.path for out in done}
            for f in g.files:
                if f.path not in ran:
                    report(Outcome(f, status=1, message="group failed before this test: %s" % exc))
        print("group %s: %d files in %.1fs" % (g.name, len(g.files), time.time() - t0), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
