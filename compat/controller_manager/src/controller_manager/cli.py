"""The three command-line tools of ros_control's controller_manager package,
talking to the controller_manager_msgs services of a controller manager.

Service names are relative (``controller_manager/load_controller``): they
resolve in the tool's namespace (``__ns:=/maxon``, ``ROS_NAMESPACE`` or the
launch file's group), as ROS's tools do. Output lines are ROS Noetic's.
"""
from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
from typing import Callable, List, Optional, Sequence

import rospy
import yaml
from controller_manager_msgs.srv import (ListControllers, ListControllerTypes, LoadController,
                                         ReloadControllerLibraries, SwitchController, SwitchControllerRequest,
                                         UnloadController)
from std_msgs.msg import Bool

USAGE = """Commands:
    load <name>          - Load the controller named <name>
    unload <name>        - Unload the controller named <name>
    start <name>         - Start the controller named <name>
    stop <name>          - Stop the controller named <name>
    spawn <name>         - Load and start the controller named <name>
    kill <name>          - Stop and unload the controller named <name>
    list                 - List active controllers
    list-types           - List controller Types
    reload-libraries     - Reloads all plugin controller libraries"""

_WAIT_NOTICE_S = 5.0


def _service(name: str, srv_type: type, namespace: str = "", timeout: Optional[float] = None) -> rospy.ServiceProxy:
    """A proxy once the service exists; waits forever when timeout is None
    (a driver offers its controller manager only after driver/init), saying
    once what it waits for."""
    full = namespace + "controller_manager/" + name
    if timeout is None:
        try:
            rospy.wait_for_service(full, timeout=_WAIT_NOTICE_S)
        except rospy.ROSException:
            print("waiting for %s (a ros_canopen driver offers it after driver/init)" % rospy.resolve_name(full),
                  flush=True)
            rospy.wait_for_service(full)
    else:
        rospy.wait_for_service(full, timeout=timeout)
    return rospy.ServiceProxy(full, srv_type)


# --- controller_manager -------------------------------------------------------

def load_controller(name: str) -> bool:
    if _service("load_controller", LoadController)(name).ok:
        print("Loaded", name)
        return True
    print("Error when loading", name)
    return False


def unload_controller(name: str) -> bool:
    if _service("unload_controller", UnloadController)(name).ok:
        print("Unloaded %s successfully" % name)
        return True
    print("Error when unloading", name)
    return False


def _switch(names: List[str], start: bool) -> bool:
    switch = _service("switch_controller", SwitchController)
    ok = switch(start_controllers=names if start else [], stop_controllers=[] if start else names,
                strictness=SwitchControllerRequest.STRICT, start_asap=False, timeout=0.0).ok
    verb = "Started" if start else "Stopped"
    if ok:
        print("%s %s successfully" % (verb, names))
    else:
        print("Error when %s " % ("starting" if start else "stopping"), names)
    return ok


def start_controller(name: str) -> bool:
    return _switch([name], True)


def stop_controller(name: str) -> bool:
    return _switch([name], False)


def list_controllers() -> bool:
    answer = _service("list_controllers", ListControllers)()
    if not answer.controller:
        print("No controllers are loaded in mechanism control")
    for c in answer.controller:
        interfaces = sorted(set(r.hardware_interface for r in c.claimed_resources))
        print("%s - %s ( %s )" % (c.name, "+".join(interfaces), c.state))
    return True


def list_controller_types() -> bool:
    for t in _service("list_controller_types", ListControllerTypes)().types:
        print(t)
    return True


def reload_libraries(restore: bool) -> bool:
    reload = _service("reload_controller_libraries", ReloadControllerLibraries)
    print("Restore:", restore)
    before = _service("list_controllers", ListControllers)().controller if restore else []
    ok = reload(force_kill=True).ok
    print("Successfully reloaded libraries" if ok else
          "Failed to reload libraries. Do you still have controllers loaded?")
    if restore:
        load = _service("load_controller", LoadController)
        for c in before:
            load(c.name)
        _service("switch_controller", SwitchController)(
            start_controllers=[c.name for c in before if c.state == "running"], stop_controllers=[],
            strictness=SwitchControllerRequest.BEST_EFFORT, start_asap=False, timeout=0.0)
        print("Controllers restored to original state")
    return ok


def _each(action: Callable[[str], bool], names: Sequence[str]) -> bool:
    results = [action(n) for n in names]  # every name is tried, as ROS's tool does
    return all(results)


def controller_manager_main(argv: Optional[List[str]] = None) -> int:
    """``controller_manager COMMAND [NAME...]``. Unlike ROS's tool the exit
    status tells whether every step succeeded (0) or not (1)."""
    args = rospy.myargv(sys.argv if argv is None else argv)
    if len(args) < 2:
        print(USAGE)
        return 0
    command, names = args[1], args[2:]
    # This client is no node, but rospy's wait_for_service logs a failed
    # contact (a killed driver's service still listed) with a throttle that
    # reads ROS time: wall time for a process without a node.
    rospy.rostime.set_rostime_initialized(True)
    try:
        if command in ("lt", "list-types"):
            ok = list_controller_types()
        elif command in ("lc", "list"):
            ok = list_controllers()
        elif command == "reload-libraries":
            ok = reload_libraries("--restore" in names)
        elif command == "load":
            ok = _each(load_controller, names)
        elif command == "unload":
            ok = _each(unload_controller, names)
        elif command == "start":
            ok = _each(start_controller, names)
        elif command == "stop":
            ok = _each(stop_controller, names)
        elif command in ("sp", "spawn"):
            ok = _each(load_controller, names) & _each(start_controller, names)
        elif command in ("kl", "kill"):
            ok = _each(stop_controller, names) & _each(unload_controller, names)
        else:
            print(USAGE)
            return 1
    except KeyboardInterrupt:
        return 130
    except (rospy.ROSException, rospy.ServiceException) as exc:
        print("controller_manager %s: %s" % (command, exc), file=sys.stderr)
        return 1
    return 0 if ok else 1


# --- spawner ------------------------------------------------------------------

def _spawner_arguments(argv: List[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="spawner", description="Controller spawner")
    parser.add_argument("--stopped", action="store_true", help="loads controllers, but does not start them")
    parser.add_argument("--wait-for", metavar="topic",
                        help='does not load or start controllers until it hears "True" on a topic (Bool)')
    parser.add_argument("--namespace", metavar="ns", help="namespace of the controller_manager services")
    parser.add_argument("--timeout", metavar="T", type=float, default=30,
                        help="how long to wait for controller_manager services when starting up [s] (default: 30)")
    parser.add_argument("--shutdown-timeout", metavar="T", type=float, default=30,
                        help="how long to wait for controller_manager services when shutting down [s] (default: 30)")
    parser.add_argument("controllers", metavar="controller", nargs="+",
                        help="controllers to load (names, or YAML files of controller parameters)")
    return parser.parse_args(argv)


def _controller_names(items: Sequence[str]) -> List[str]:
    """Names as given; a YAML file is loaded onto the parameter server (in
    the spawner's namespace) and stands for its top-level keys."""
    names: List[str] = []
    for item in items:
        if os.path.isfile(item):
            with open(item) as stream:
                content = yaml.safe_load(stream) or {}
            if not isinstance(content, dict):
                raise ValueError("%s: expected a mapping of controller names to parameters" % item)
            for key, value in content.items():
                rospy.set_param(str(key), value)
                names.append(str(key))
        else:
            names.append(item)
    return names


def _interrupted(_signum: int, _frame: object) -> None:
    raise KeyboardInterrupt


def spawner_main(argv: Optional[List[str]] = None) -> int:
    """Loads (and starts) controllers; stops and unloads them when it is
    stopped itself, as ROS Noetic's spawner does."""
    args = _spawner_arguments(rospy.myargv(sys.argv if argv is None else argv)[1:])
    namespace = args.namespace or ""
    if namespace and not namespace.endswith("/"):
        namespace += "/"
    # Ctrl-C and SIGTERM end the spawner through an exception in its main
    # thread, and it takes its controllers down afterwards, outside the
    # signal handler. rospy's own handler runs the shutdown hooks inside the
    # handler: when the signal came while the main thread held a lock of
    # rospy's (publishing a log line to /rosout), the hook's first log line
    # waited for that lock forever and the spawner never ended.
    rospy.init_node("spawner", anonymous=True, disable_signals=True)
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, _interrupted)
    loaded: List[str] = []
    taken_down = threading.Event()

    def take_down() -> None:
        """Once, after Ctrl-C or SIGTERM, or from rospy's shutdown hooks
        when the node is shut down from outside (rosnode kill)."""
        if taken_down.is_set() or not loaded:
            return
        taken_down.set()
        rospy.loginfo("Shutting down spawner. Stopping and unloading controllers...")
        try:
            unload = _service("unload_controller", UnloadController, namespace, args.shutdown_timeout)
            down = _service("switch_controller", SwitchController, namespace, args.shutdown_timeout)
            down(start_controllers=[], stop_controllers=loaded, strictness=SwitchControllerRequest.STRICT,
                 start_asap=False, timeout=0.0)
            for name in reversed(loaded):
                unload(name)
        except (rospy.ServiceException, rospy.ROSException):
            rospy.logwarn("Controller Spawner couldn't reach controller_manager to take down controllers. "
                          "Waited for %g second(s).", args.shutdown_timeout)

    try:
        try:
            rospy.loginfo("Controller Spawner: Waiting for service %scontroller_manager/load_controller", namespace)
            load = _service("load_controller", LoadController, namespace, args.timeout)
            switch = _service("switch_controller", SwitchController, namespace, args.timeout)
            _service("unload_controller", UnloadController, namespace, args.timeout)
        except rospy.ROSException:
            rospy.logwarn("Controller Spawner couldn't find the expected controller_manager ROS interface.")
            return 0
        if args.wait_for:
            heard = threading.Event()
            rospy.Subscriber(args.wait_for, Bool, lambda msg: heard.set() if msg.data else None)
            while not heard.wait(0.1):
                if rospy.is_shutdown():
                    return 0
        rospy.on_shutdown(take_down)
        try:
            names = _controller_names(args.controllers)
        except (OSError, ValueError, yaml.YAMLError) as exc:
            rospy.logerr("Controller Spawner: %s", exc)
            return 1
        for name in names:
            rospy.loginfo("Loading controller: %s", name)
            if load(name).ok:
                loaded.append(name)
            else:
                rospy.logerr("Failed to load %s", name)
        rospy.loginfo("Controller Spawner: Loaded controllers: %s", ", ".join(loaded))
        if not args.stopped and not rospy.is_shutdown():
            if switch(start_controllers=loaded, stop_controllers=[], strictness=SwitchControllerRequest.STRICT,
                      start_asap=False, timeout=0.0).ok:
                rospy.loginfo("Started controllers: %s", ", ".join(loaded))
            else:
                rospy.logerr("Failed to start controllers: %s", ", ".join(loaded))
        while not rospy.is_shutdown():
            rospy.rostime.wallsleep(0.5)
    except KeyboardInterrupt:
        take_down()
        rospy.signal_shutdown("spawner stopped")
    return 0


# --- unspawner ----------------------------------------------------------------

UNSPAWNER_HELP = """unspawner name1 name2 name3

\tStops a set of controllers until killed.
\tUseful in roslaunch files to temporarily stop controllers"""

UNSPAWNER_PERIOD_S = 3.0


def unspawner_main(argv: Optional[List[str]] = None) -> int:
    """Keeps the named controllers stopped while it runs (checking every 3 s)
    and starts those it stopped again when it exits."""
    names = rospy.myargv(sys.argv if argv is None else argv)[1:]
    if not names or names[0] in ("-h", "--help"):
        print(UNSPAWNER_HELP)
        return 1
    rospy.init_node("inhibit", anonymous=True)
    try:
        listing = _service("list_controllers", ListControllers)
        switch = _service("switch_controller", SwitchController)
    except rospy.ROSException:
        return 0
    inhibited: List[str] = []

    def restart() -> None:
        if inhibited:
            try:
                switch(start_controllers=inhibited, stop_controllers=[],
                       strictness=SwitchControllerRequest.BEST_EFFORT, start_asap=False, timeout=0.0)
            except (rospy.ServiceException, rospy.ROSException) as exc:
                rospy.logwarn("unspawner: could not start %s again: %s", ", ".join(inhibited), exc)

    stop = threading.Event()
    rospy.on_shutdown(stop.set)
    rospy.on_shutdown(restart)
    while not rospy.is_shutdown():
        try:
            to_stop = [c.name for c in listing().controller if c.name in names and c.state == "running"]
            if to_stop:
                rospy.loginfo("Inhibiting controllers: %s", ", ".join(to_stop))
                # recorded first: stopped while the switch is under way, the
                # unspawner still starts them again (starting a running one
                # is no change)
                inhibited.extend(n for n in to_stop if n not in inhibited)
                switch(start_controllers=[], stop_controllers=to_stop,
                       strictness=SwitchControllerRequest.BEST_EFFORT, start_asap=False, timeout=0.0)
        except (rospy.ServiceException, rospy.ROSException) as exc:
            if rospy.is_shutdown():
                break
            rospy.logwarn("unspawner: %s", exc)
        stop.wait(UNSPAWNER_PERIOD_S)
    return 0
