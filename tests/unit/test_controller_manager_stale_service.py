"""`controller_manager spawn` started while the master still lists the
controller manager of a driver that was killed (SIGKILL leaves its services
registered): it must keep waiting for the new driver's services, as it does
when none are listed, not exit with "time is not initialized"."""
import os
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest
import rosgraph  # noqa: F401 (a master and a killed node's service: ROS 1 needed)

REPO = os.path.join(os.path.dirname(__file__), "..", "..")
CLI = os.path.join(REPO, ".ws", "devel", "lib", "controller_manager", "controller_manager")


PRIVATE_MASTER = os.path.join(REPO, "maxon_epos4_ros_canopen", "test", "unit", "private_master.py")


def _unused_port() -> int:
    """A port nobody listens on (bound, not listening, then released)."""
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


@pytest.fixture
def master():
    # a master on a port it binds itself (see private_master.py for why)
    proc = subprocess.Popen([sys.executable, PRIVATE_MASTER], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True, start_new_session=True)
    uri = proc.stdout.readline().strip()
    assert uri.startswith("http://"), "the private master did not start"
    import rosgraph
    yield uri, rosgraph.Master("/test", master_uri=uri)
    os.killpg(proc.pid, signal.SIGINT)
    proc.wait(timeout=30)


def test_spawn_keeps_waiting_while_a_killed_drivers_service_is_still_listed(master):
    uri, m = master
    # what a SIGKILLed driver leaves: its service registered at an address nobody answers on
    m.registerService("/controller_manager/load_controller", "rosrpc://localhost:%d" % _unused_port(),
                      "http://localhost:%d/" % _unused_port())
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
