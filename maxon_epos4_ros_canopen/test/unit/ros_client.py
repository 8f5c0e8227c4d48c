"""One ROS client process for a test's whole session (see node_session.py),
so that a step costs a round trip instead of a Python start of a CLI tool.

    python ros_client.py

It waits for the master of its ROS_MASTER_URI, becomes a node and answers
JSON requests, one a line on stdin, with one JSON line on stdout:
``{"id": ID, "ok": true, "result": ...}`` or ``{"id": ID, "ok": false,
"error": "..."}``, ID being the request's ``id``.
Each request does what the user's tool of the same name does, through the
same library calls:

- ``call``: ``rosservice call SERVICE ARGS...`` (each arg a YAML string);
  the result is the YAML text the tool prints.
- ``pub``: ``rostopic pub -1 TOPIC TYPE -- VALUE``, once a subscriber is
  connected. Not latched: the tool's latch ends when it exits after 3 s,
  and a latched value here would reach a controller that subscribes later.
- ``echo``: ``rostopic echo -n 1 TOPIC``: the next message's YAML text.
- ``services``, ``topic_type``, ``wait_service``, ``set_param``.
- ``cli``: ``controller_manager ARGV...`` (compat/controller_manager's
  ``controller_manager_main``) with its exit status and output.
"""
from __future__ import annotations

import contextlib
import io
import json
import os
import sys
import time
import traceback
from typing import Any, Dict

import genpy
import rosgraph
import rospy
import rosservice
import rostopic
import yaml

from controller_manager.cli import controller_manager_main

MASTER_WAIT = 60.0

_publishers: Dict[str, rospy.Publisher] = {}


def _call(req: Dict[str, Any]) -> str:
    name = rosgraph.names.script_resolve_name("rosservice", req["service"])
    _, response = rosservice.call_service(name, [yaml.safe_load(a) for a in req["args"]])
    return str(response)


def _pub(req: Dict[str, Any]) -> None:
    topic = req["topic"]
    pub = _publishers.get(topic)
    if pub is None:
        cls = genpy.message.get_message_class(req["type"])
        pub = _publishers[topic] = rospy.Publisher(topic, cls, queue_size=10)
    msg = pub.data_class()
    genpy.message.fill_message_args(msg, [yaml.safe_load(req["value"])])
    deadline = time.monotonic() + req.get("timeout", 30.0)
    while pub.get_num_connections() == 0:
        if time.monotonic() > deadline:
            raise RuntimeError("no subscriber of %s" % topic)
        time.sleep(0.01)
    pub.publish(msg)


def _echo(req: Dict[str, Any]) -> str:
    cls, _, _ = rostopic.get_topic_class(req["topic"], blocking=True)
    return str(rospy.wait_for_message(req["topic"], cls, timeout=req.get("timeout", 30.0)))


def _cli(req: Dict[str, Any]) -> Dict[str, Any]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = controller_manager_main(["controller_manager"] + req["argv"])
    return {"returncode": rc, "stdout": out.getvalue(), "stderr": err.getvalue()}


def handle(req: Dict[str, Any]) -> Any:
    op = req["op"]
    if op == "call":
        return _call(req)
    if op == "pub":
        return _pub(req)
    if op == "echo":
        return _echo(req)
    if op == "services":
        return sorted(rosservice.get_service_list())
    if op == "topic_type":
        return rostopic.get_topic_type(req["topic"])[0]
    if op == "wait_service":
        rospy.wait_for_service(req["service"], timeout=req.get("timeout", 60.0))
        return None
    if op == "set_param":
        rospy.set_param(req["name"], req["value"])
        return None
    if op == "cli":
        return _cli(req)
    raise ValueError("unknown op %r" % op)


def main() -> int:
    answers = os.fdopen(os.dup(sys.stdout.fileno()), "w")
    sys.stdout = sys.stderr  # the answers' channel carries answers only
    master = rosgraph.Master("/ros_client")
    deadline = time.monotonic() + MASTER_WAIT
    while not master.is_online():
        if time.monotonic() > deadline:
            print("no master at %s" % rosgraph.get_master_uri(), file=sys.stderr)
            return 1
        time.sleep(0.05)
    # the name rosservice.call_service gives its node: it calls init_node again
    rospy.init_node("rosservice", anonymous=True)
    answers.write(json.dumps({"id": "ready", "ok": True, "result": "ready"}) + "\n")
    answers.flush()
    for line in sys.stdin:
        if not line.strip():
            continue
        req = json.loads(line)
        try:
            answer = {"id": req.get("id"), "ok": True, "result": handle(req)}
        except Exception as exc:  # every request is answered: the test shows why it failed
            answer = {"id": req.get("id"), "ok": False,
                      "error": "%s: %s\n%s" % (type(exc).__name__, exc, traceback.format_exc())}
        answers.write(json.dumps(answer) + "\n")
        answers.flush()
    rospy.signal_shutdown("stdin closed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
