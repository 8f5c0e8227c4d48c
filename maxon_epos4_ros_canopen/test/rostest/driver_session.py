"""Helpers for the driver rostests: the user's command lines, an independent
look at the drives over SDO, and a recorder of the frames on the bus.

Imported by the executable test scripts next to it (not a test itself).
"""
from __future__ import annotations

import os
import subprocess
import threading
import time
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import can
import rospy
import yaml
from sensor_msgs.msg import JointState

from maxon_epos4_ros_canopen.bus_watch import FrameRecorder, SdoObserver, poll
from maxon_epos4_ros_canopen.can_device import enlarge_receive_buffer

CLI_TIMEOUT = 120.0  # user-mode Linux runs ROS tools 6-10x slower than native
WAIT = 90.0
DRIVER_NODE = "/maxon/canopen_motor"
# The driver node warns of a refused command at most once a second
# (rospy.logwarn_throttle in nodes/canopen_motor_node, CanopenMotorNode._command).
REFUSAL_WARNING_PERIOD = 1.0
SYNC_COB_ID = 0x080


def run(args: Sequence[str], timeout: float = CLI_TIMEOUT) -> subprocess.CompletedProcess:
    """Run a command line exactly as a user types it (already split by the shell)."""
    return subprocess.run(list(args), capture_output=True, text=True, timeout=timeout)


def rosservice_call(service: str, *args: str, cli: bool = False) -> Dict[str, Any]:
    """`rosservice call SERVICE ARGS...` as a user types it; the YAML answer
    as a dict (fails the test on an error). The arguments are taken as the
    command takes them: each one read as YAML (so "!!str 6081" is a
    string), the request filled from them in order, the answer printed as
    YAML. ``cli``: run the command itself; otherwise the same steps in this
    process, since the command's own start-up costs seconds in user-mode
    Linux and the suite calls services some forty times."""
    if cli:
        proc = run(["rosservice", "call", service] + list(args))
        if proc.returncode != 0:
            raise AssertionError("rosservice call %s %s failed (%d): %s %s"
                                 % (service, " ".join(args), proc.returncode, proc.stdout, proc.stderr))
        text = proc.stdout
    else:
        import genpy
        import rosservice
        try:
            service_class = rosservice.get_service_class_by_name(service)
            request = service_class._request_class()
            fill_from_yaml(request, [a if a != "" else "''" for a in args])
            text = str(rospy.ServiceProxy(service, service_class)(request))
        except (rosservice.ROSServiceException, rospy.ServiceException, genpy.MessageException) as e:
            raise AssertionError("rosservice call %s %s failed: %s" % (service, " ".join(args), e)) from None
    answer = yaml.safe_load(text)
    return answer if isinstance(answer, dict) else {"raw": text}


def fill_from_yaml(msg: Any, args: Sequence[str]) -> None:
    """Fill ``msg`` from command-line arguments as `rosservice call` and
    `rostopic pub` do: each read as YAML, the fields filled in order, with
    their keys "now" and "auto" (raises genpy.MessageException)."""
    import genpy
    import std_msgs.msg
    now = rospy.get_rostime()
    genpy.message.fill_message_args(msg, [yaml.safe_load(a) for a in args],
                                    keys={"now": now, "auto": std_msgs.msg.Header(stamp=now)})


_publishers: Dict[str, Any] = {}


def rostopic_pub_once(topic: str, msg_type: str, *args: str, cli: bool = False) -> None:
    """`rostopic pub -1 TOPIC TYPE ARGS...` as a user types it. The
    arguments are taken as the command takes them: read as YAML after an
    optional ``--``, the message filled from them in order. ``cli``: run
    the command itself; otherwise the same steps in this process, sent once
    the topic's subscribers are connected, since the command's start-up and
    its 3 s latch cost seconds in user-mode Linux. The publisher does not
    latch: a node started later must not get an old command."""
    if cli:
        proc = run(["rostopic", "pub", "-1", topic, msg_type] + list(args))
        if proc.returncode != 0:
            raise AssertionError("rostopic pub -1 %s %s %s failed (%d): %s %s"
                                 % (topic, msg_type, " ".join(args), proc.returncode, proc.stdout, proc.stderr))
        return
    import roslib.message
    msg_class = roslib.message.get_message_class(msg_type)
    if msg_class is None:
        raise AssertionError("rostopic pub: no message type %s" % msg_type)
    msg = msg_class()
    fill_from_yaml(msg, args[1:] if args[:1] == ("--",) else args)
    pub = _publishers.get(topic)
    if pub is None or pub.type != msg_type:
        pub = _publishers[topic] = rospy.Publisher(topic, msg_class, queue_size=10)
    if not poll(lambda: pub.get_num_connections() > 0, WAIT, step=0.05):
        raise AssertionError("rostopic pub -1 %s: no subscriber for %.0f s" % (topic, WAIT))
    pub.publish(msg)


class Background:
    """A long-running command (`rostopic pub ...` latches until Ctrl-C)."""

    def __init__(self, args: Sequence[str]) -> None:
        self.proc = subprocess.Popen(list(args), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


class SdoProbe(SdoObserver):
    """Reads a drive's object dictionary over SDO, independently of the driver,
    so the test sees the drive's own values (the simulator's 0x607A etc.);
    only SDO answers reach its socket (bus_watch.SdoObserver)."""

    def __init__(self, device: str) -> None:
        super().__init__(channel=device)

    def velocity(self, node_id: int) -> int:
        """0x606C velocity actual value."""
        return self.read(node_id, 0x606C, signed=True)

    def position(self, node_id: int, within: float = 0.0) -> int:
        """0x6064 position actual value."""
        return self.read(node_id, 0x6064, signed=True, within=within)


class DiagnosticsWatch:
    """Every /diagnostics status of the joints, with the time it arrived, so a
    test can ask when a condition first showed (detection time)."""

    def __init__(self) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        self._lock = threading.Lock()
        self._history: Dict[str, List[Any]] = {}
        self._sub = rospy.Subscriber("/diagnostics", DiagnosticArray, self._cb, queue_size=50)

    def _cb(self, msg: Any) -> None:
        now = time.monotonic()
        with self._lock:
            for status in msg.status:
                joint = status.name.split(":")[-1].strip()
                entries = self._history.setdefault(joint, [])
                entries.append((now, {v.key: v.value for v in status.values}))
                del entries[:-2000]

    def latest(self, joint: str) -> Dict[str, str]:
        with self._lock:
            entries = self._history.get(joint) or [(0.0, {})]
            return dict(entries[-1][1])

    def errors_since(self, since: float) -> Dict[str, List[Tuple[float, str]]]:
        """Each joint's distinct errors shown after `since` (time.monotonic()),
        with the time each first arrived."""
        found: Dict[str, List[Tuple[float, str]]] = {}
        with self._lock:
            for joint, entries in self._history.items():
                seen: List[Tuple[float, str]] = []
                for stamp, values in entries:
                    error = values.get("error")
                    if stamp >= since and error and all(error != e for _, e in seen):
                        seen.append((stamp, error))
                if seen:
                    found[joint] = seen
        return found

    def first_since(self, joint: str, since: float, condition: Callable[[Dict[str, str]], bool],
                    timeout: float = WAIT) -> Tuple[float, Dict[str, str]]:
        """(arrival time, values) of the first status of `joint` that arrived
        after `since` (time.monotonic()) and meets `condition`."""
        deadline = time.monotonic() + timeout
        while True:
            with self._lock:
                for stamp, values in self._history.get(joint, []):
                    if stamp >= since and condition(values):
                        return stamp, values
            if time.monotonic() > deadline:
                raise AssertionError("diagnostics of %s never met the condition; latest %r"
                                     % (joint, self.latest(joint)))
            time.sleep(0.05)


def wait_for_running_controllers(names: Sequence[str], ns: str = "/maxon", timeout: float = WAIT,
                                 attempts: int = 3) -> None:
    """Wait until the controller manager lists every controller in `names`
    as running. Tests wait for this before their own SDO reads: the spawner's
    mode switch uses the drives' one SDO channel, and a second client's
    answers on it break that switch. When another running controller holds
    their joints (left so by a test before), stop it and start them at once,
    as the spawner would; when the spawner could not start them (a drive in
    error right after init), `driver/recover` and start them so, up to
    `attempts` times. The joint state controller is never stopped."""
    from controller_manager_msgs.srv import ListControllers, SwitchController
    from std_srvs.srv import Trigger
    rospy.wait_for_service(ns + "/controller_manager/list_controllers", timeout=timeout)
    listing = rospy.ServiceProxy(ns + "/controller_manager/list_controllers", ListControllers)
    switch = rospy.ServiceProxy(ns + "/controller_manager/switch_controller", SwitchController)
    recover = rospy.ServiceProxy(ns + "/driver/recover", Trigger)
    wanted = [n.split("/")[-1] for n in names]

    def stopped(controllers: Optional[List[Any]] = None) -> List[str]:
        if controllers is None:
            controllers = listing().controller
        states = {c.name.split("/")[-1]: (c.name, c.state) for c in controllers}
        return [states[n][0] if n in states else n for n in wanted if states.get(n, ("", ""))[1] != "running"]

    def running_others(controllers: List[Any]) -> List[Any]:
        return [c for c in controllers if c.state == "running"
                and c.name.split("/")[-1] not in wanted and not c.name.endswith("joint_state_controller")]

    def running_or_blocked() -> bool:
        """All wanted controllers run, or one is loaded but another running
        one holds its joints: a test before left it so (the launch may have
        served another test: tools/e2e_group.py), and the spawner cannot
        start it. One listing per poll."""
        controllers = listing().controller
        if not stopped(controllers):
            return True
        held = {res for c in running_others(controllers) for r in c.claimed_resources for res in r.resources}
        return any(c.name.split("/")[-1] in wanted and c.state != "running"
                   and held.intersection(res for r in c.claimed_resources for res in r.resources)
                   for c in controllers)

    def take_over() -> None:
        controllers = listing().controller
        switch(start_controllers=stopped(controllers),
               stop_controllers=[c.name for c in running_others(controllers)], strictness=1,
               start_asap=False, timeout=0.0)

    for attempt in range(attempts):
        try:
            wait_until(running_or_blocked, "controllers %s running" % ", ".join(names),
                       timeout=timeout if attempt == 0 else 20.0)
            if not stopped():
                return
            take_over()
            wait_until(lambda: not stopped(), "controllers %s running" % ", ".join(names), timeout=20.0)
            return
        except AssertionError:
            missing = stopped()
            answer = recover()
            print("controllers %s not running (attempt %d); recover: %s %r"
                  % (missing, attempt + 1, answer.success, answer.message), flush=True)
            take_over()
    wait_until(lambda: not stopped(), "controllers %s running" % ", ".join(names), timeout=20.0)


def driver_pid(pattern: str = "canopen_motor_node") -> int:
    """Process id of the driver node (the one process whose command line has `pattern`)."""
    proc = run(["pgrep", "-f", pattern])
    pids = [int(p) for p in proc.stdout.split() if int(p) != os.getpid()]
    if len(pids) != 1:
        raise AssertionError("expected one %s process, found %r" % (pattern, pids))
    return pids[0]


class BusRecorder(FrameRecorder):
    """Keeps every frame seen on the bus between start() and stop() (only
    those `can_filters` pass when given: the kernel filters, so a busy bus
    does not overflow the socket with frames nobody counts)."""

    def __init__(self, device: str, can_filters: Optional[List[Dict[str, Any]]] = None) -> None:
        bus = can.Bus(interface="socketcan", channel=device, can_filters=can_filters)
        # a recording may fall far behind on a loaded host: room for minutes of traffic
        enlarge_receive_buffer(bus.socket, 64 * 1024 * 1024)
        super().__init__(bus, period=0.2)

    def wait_for(self, match: Callable[[can.Message], bool], what: str, count: int = 1,
                 timeout: float = WAIT) -> List[can.Message]:
        """The first `count` frames recorded since start() that `match`,
        once the recorder has them (fails after `timeout`)."""
        found = self.matching(match, count, timeout, step=0.2)
        if found is None:
            raise AssertionError("timed out waiting for " + what)
        return found


def wait_for_syncs(device: str, count: int = 2) -> None:
    """Return once `count` SYNC frames were on the bus after this call.

    With the shipped bus layer (sync/interval_ms == update_ms, no
    kernel_timer) the driver's cycle sends SYNC itself, last, after the
    RxPDOs of the commands it drained from its inbox. The first SYNC seen
    may end a cycle that began before this call; the second ends one that
    began after it. So whatever the driver had queued before this call is
    on the bus by then, and the drives, which handle frames in bus order,
    have it before any SDO request sent afterwards."""
    # A fresh socket: it holds only frames sent after it was opened.
    recorder = BusRecorder(device, can_filters=[{"can_id": SYNC_COB_ID, "can_mask": 0x7FF, "extended": False}])
    try:
        recorder.start()
        recorder.wait_for(lambda f: f.arbitration_id == SYNC_COB_ID, "%d SYNC frames on %s" % (count, device),
                          count=count)
    finally:
        recorder.stop()
        recorder.close()


class NodeLog:
    """The lines one node sends to /rosout, in the order they arrive. Some
    inputs the node answers only in its log (a refused command on a
    <controller>/command topic): the line is the evidence that the node
    handled the input."""

    def __init__(self, node: str = DRIVER_NODE) -> None:
        from rosgraph_msgs.msg import Log
        self.node = node
        self._lock = threading.Lock()
        self._lines: List[Any] = []
        self._sub = rospy.Subscriber("/rosout", Log, self._cb, queue_size=1000)

    def _cb(self, msg: Any) -> None:
        if msg.name == self.node:
            with self._lock:
                self._lines.append(msg)

    def mark(self) -> int:
        """A position in the log: wait_for(..., since=mark()) sees only later lines."""
        with self._lock:
            return len(self._lines)

    def last(self, condition: Callable[[str], bool]) -> Optional[Any]:
        """The latest line (rosgraph_msgs/Log) whose text meets `condition`, or None."""
        with self._lock:
            return next((m for m in reversed(self._lines) if condition(m.msg)), None)

    def wait_for(self, condition: Callable[[str], bool], what: str, since: int = 0,
                 timeout: float = WAIT) -> Any:
        """The first line after position `since` whose text meets `condition`."""
        found: List[Any] = []

        def arrived() -> bool:
            with self._lock:
                found[:] = [m for m in self._lines[since:] if condition(m.msg)]
            return bool(found)

        try:
            wait_until(arrived, what, timeout)
        except AssertionError:
            with self._lock:
                recent = [m.msg for m in self._lines[since:]][-10:]
            raise AssertionError("timed out waiting for %s; the node's lines since: %r" % (what, recent))
        return found[0]


def is_refusal(text: str) -> bool:
    """A line of the driver node's warning of a refused <controller>/command."""
    return "/command [" in text and "] refused: " in text


class CommandRefusals:
    """Commands the driver node must refuse, sent and waited on until the
    node demonstrably handled them.

    A refused command changes nothing, so there is no change to wait for;
    the node's warning "<controller>/command [values] refused: reason" on
    /rosout is what shows it took the command in and refused it. After the
    warning, wait_for_syncs() lets the cycle run: a command the node had
    queued all the same would then be in the drive, and the test's own
    check of the drive (an SDO read) would see it."""

    def __init__(self, device: str, log: Optional[NodeLog] = None) -> None:
        self.device = device
        self.log = log if log is not None else NodeLog()

    def refuse(self, controller: str, values: str, reason: str, send: Callable[[], None]) -> str:
        """send() a command the node must refuse; return the node's warning
        once it named `values` (as the node prints the list, e.g. "[nan]",
        "[7.0]") and `reason`, and the cycle ran after it."""
        # The warning is throttled: one sent within REFUSAL_WARNING_PERIOD
        # of the previous one (by the node's clock, which stamped it) would
        # not be logged, and this would wait in vain.
        previous = self.log.last(is_refusal)
        if previous is not None:
            quiet_from = previous.header.stamp.to_sec() + REFUSAL_WARNING_PERIOD
            wait_until(lambda: time.time() > quiet_from, "the node's refusal warning throttle to let a warning through")
        since = self.log.mark()
        send()
        head = "%s/command %s refused: " % (controller, values)
        line = self.log.wait_for(lambda text: text.startswith(head), "the node's warning '%s...'" % head, since)
        if reason not in line.msg:
            raise AssertionError("refused for another reason than %r: %s" % (reason, line.msg))
        wait_for_syncs(self.device)
        return line.msg


class JointStates:
    """Latest /maxon/joint_states message."""

    def __init__(self, topic: str = "/maxon/joint_states") -> None:
        self.msg: Optional[JointState] = None
        self._sub = rospy.Subscriber(topic, JointState, self._cb, queue_size=1)

    def _cb(self, msg: JointState) -> None:
        self.msg = msg

    def close(self) -> None:
        """Stop listening: a subscriber costs the publishing node time too."""
        self._sub.unregister()

    def value(self, joint: str, field: str = "position") -> Optional[float]:
        msg = self.msg
        if msg is None or joint not in msg.name:
            return None
        values = getattr(msg, field)
        return values[msg.name.index(joint)]

    def wait_for(self, joint: str, predicate: Callable[[float], bool], field: str = "position",
                 timeout: float = WAIT) -> Optional[float]:
        last: List[Optional[float]] = [None]

        def met() -> bool:
            last[0] = self.value(joint, field)
            return last[0] is not None and predicate(last[0])

        if poll(met, timeout, step=0.1, stop=rospy.is_shutdown):
            return last[0]
        raise AssertionError("joint_states %s.%s never met the condition; last value %r" % (joint, field, last[0]))


def wait_until(condition: Callable[[], bool], what: str, timeout: float = WAIT) -> None:
    """bus_watch.poll that fails the test, naming `what`, after `timeout`."""
    if not poll(condition, timeout, step=0.2):
        raise AssertionError("timed out waiting for " + what)


def operation_enabled(statusword: int) -> bool:
    # CiA 402: state bits 0-3, 5, 6 == 0b0100111 in Operation enabled
    return statusword & 0x6F == 0x27


def controllers_by_name(answer: Dict[str, Any]) -> Dict[str, Dict[str, Any]]:
    return {c["name"]: c for c in answer.get("controller") or []}


def diagnostic_values(joint: str) -> Dict[str, str]:
    """Key/values of the joint's status on /diagnostics (empty when absent)."""
    from diagnostic_msgs.msg import DiagnosticArray
    try:
        msg = rospy.wait_for_message("/diagnostics", DiagnosticArray, timeout=10.0)
    except rospy.ROSException:
        return {}
    for status in msg.status:
        if status.name.endswith(joint):
            return {v.key: v.value for v in status.values}
    return {}


def device() -> str:
    return rospy.get_param("~device", os.environ.get("CAN_DEVICE", "vcan0"))
