"""`controller_manager spawn` started while the master still lists the
controller manager of a driver that was killed (SIGKILL leaves its services
registered): it must keep waiting for the new driver's services, as it does
when none are listed, not exit with "time is not initialized"."""
import os
import signal
import socket
import subprocess
import threading
import time

import pytest
import rosgraph  # noqa: F401 (a master and a killed node's service: ROS 1 needed)

REPO = os.path.join(os.path.dirname(__file__), "..", "..")
CLI = os.path.join(REPO, ".ws", "devel", "lib", "controller_manager", "controller_manager")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


@pytest.fixture
def master():
    port = _free_port()
    uri = "http://localhost:%d/" % port
    proc = subprocess.Popen(["rosmaster", "--core", "-p", str(port)], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    import rosgraph
    m = rosgraph.Master("/test", master_uri=uri)
    deadline = time.monotonic() + 60
    while not m.is_online():
        assert time.monotonic() < deadline and proc.poll() is None, "rosmaster did not start"
        time.sleep(0.1)
    yield uri, m
    os.killpg(proc.pid, signal.SIGINT)
    proc.wait(timeout=30)


def test_spawn_keeps_waiting_while_a_killed_drivers_service_is_still_listed(master):
    uri, m = master
    # what a SIGKILLed driver leaves: its service registered at an address nobody answers on
    m.registerService("/controller_manager/load_controller", "rosrpc://localhost:%d" % _free_port(),
                         "http://localhost:%d/" % _free_port())
    env = dict(os.environ, ROS_MASTER_URI=uri)
    proc = subprocess.Popen([CLI, "spawn", "some_controller"], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)
    output = []
    reader = threading.Thread(target=lambda: output.extend(proc.stdout), daemon=True)
    reader.start()
    try:
        # rospy's wait says so after its first failed contact, then tries again
        deadline = time.monotonic() + 120
        while proc.poll() is None and not any("failed to contact, will keep trying" in line for line in output):
            assert time.monotonic() < deadline, "no answer from the CLI: %r" % output
            time.sleep(0.1)
        assert proc.poll() is None, "spawn exited %s: %s" % (proc.returncode, "".join(output))
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)
        proc.wait(timeout=30)
