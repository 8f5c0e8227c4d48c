"""The controller_manager package's tools (compat/controller_manager) against
ros_control's documented behaviour, on the driver's controller manager:
`controller_manager load|unload|start|stop|spawn|kill|list|list-types`,
`spawner` (load and start; stop and unload when stopped itself; --stopped;
--timeout) and `unspawner` (keep controllers stopped while it runs). The
node and a virtual EPOS4 share python-can's in-process bus (node_with_sim.py).

`controller_manager COMMAND` runs the tool's main in the session's ROS
client process (node_session.py): one Python start for all of them. The
entry points run as the user's own processes where that is what a test
shows: the usage text, `controller_manager spawn` (and in
test_canopen_motor_node.py, as the seed's launch file runs it), the
spawner and the unspawner. Those that need no controller manager start
together at the module's start (``independent_runs``).
"""
from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path
from typing import List

import pytest

from node_session import Session, start_node

PKG = Path(__file__).resolve().parents[2]
TOOLS = PKG.parent / "compat" / "controller_manager" / "scripts"
JSC = "/maxon/canopen_motor/joint_state_controller"
POS = "/maxon/canopen_motor/base_link1_joint_position_controller"
VEL = "/maxon/canopen_motor/base_link1_joint_velocity_controller"


INDEPENDENT = {  # runs that need no controller manager: name -> (tool, args)
    "usage": ("controller_manager", ()),
    "unknown": ("controller_manager", ("explode",)),
    "spawner_timeout": ("spawner", ("--timeout", "1", "--namespace", "/nowhere", POS)),
    "unspawner_help": ("unspawner", ()),
}


@pytest.fixture(scope="module")
def session_and_runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("cli")
    s = Session(tmp, namespace="/maxon")  # as a launch file's <group ns="/maxon"> sets it
    runs = {}
    try:
        start_node(s, ("canopen_bus_layer.yaml", "controller_1dof_ppm.yaml", "node_layer_1dof_ppm.yaml"))
        # the master is up: these run beside the rest of the module
        runs = {name: subprocess.Popen([sys.executable, str(TOOLS / tool)] + list(args), env=s.env, text=True,
                                       stdout=subprocess.PIPE, stderr=subprocess.PIPE)
                for name, (tool, args) in INDEPENDENT.items()}
        assert s.call("/maxon/driver/init")["success"]
        yield s, runs
    finally:
        for proc in runs.values():
            if proc.poll() is None:
                proc.kill()
            proc.communicate()
        s.close()


@pytest.fixture
def session(session_and_runs):
    return session_and_runs[0]


def finished(session_and_runs, name: str) -> subprocess.CompletedProcess:
    """One of the INDEPENDENT runs, once it exited."""
    proc = session_and_runs[1][name]
    out, err = proc.communicate(timeout=120)
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def tool(session: Session, name: str, *args: str, timeout: float = 120.0) -> subprocess.CompletedProcess:
    """A tool's entry point in its own process, as the user runs it."""
    return session.run(sys.executable, str(TOOLS / name), *args, timeout=timeout)



def listed(session: Session) -> List[str]:
    run = session.controller_manager("list")
    assert run.returncode == 0, run.stderr
    return run.stdout.splitlines()


def test_usage_without_command_and_for_an_unknown_one(session_and_runs):
    run = finished(session_and_runs, "usage")
    assert run.returncode == 0 and run.stdout.startswith("Commands:")
    for command in ("load", "unload", "start", "stop", "spawn", "kill", "list", "list-types", "reload-libraries"):
        assert "    %s " % command in run.stdout
    run = finished(session_and_runs, "unknown")
    assert run.returncode == 1 and run.stdout.startswith("Commands:")


def test_list_when_nothing_is_loaded(session):
    assert listed(session) == ["No controllers are loaded in mechanism control"]


def test_load_start_stop_unload_one_by_one(session):
    run = session.controller_manager("load", POS)
    assert (run.returncode, run.stdout) == (0, "Loaded %s\n" % POS)
    assert session.controller_states() == {POS: "initialized"}
    assert listed(session)[0].startswith(POS + " - ") and listed(session)[0].endswith(" ( initialized )")
    run = session.controller_manager("start", POS)
    assert (run.returncode, run.stdout) == (0, "Started ['%s'] successfully\n" % POS)
    assert session.controller_states() == {POS: "running"}
    run = session.controller_manager("stop", POS)
    assert (run.returncode, run.stdout) == (0, "Stopped ['%s'] successfully\n" % POS)
    assert session.controller_states() == {POS: "stopped"}
    run = session.controller_manager("unload", POS)
    assert (run.returncode, run.stdout) == (0, "Unloaded %s successfully\n" % POS)
    assert session.controller_states() == {}


def test_spawn_loads_starts_and_exits_kill_stops_and_unloads(session):
    run = tool(session, "controller_manager", "spawn", JSC, POS)  # the entry point, in its own process
    assert run.returncode == 0, run.stdout + run.stderr
    assert run.stdout.splitlines() == ["Loaded %s" % JSC, "Loaded %s" % POS,
                                       "Started ['%s'] successfully" % JSC, "Started ['%s'] successfully" % POS]
    assert session.controller_states() == {JSC: "running", POS: "running"}
    run = session.controller_manager("kill", POS, JSC)
    assert run.returncode == 0, run.stdout + run.stderr
    assert session.controller_states() == {}


def test_failures_are_reported_and_set_the_exit_status(session):
    run = session.controller_manager("load", "/maxon/canopen_motor/no_such_controller")
    assert (run.returncode, run.stdout) == (1, "Error when loading /maxon/canopen_motor/no_such_controller\n")
    run = session.controller_manager("unload", POS)
    assert (run.returncode, run.stdout) == (1, "Error when unloading %s\n" % POS)


def test_list_types_prints_one_type_a_line(session):
    run = session.controller_manager("list-types")
    assert run.returncode == 0
    types = run.stdout.splitlines()
    assert "position_controllers/JointPositionController" in types
    assert "joint_state_controller/JointStateController" in types


def test_spawner_starts_then_stops_and_unloads_when_stopped(session):
    spawner = session.spawn([sys.executable, str(TOOLS / "spawner"), JSC, POS], "spawner.log")
    try:
        session.wait(lambda: session.controller_states() == {JSC: "running", POS: "running"},
                     "the spawner to load and start both")
        # the manager lists them running before the spawner has its answer
        started = "Started controllers: %s, %s" % (JSC, POS)
        session.wait(lambda: started in session.text("spawner.log"), "the spawner's %r" % started)
        assert spawner.poll() is None  # stays, to take them down later
    finally:
        interrupt(session, spawner, "spawner.log")
    assert session.controller_states() == {}


# How long a tool may take to end after SIGINT: it stops and unloads
# controllers through the manager's services first. Only bounds how long a
# tool that hangs takes to fail.
EXIT_TIMEOUT = 60.0


def interrupt(session: Session, proc: subprocess.Popen, log: str) -> None:
    """Ctrl-C to a tool, as a user or roslaunch stops it; it must end."""
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(EXIT_TIMEOUT)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        # the tool waits on the node's services: what the node did meanwhile
        raise AssertionError("%s did not end within %g s of SIGINT; its log:\n%s\nthe node's log:\n%s"
                             % (log, EXIT_TIMEOUT, session.log(log), session.log("node.log"))) from None


def spawner_loaded(session: Session, log: str, *names: str) -> None:
    """Wait until the spawner says it loaded ``names``: the controller
    manager lists a controller as loaded before the spawner has its answer
    and counts it as one to take down when it is stopped."""
    line = "Controller Spawner: Loaded controllers: %s" % ", ".join(names)
    session.wait(lambda: line in session.text(log), "the spawner's %r" % line)


def test_spawner_stopped_only_loads(session):
    spawner = session.spawn([sys.executable, str(TOOLS / "spawner"), "--stopped", POS], "spawner_stopped.log")
    try:
        session.wait(lambda: session.controller_states() == {POS: "initialized"}, "the spawner to load only")
        spawner_loaded(session, "spawner_stopped.log", POS)
    finally:
        interrupt(session, spawner, "spawner_stopped.log")
    assert session.controller_states() == {}


def test_spawner_gives_up_after_timeout_without_a_controller_manager(session_and_runs):
    run = finished(session_and_runs, "spawner_timeout")
    assert run.returncode == 0
    assert "Controller Spawner couldn't find the expected controller_manager ROS interface." in run.stderr + run.stdout


def test_spawner_loads_controller_parameters_from_a_yaml_file(session, tmp_path):
    extra = tmp_path / "extra.yaml"
    extra.write_text("/maxon/canopen_motor/extra_position_controller:\n"
                     "  type: position_controllers/JointPositionController\n"
                     "  joint: base_link1_joint\n")
    name = "/maxon/canopen_motor/extra_position_controller"
    spawner = session.spawn([sys.executable, str(TOOLS / "spawner"), "--stopped", str(extra)], "spawner_yaml.log")
    try:
        session.wait(lambda: session.controller_states() == {name: "initialized"},
                     "the spawner to load the controller its YAML file defines")
        spawner_loaded(session, "spawner_yaml.log", name)
    finally:
        interrupt(session, spawner, "spawner_yaml.log")
    assert session.controller_states() == {}


def test_unspawner_keeps_a_controller_stopped_and_restarts_it_on_exit(session):
    assert session.controller_manager("spawn", JSC, POS).returncode == 0
    unspawner = session.spawn([sys.executable, str(TOOLS / "unspawner"), POS], "unspawner.log")
    try:
        session.wait(lambda: session.controller_states() == {JSC: "running", POS: "stopped"},
                     "the unspawner to stop the position controller")
    finally:
        interrupt(session, unspawner, "unspawner.log")
    assert session.controller_states() == {JSC: "running", POS: "running"}
    assert session.controller_manager("kill", POS, JSC).returncode == 0


def test_unspawner_without_names_prints_its_help(session_and_runs):
    run = finished(session_and_runs, "unspawner_help")
    assert run.returncode == 1 and "Stops a set of controllers until killed." in run.stdout
