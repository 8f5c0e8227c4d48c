"""The controller_manager package's tools (compat/controller_manager) against
ros_control's documented behaviour, on the driver's controller manager:
`controller_manager load|unload|start|stop|spawn|kill|list|list-types`,
`spawner` (load and start; stop and unload when stopped itself; --stopped;
--timeout) and `unspawner` (keep controllers stopped while it runs). The
node and a virtual EPOS4 share python-can's in-process bus (node_with_sim.py).
"""
from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path
from typing import List

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_canopen_motor_node import Session, controller_states, start_node  # noqa: E402

PKG = Path(__file__).resolve().parents[2]
TOOLS = PKG.parent / "compat" / "controller_manager" / "scripts"
JSC = "/maxon/canopen_motor/joint_state_controller"
POS = "/maxon/canopen_motor/base_link1_joint_position_controller"
VEL = "/maxon/canopen_motor/base_link1_joint_velocity_controller"


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("cli")
    s = Session(tmp)
    s.env["ROS_NAMESPACE"] = "/maxon"  # as a launch file's <group ns="/maxon"> sets it
    start_node(s, ("canopen_bus_layer.yaml", "controller_1dof_ppm.yaml", "node_layer_1dof_ppm.yaml"))
    assert s.call("/maxon/driver/init")["success"]
    yield s
    s.close()


def tool(session: Session, name: str, *args: str, timeout: float = 120.0) -> subprocess.CompletedProcess:
    return session.run(sys.executable, str(TOOLS / name), *args, timeout=timeout)


def listed(session: Session) -> List[str]:
    run = tool(session, "controller_manager", "list")
    assert run.returncode == 0, run.stderr
    return run.stdout.splitlines()


def test_usage_without_command_and_for_an_unknown_one(session):
    run = tool(session, "controller_manager")
    assert run.returncode == 0 and run.stdout.startswith("Commands:")
    for command in ("load", "unload", "start", "stop", "spawn", "kill", "list", "list-types", "reload-libraries"):
        assert "    %s " % command in run.stdout
    run = tool(session, "controller_manager", "explode")
    assert run.returncode == 1 and run.stdout.startswith("Commands:")


def test_list_when_nothing_is_loaded(session):
    assert listed(session) == ["No controllers are loaded in mechanism control"]


def test_load_start_stop_unload_one_by_one(session):
    run = tool(session, "controller_manager", "load", POS)
    assert (run.returncode, run.stdout) == (0, "Loaded %s\n" % POS)
    assert controller_states(session) == {POS: "initialized"}
    assert listed(session)[0].startswith(POS + " - ") and listed(session)[0].endswith(" ( initialized )")
    run = tool(session, "controller_manager", "start", POS)
    assert (run.returncode, run.stdout) == (0, "Started ['%s'] successfully\n" % POS)
    assert controller_states(session) == {POS: "running"}
    run = tool(session, "controller_manager", "stop", POS)
    assert (run.returncode, run.stdout) == (0, "Stopped ['%s'] successfully\n" % POS)
    assert controller_states(session) == {POS: "stopped"}
    run = tool(session, "controller_manager", "unload", POS)
    assert (run.returncode, run.stdout) == (0, "Unloaded %s successfully\n" % POS)
    assert controller_states(session) == {}


def test_spawn_loads_starts_and_exits_kill_stops_and_unloads(session):
    run = tool(session, "controller_manager", "spawn", JSC, POS)
    assert run.returncode == 0, run.stdout + run.stderr
    assert run.stdout.splitlines() == ["Loaded %s" % JSC, "Loaded %s" % POS,
                                       "Started ['%s'] successfully" % JSC, "Started ['%s'] successfully" % POS]
    assert controller_states(session) == {JSC: "running", POS: "running"}
    run = tool(session, "controller_manager", "kill", POS, JSC)
    assert run.returncode == 0, run.stdout + run.stderr
    assert controller_states(session) == {}


def test_failures_are_reported_and_set_the_exit_status(session):
    run = tool(session, "controller_manager", "load", "/maxon/canopen_motor/no_such_controller")
    assert (run.returncode, run.stdout) == (1, "Error when loading /maxon/canopen_motor/no_such_controller\n")
    run = tool(session, "controller_manager", "unload", POS)
    assert (run.returncode, run.stdout) == (1, "Error when unloading %s\n" % POS)


def test_list_types_prints_one_type_a_line(session):
    run = tool(session, "controller_manager", "list-types")
    assert run.returncode == 0
    types = run.stdout.splitlines()
    assert "position_controllers/JointPositionController" in types
    assert "joint_state_controller/JointStateController" in types


def test_spawner_starts_then_stops_and_unloads_when_stopped(session):
    spawner = session.spawn([sys.executable, str(TOOLS / "spawner"), JSC, POS], "spawner.log")
    try:
        session.wait(lambda: controller_states(session) == {JSC: "running", POS: "running"},
                     "the spawner to load and start both")
        assert spawner.poll() is None  # stays, to take them down later
    finally:
        spawner.send_signal(signal.SIGINT)
        spawner.wait(60)
    assert controller_states(session) == {}
    assert "Started controllers: %s, %s" % (JSC, POS) in session.log("spawner.log")


def test_spawner_stopped_only_loads(session):
    spawner = session.spawn([sys.executable, str(TOOLS / "spawner"), "--stopped", POS], "spawner_stopped.log")
    try:
        session.wait(lambda: controller_states(session) == {POS: "initialized"}, "the spawner to load only")
    finally:
        spawner.send_signal(signal.SIGINT)
        spawner.wait(60)
    assert controller_states(session) == {}


def test_spawner_gives_up_after_timeout_without_a_controller_manager(session):
    run = tool(session, "spawner", "--timeout", "1", "--namespace", "/nowhere", POS)
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
        session.wait(lambda: controller_states(session) == {name: "initialized"},
                     "the spawner to load the controller its YAML file defines")
    finally:
        spawner.send_signal(signal.SIGINT)
        spawner.wait(60)
    assert controller_states(session) == {}


def test_unspawner_keeps_a_controller_stopped_and_restarts_it_on_exit(session):
    assert tool(session, "controller_manager", "spawn", JSC, POS).returncode == 0
    unspawner = session.spawn([sys.executable, str(TOOLS / "unspawner"), POS], "unspawner.log")
    try:
        session.wait(lambda: controller_states(session) == {JSC: "running", POS: "stopped"},
                     "the unspawner to stop the position controller")
    finally:
        unspawner.send_signal(signal.SIGINT)
        unspawner.wait(60)
    assert controller_states(session) == {JSC: "running", POS: "running"}
    assert tool(session, "controller_manager", "kill", POS, JSC).returncode == 0


def test_unspawner_without_names_prints_its_help(session):
    run = tool(session, "unspawner")
    assert run.returncode == 1 and "Stops a set of controllers until killed." in run.stdout
