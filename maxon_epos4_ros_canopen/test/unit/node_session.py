"""A ROS session for the node's tests (test_canopen_motor_node.py,
test_compat_cli.py): a private master (private_master.py), canopen_motor_node with a virtual
EPOS4 in one process (node_with_sim.py), and one ROS client process
(ros_client.py) that makes the test's service calls, publications and
controller_manager commands. The user's command-line tools themselves run
as subprocesses only where a test proves they work (``run``)."""
from __future__ import annotations

import json
import os
import re
import selectors
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence

import rosgraph  # noqa: F401 (a session runs ROS 1 processes: the tests that use one need ROS)
import yaml

from driver_support import GENEROUS_MASTER_CONSUMER

PKG = Path(__file__).resolve().parents[2]
REPO = PKG.parent
HERE = Path(__file__).resolve().parent
CM_PKG = REPO / "compat" / "controller_manager"
JOINT = "base_link1_joint"
WAIT = 60.0  # generous: the node and a loaded host
CLI_TIMEOUT = 60.0
# The node warns of a refused command at most once a second
# (rospy.logwarn_throttle in nodes/canopen_motor_node, CanopenMotorNode._command).
REFUSAL_WARNING_PERIOD = 1.0
# rospy's console format (its default, set so the node's log lines carry
# their time whatever the caller's environment says)
LOG_FORMAT = "[${severity}] [${time}]: ${message}"
REFUSAL_LINE = re.compile(r"^\[WARN\] \[([0-9.]+)\]: (\S+/command \[.*\] refused: .*)$", re.M)


class ClientError(AssertionError):
    """A request the ROS client could not carry out."""


class Session:
    def __init__(self, tmp: Path, namespace: Optional[str] = None) -> None:
        self.env = dict(os.environ)
        self.env.pop("ROS_MASTER_URI", None)  # start_master sets it: the session's own master
        self.env["ROS_LOG_DIR"] = str(tmp / "log")
        self.env["ROS_HOSTNAME"] = "localhost"
        self.env["ROSCONSOLE_FORMAT"] = LOG_FORMAT
        self.env["PYTHONUNBUFFERED"] = "1"  # the tools' log lines reach their files as they are written
        self.env["PYTHONPATH"] = os.pathsep.join([str(PKG / "src"), str(CM_PKG / "src"),
                                                  self.env.get("PYTHONPATH", "")])
        if namespace:
            self.env["ROS_NAMESPACE"] = namespace  # as a launch file's <group ns=...> sets it
        self.tmp = tmp
        self.procs: List[subprocess.Popen] = []
        self.client: Optional[subprocess.Popen] = None
        self.node: Optional[subprocess.Popen] = None
        self._requests = 0

    # --- processes --------------------------------------------------------

    def spawn(self, args: List[str], log: str) -> subprocess.Popen:
        out = open(self.tmp / log, "w")
        proc = subprocess.Popen(args, env=self.env, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.PIPE,
                                text=True)
        self.procs.append(proc)
        return proc

    def run(self, *args: str, timeout: float = CLI_TIMEOUT) -> subprocess.CompletedProcess:
        """A command-line tool as the user runs it, in its own process."""
        return subprocess.run(list(args), env=self.env, capture_output=True, text=True, timeout=timeout)

    def start_master(self) -> None:
        """The session's private master (private_master.py, on a port it
        binds itself); every process started after it uses it."""
        log = self.tmp / "master.log"
        master = subprocess.Popen([sys.executable, str(HERE / "private_master.py")], env=self.env,
                                  stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=open(log, "w"), text=True)
        self.procs.insert(0, master)  # close() stops it last
        sel = selectors.DefaultSelector()
        sel.register(master.stdout, selectors.EVENT_READ)
        try:
            uri = master.stdout.readline().strip() if sel.select(WAIT) else ""
        finally:
            sel.close()
        if not uri.startswith("http://"):
            raise ClientError("the private master gave no URI in %.0f s; its log:\n%s" % (WAIT, self.log("master.log")))
        self.env["ROS_MASTER_URI"] = uri

    def start_client(self) -> None:
        """The ROS client process, on the session's master. ``ready`` waits
        for it."""
        self.client = subprocess.Popen([sys.executable, str(HERE / "ros_client.py")], env=self.env,
                                       stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                       stderr=open(self.tmp / "client.log", "w"), text=True)
        self.procs.append(self.client)

    def _answer(self, request_id: Any, timeout: float) -> Any:
        """The answer to request ``request_id``; answers to earlier requests
        that timed out here are passed over."""
        deadline = time.monotonic() + timeout
        sel = selectors.DefaultSelector()
        sel.register(self.client.stdout, selectors.EVENT_READ)
        try:
            while True:
                if not sel.select(max(0.0, deadline - time.monotonic())):
                    raise ClientError("the ROS client gave no answer in %.0f s; its log:\n%s"
                                      % (timeout, self.log("client.log")))
                line = self.client.stdout.readline()
                if not line:
                    raise ClientError("the ROS client exited; its log:\n%s" % self.log("client.log"))
                answer = json.loads(line)
                if answer["id"] == request_id:
                    break
        finally:
            sel.close()
        if not answer["ok"]:
            raise ClientError(answer["error"])
        return answer["result"]

    def request(self, op: str, answer_within: float = CLI_TIMEOUT, **fields: Any) -> Any:
        self._requests += 1
        fields["op"], fields["id"] = op, self._requests
        self.client.stdin.write(json.dumps(fields) + "\n")
        self.client.stdin.flush()
        return self._answer(self._requests, answer_within)

    # --- what the user's tools do, through the client ---------------------

    def call(self, service: str, *args: str) -> Dict[str, Any]:
        """``rosservice call SERVICE ARGS...``: the answer as the tool prints it, parsed."""
        return yaml.safe_load(self.request("call", service=service, args=list(args)))

    def publish(self, topic: str, msg_type: str, value: str) -> None:
        """``rostopic pub -1 TOPIC TYPE -- VALUE``"""
        self.request("pub", topic=topic, type=msg_type, value=value)

    def echo(self, topic: str) -> Dict[str, Any]:
        """``rostopic echo -n 1 TOPIC``: the next message, parsed."""
        return yaml.safe_load(self.request("echo", topic=topic, timeout=WAIT, answer_within=WAIT + 10))

    def services(self) -> List[str]:
        return self.request("services")

    def topic_type(self, topic: str) -> Optional[str]:
        return self.request("topic_type", topic=topic)

    def set_param(self, name: str, value: Any) -> None:
        self.request("set_param", name=name, value=value)

    def controller_states(self) -> Dict[str, str]:
        """The controllers /maxon/controller_manager lists: name -> state."""
        answer = self.call("/maxon/controller_manager/list_controllers")
        return {c["name"]: c["state"] for c in answer.get("controller") or []}

    def controller_manager(self, *argv: str) -> subprocess.CompletedProcess:
        """``controller_manager ARGV...`` (compat/controller_manager's main,
        in the client process): its exit status and output."""
        r = self.request("cli", argv=list(argv), answer_within=120.0)
        return subprocess.CompletedProcess(["controller_manager"] + list(argv), r["returncode"], r["stdout"],
                                           r["stderr"])

    # --- waits and logs ---------------------------------------------------

    def wait(self, condition: Callable[[], bool], what: str, timeout: float = WAIT) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if condition():
                return
            time.sleep(0.05)
        raise AssertionError("timed out waiting for %s; node log:\n%s" % (what, self.log("node.log")))

    def log(self, name: str) -> str:
        return self.text(name)[-4000:]

    def text(self, name: str) -> str:
        path = self.tmp / name
        return path.read_text() if path.exists() else ""

    def refusals(self) -> List[Any]:
        """The node's refused-command warnings so far (re matches: stamp, text)."""
        return list(REFUSAL_LINE.finditer(self.text("node.log")))

    def refuse(self, values: str, reason: str, send: Callable[[], None]) -> str:
        """send() a command the node must refuse; return the node's warning
        "<controller>/command VALUES refused: ..." once it is in the node's
        log and names `reason`, and the driver's cycle ran after it.

        A refused command changes nothing, so there is nothing to wait for
        but the warning: it shows the node took the command in and refused
        it. After it, the simulator's `sync` answer (node_with_sim.py) says
        a whole cycle ran: a command the node had queued all the same would
        then be in the drive, where the caller's SDO read sees it."""
        previous = self.refusals()
        if previous:
            # throttled: a warning within REFUSAL_WARNING_PERIOD of the
            # previous one (by the node's clock, which stamped it) would not
            # be logged, and this would wait in vain
            quiet_from = float(previous[-1].group(1)) + REFUSAL_WARNING_PERIOD
            self.wait(lambda: time.time() > quiet_from, "the node's refusal warning throttle to let a warning through")
        count = len(previous)
        send()
        found: List[str] = []

        def warned() -> bool:
            found[:] = [m.group(2) for m in self.refusals()[count:] if "/command %s refused: " % values in m.group(2)]
            return bool(found)

        self.wait(warned, "the node's warning that it refused %s" % values)
        assert reason in found[0], "refused for another reason than %r: %s" % (reason, found[0])
        token = uuid.uuid4().hex[:8]
        self.node.stdin.write("sync %s\n" % token)
        self.node.stdin.flush()
        self.wait(lambda: "synced %s" % token in self.text("node.log"), "two SYNCs after the refusal")
        return found[0]

    def alive(self, proc: subprocess.Popen) -> bool:
        return proc.poll() is None

    def close(self) -> None:
        """Every process but the master at once, then the master (the others
        unregister from it on their way out)."""
        if self.client is not None and self.client.poll() is None:
            self.client.stdin.close()
        master, others = self.procs[:1], self.procs[1:]
        for group in (others, master):
            for proc in group:
                if proc.poll() is None and proc is not self.client:
                    proc.send_signal(signal.SIGINT)
            for proc in group:
                try:
                    proc.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()


def load_layers(layers: Sequence[str]) -> Dict[str, Any]:
    """The example's layers (config/), merged as roslaunch's rosparam loads do."""
    params: Dict[str, Any] = {}
    for name in layers:
        with open(PKG / "config" / name) as stream:
            for key, value in yaml.safe_load(stream).items():
                if isinstance(value, dict) and isinstance(params.get(key), dict):
                    params[key].update(value)
                else:
                    params[key] = value
    return params


def start_node(s: Session, layers: Sequence[str]) -> None:
    """A private master, the example's layers (config/) on the parameter server, and the
    node with a virtual EPOS4 (node-ID 1) on a private virtual channel; returns
    once the driver's services are offered. The node is ``s.node``."""
    s.start_master()
    s.start_client()
    s._answer("ready", WAIT)
    params = load_layers(layers)
    channel = "node_test_" + uuid.uuid4().hex[:8]
    params["bus"]["device"] = "virtual:" + channel
    dcf = str(PKG / "config" / "epos4_node1.dcf")
    params["nodes"]["node1"]["eds_file"] = dcf
    del params["nodes"]["node1"]["eds_pkg"]
    # the drive watches the master's heartbeat with a timeout no GIL stall
    # of a loaded host reaches (driver_support.GENEROUS_MASTER_CONSUMER):
    # these tests are about the ROS interface, master loss has its own
    params["nodes"]["node1"].setdefault("dcf_overlay", {}).update(GENEROUS_MASTER_CONSUMER)
    # the virtual EPOS4 runs in the node's process: a SCHED_FIFO cycle thread
    # would take the CPU from it (the launch files say the same with sim:=true)
    params["realtime"] = {"enabled": False}
    s.set_param("/maxon/canopen_motor", params)
    s.node = s.spawn([sys.executable, str(HERE / "node_with_sim.py"), channel, "1:" + dcf, "--",
                      "__ns:=/maxon", "__name:=canopen_motor"], "node.log")
    s.request("wait_service", service="/maxon/driver/init", timeout=WAIT, answer_within=WAIT + 10)
