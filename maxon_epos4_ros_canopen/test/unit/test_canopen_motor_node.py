"""canopen_motor_node's ROS interface, natively: the node and a virtual EPOS4
share python-can's in-process bus (node_with_sim.py), a private master
serves the parameters (node_session.py).

Most steps go through one ROS client process (ros_client.py) that does what
the user's command-line tools do with the same library calls; a few steps
run the tools themselves, as the seeds type them, to prove they work:
`rosservice call` (init, set_object), `rostopic pub -1`, `rostopic echo`
and compat/controller_manager's `controller_manager spawn`.

The same session runs on a real vcan0 in test/rostest/driver_1dof_ppm.test;
this one gives the fast suite the node's adapter code (services, controller
manager, topics, diagnostics, bad input) without SocketCAN.
"""
from __future__ import annotations

import shutil
import subprocess
import sys
import time
from typing import Any, Dict, List

import pytest
import yaml

from node_session import CM_PKG, JOINT, PKG, REPO, Session, start_node

POS_CTRL = "/maxon/canopen_motor/base_link1_joint_position_controller"
VEL_CTRL = "/maxon/canopen_motor/base_link1_joint_velocity_controller"

if shutil.which("rosmaster") is None or shutil.which("rosservice") is None:
    pytest.fail("ROS 1 command-line tools (rosmaster, rosservice) are not installed: run tools/setup.sh",
                pytrace=False)
try:
    import controller_manager_msgs.srv  # noqa: F401
    import canopen_chain_node.srv  # noqa: F401
except ImportError:
    pytest.fail("message packages not built: run tools/setup.sh and source tools/env.sh", pytrace=False)


def get_value(session: Session, obj: str, cached: str = "false") -> str:
    answer = session.call("/maxon/driver/get_object", JOINT, "!!str " + obj, cached)
    assert answer["success"], answer
    return str(answer["value"])



@pytest.fixture(scope="module")
def session(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("node")
    s = Session(tmp)
    start_node(s, ("canopen_bus_layer.yaml", "controller_1dof_ppm.yaml", "node_layer_1dof_ppm.yaml",
                   "ros_layer.yaml"))
    s.spawner = s.spawn([sys.executable, str(CM_PKG / "scripts" / "controller_manager"), "spawn",
                         "/maxon/canopen_motor/joint_state_controller", POS_CTRL,
                         "__ns:=/maxon", "__name:=controller_spawner"], "spawner.log")
    yield s
    s.close()


def rosservice_call(session: Session, *args: str) -> Dict[str, Any]:
    """`rosservice call ARGS...`, the tool itself in its own process."""
    proc = session.run("rosservice", "call", *args)
    assert proc.returncode == 0, "rosservice call %s: %s %s" % (args, proc.stdout, proc.stderr)
    return yaml.safe_load(proc.stdout)


def test_01_init_brings_up_the_controller_manager_and_controllers(session):
    answer = rosservice_call(session, "/maxon/driver/init")  # as the seed types it
    assert answer["success"] is True, answer
    session.wait(lambda: session.controller_states().get(POS_CTRL) == "running", "the spawner to start controllers")
    assert session.controller_states()["/maxon/canopen_motor/joint_state_controller"] == "running"
    assert get_value(session, "6061") == "1"
    services = session.services()
    for name in ("list_controllers", "list_controller_types", "load_controller", "unload_controller",
                 "switch_controller", "reload_controller_libraries"):
        assert "/maxon/controller_manager/" + name in services


def test_02_position_command_moves_the_joint(session):
    # `rostopic pub -1` as the seed types it
    proc = session.run("rostopic", "pub", "-1", POS_CTRL + "/command", "std_msgs/Float64", "--", "1000")
    assert proc.returncode == 0, proc.stderr
    session.wait(lambda: get_value(session, "607A") == "1000", "0x607A of the drive to be 1000")

    states = []

    def at_target() -> bool:
        msg = session.echo("/maxon/joint_states")
        states.append((msg, time.time()))
        return bool(msg) and msg["name"] == [JOINT] and abs(msg["position"][0] - 1000.0) < 0.5

    session.wait(at_target, "joint_states to report 1000")
    # stamped with when the drive's TPDOs arrived (wall clock): before the
    # message was received, and not long before on a drive answering every SYNC
    msg, received = states[-1]
    stamp = msg["header"]["stamp"]["secs"] + msg["header"]["stamp"]["nsecs"] * 1e-9
    assert received - 10.0 < stamp <= received, (stamp, received)


def test_03_objects_round_trip_with_the_seed_syntax(session):
    # `rosservice call` as the seed types it, with YAML tags
    answer = rosservice_call(session, "/maxon/driver/set_object", JOINT, "!!str 6081", "!!str 1000", "false")
    assert answer["success"], answer
    assert get_value(session, "6081") == "1000"
    answer = session.call("/maxon/driver/set_object", JOINT, "6099sub02", "!!str 12", "false")
    assert answer["success"], answer
    assert str(session.call("/maxon/driver/get_object", JOINT, "6099sub02", "false")["value"]) == "12"
    assert str(session.call("/maxon/driver/get_object", JOINT, "6099sub2", "false")["value"]) == "12"


def test_04_ros_layer_objects_are_published_with_their_data_type(session):
    topic = "/maxon/%s_6041" % JOINT
    session.wait(lambda: session.topic_type(topic) == "std_msgs/UInt16", "the statusword topic")
    echo = session.run("rostopic", "echo", "-n", "1", topic)  # the tool itself
    assert echo.returncode == 0, echo.stderr
    statusword = yaml.safe_load(echo.stdout.split("---")[0])["data"]
    assert statusword & 0x6F == 0x27  # operation enabled


def test_05_switch_to_velocity_controller_changes_the_mode(session):
    assert session.call("/maxon/controller_manager/load_controller", VEL_CTRL)["ok"]
    answer = session.call("/maxon/controller_manager/switch_controller",
                          "{start_controllers: ['%s'], stop_controllers: ['%s'], strictness: 2}"
                          % (VEL_CTRL, POS_CTRL))
    assert answer["ok"], session.log("node.log")
    assert get_value(session, "6061") == "3"
    answer = session.call("/maxon/controller_manager/switch_controller",
                          "{start_controllers: ['%s'], stop_controllers: ['%s'], strictness: 2}"
                          % (POS_CTRL, VEL_CTRL))
    assert answer["ok"]
    assert get_value(session, "6061") == "1"
    states = session.controller_states()
    assert states[VEL_CTRL] == "stopped" and states[POS_CTRL] == "running"


@pytest.mark.parametrize("ctype,mode,topic_value,obj", [
    ("velocity_controllers/JointVelocityController", 9, "250", "60FF"),  # CSV
    ("effort_controllers/JointEffortController", 10, "100", "6071"),  # CST: eff_to_device rint(eff)
])
def test_05b_cyclic_modes_through_the_generic_mode_switch(session, ctype, mode, topic_value, obj):
    name = "/maxon/canopen_motor/cyclic_%d_controller" % mode
    session.set_param(name, {"type": ctype, "joint": JOINT, "required_drive_mode": mode})
    assert session.call("/maxon/controller_manager/load_controller", name)["ok"]
    answer = session.call("/maxon/controller_manager/switch_controller",
                          "{start_controllers: ['%s'], stop_controllers: ['%s'], strictness: 2}" % (name, POS_CTRL))
    assert answer["ok"], session.log("node.log")
    try:
        assert get_value(session, "6061") == str(mode)
        session.publish(name + "/command", "std_msgs/Float64", topic_value)
        session.wait(lambda: get_value(session, obj) == topic_value, "0x%s to be %s" % (obj, topic_value))
    finally:
        answer = session.call("/maxon/controller_manager/switch_controller",
                              "{start_controllers: ['%s'], stop_controllers: ['%s'], strictness: 2}"
                              % (POS_CTRL, name))
        assert answer["ok"]
        assert session.call("/maxon/controller_manager/unload_controller", name)["ok"]
    assert get_value(session, "6061") == "1"


@pytest.mark.parametrize("args,mention", [
    (("/maxon/driver/get_object", "no_such_joint", "!!str 6081", "false"), "no_such_joint"),
    (("/maxon/driver/get_object", JOINT, "!!str 60G1", "false"), "60G1"),
    (("/maxon/driver/set_object", JOINT, "!!str 6098", "!!str 300", "false"), "300"),
    (("/maxon/driver/set_object", JOINT, "!!str 6041", "!!str 1", "false"), "read-only"),
])
def test_06_bad_requests_are_answered(session, args, mention):
    answer = session.call(*args)
    assert answer["success"] is False
    assert mention.lower() in answer["message"].lower(), answer
    assert session.alive(session.node)


def publish_once(session: Session, value: str) -> None:
    """One position command, the value parsed as `rostopic pub` parses it."""
    session.publish(POS_CTRL + "/command", "std_msgs/Float64", value)


def test_07_non_finite_commands_do_not_reach_the_drive(session):
    before = get_value(session, "607A")
    # Each one until the node's warning names it and a cycle ran after it
    # (Session.refuse): a valid marker command after it would overwrite a
    # target it had set, and hide it. YAML spellings: rostopic sends "nan"
    # as a string.
    for bad, shown in ((".nan", "[nan]"), ("-.inf", "[-inf]")):
        session.refuse(shown, "not a finite number", lambda bad=bad: publish_once(session, bad))
        assert get_value(session, "607A") == before, "a non-finite command (%s) reached the drive" % bad
    assert session.alive(session.node)


def test_08_halt_refuses_commands_recover_resumes(session):
    assert session.call("/maxon/driver/halt")["success"]
    assert int(get_value(session, "6040"), 0) & 0x000F == 0x0002  # quick stop, as ros_canopen
    before = get_value(session, "607A")
    # no valid command exists while halted to mark the topic with: the
    # node's refusal warning is the evidence it took the command in
    session.refuse("[5000.0]", "is halted", lambda: publish_once(session, "5000"))
    assert get_value(session, "607A") == before, "a command while halted reached the drive"
    assert session.call("/maxon/driver/recover")["success"]
    # in profile position the halt bit stays until the drive took the held
    # position as its set-point (no target of someone else's survives it)
    session.wait(lambda: not int(get_value(session, "6040"), 0) & 0x0100, "the halt bit released after recover")
    publish_once(session, "2000")
    session.wait(lambda: get_value(session, "607A") == "2000", "commands to work again after recover")


def diagnostics(session: Session) -> List[Dict[str, Any]]:
    msg = session.echo("/diagnostics")
    return [s for s in msg["status"] if s["name"].endswith(JOINT)]


def test_09_diagnostics_one_status_per_node(session):
    status = diagnostics(session)
    assert len(status) == 1, status
    values = {v["key"]: v["value"] for v in status[0]["values"]}
    assert values["state"] == "operation_enabled"
    assert status[0]["level"] == 0, status[0]


def test_09b_emcy_is_decoded_logged_and_on_diagnostics_recover_clears_it(session):
    session.node.stdin.write("1 emcy 0x8611\n")  # the simulated drive raises a following error
    session.node.stdin.flush()

    def in_error() -> bool:
        status = diagnostics(session)
        return bool(status) and status[0]["level"] == 2 and "Following error" in str(status[0]["values"])

    session.wait(in_error, "diagnostics to report the EMCY as an error")
    session.wait(lambda: "EMCY 0x8611 Following error" in session.log("node.log"), "the EMCY in the node's log")
    # refused while in fault: read the drive once the node said so and a cycle ran
    session.refuse("[3000.0]", "is in error", lambda: publish_once(session, "3000"))
    assert get_value(session, "607A") != "3000", "a command while in fault reached the drive"
    assert session.call("/maxon/driver/recover")["success"]
    session.wait(lambda: diagnostics(session)[0]["level"] == 0, "diagnostics back to OK after recover")
    assert int(get_value(session, "6041"), 0) & 0x6F == 0x27


def test_10_python_example_moves_the_joint_through_a_sine_wave(session):
    proc = session.run(sys.executable, str(PKG / "scripts" / "python_example_1dof_ppm.py"), "--no-init",
                       "--cycles", "1", "--steps", "4", "--step-time", "0.5", "--amplitude", "3000",
                       timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    rows = [line.split() for line in proc.stdout.splitlines() if line.strip() and line.split()[0].isdigit()]
    assert [float(r[1]) for r in rows] == [0.0, 3000.0, 0.0, -3000.0, 0.0]
    positions = [float(r[2]) for r in rows if r[2] != "n/a"]
    assert len(set(positions)) > 1, "the joint did not move: %r" % rows
    session.wait(lambda: get_value(session, "607A") == "0", "the example's last target 0")


def test_11_cpp_example_menu(session):
    binary = REPO / ".ws" / "devel" / "lib" / "maxon_epos4_ros_canopen" / "cpp_example_1dof_ppm"
    if not binary.exists():
        pytest.fail("cpp_example_1dof_ppm not built: run tools/setup.sh")
    # as a user types it: set a target, wait, read the position, exit
    proc = subprocess.Popen([str(binary)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, env=session.env, text=True)
    try:
        proc.stdin.write("5\n1500\n")
        proc.stdin.flush()
        session.wait(lambda: get_value(session, "607A") == "1500", "the C++ example's target")
        output, _ = proc.communicate("6\n7\n", timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, output
    assert "Target Position 1500 sent" in output
    assert "Position Actual Value" in output, output


def test_12_shutdown_then_init_again(session):
    assert session.call("/maxon/driver/shutdown")["success"]

    def disabled() -> bool:
        values = {v["key"]: v["value"] for v in diagnostics(session)[0]["values"]}
        return values["state"] != "operation_enabled" and values["nmt_state"] == "STOPPED"

    session.wait(disabled, "diagnostics to show the drive disabled and NMT stopped")
    assert session.call("/maxon/driver/init")["success"]
    assert get_value(session, "6061") == "1"  # the running position controller's mode is restored
    assert session.alive(session.node)
    assert session.spawner.poll() == 0  # `controller_manager spawn` loads, starts and exits, as ROS's does
