"""ros_canopen's YAML layers, read into frozen dataclasses.

The node hands over its private parameter tree (what ``rospy.get_param('~')``
returns after the launch file's ``<rosparam command="load">`` lines); the
layers are the ones canopen_chain_node and canopen_motor_node read:

* bus layer: ``bus``, ``sync``, ``heartbeat``
* node layer: ``nodes`` (dict or list) and ``defaults`` merged under every node
* ROS layer: ``publish`` per node or in ``defaults``
* controller layer: ``joint_names`` and every top-level dict with a ``type``

Unknown options are accepted and listed in ``DriverConfig.warnings`` (as
ros_canopen ignores them); a wrong type or a missing required key raises
ConfigError naming the key and the source. Unit expressions are compiled
here so an invalid or hostile one stops the node at start.

The dataclasses and ConfigError are in config_schema.py, the typed reading
of a mapping and the merging of YAML files in config_reader.py.
"""
from __future__ import annotations

import os
import re
from dataclasses import replace
from types import MappingProxyType
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence, Tuple

from .can_device import SOCKETCAN, CanDeviceError, parse_device
from .config_reader import ParamReader, merge_params
from .config_schema import (DEFAULT_SHUTDOWN_TIMEOUT, DEFAULT_UNITS, HALT_MODES, PDO_LAYOUTS, SOCKETCAN_PLUGIN,
                            SUPPORTED_DRIVE_MODES, SWITCHING_STATES, BusConfig, ConfigError, ControllerConfig,
                            DriverConfig, HeartbeatConfig, NodeConfig, PublishConfig, RealtimeConfig, SyncConfig)
from .objects import ObjectKey, ObjectStringError, parse_object_key, parse_publish_spec
from .units import Expression, UnitExpressionError, compile_expression

__all__ = ["ConfigError", "load_config", "parse_cansend"]

Resolver = Callable[[str], str]

_UNIT_KEYS = tuple(DEFAULT_UNITS)

_BUS_KEYS = {"device", "loopback", "driver_plugin", "master_allocator", "bitrate"}
# CiA 301 bit rates, bit/s
_BITRATES = (10000, 20000, 50000, 125000, 250000, 500000, 800000, 1000000)
MAX_PERIOD_MS = 65535.0
_SYNC_KEYS = {"interval_ms", "update_ms", "overflow", "kernel_timer"}
_HEARTBEAT_KEYS = {"rate", "msg"}
_NODE_KEYS = {"id", "name", "eds_pkg", "eds_file", "dcf_overlay", "motor_allocator",
              "motor_layer", "switching_state", "publish"} | set(_UNIT_KEYS) | {"pdo_layout", "modes", "halt_mode",
                                                                                 "readings_every"}
_TOP_KEYS = {"bus", "sync", "heartbeat", "nodes", "defaults", "joint_names", "realtime", "timeouts"}
_REALTIME_KEYS = {"enabled", "priority", "lock_memory"}
_TIMEOUT_KEYS = {"shutdown"}
MAX_SHUTDOWN_TIMEOUT = 3600.0  # s
_CONTROLLER_KEYS = {"type", "joint", "joints", "publish_rate", "required_drive_mode", "constraints"}

_CANSEND_RE = re.compile(r"^([0-9a-fA-F]{3}|[0-9a-fA-F]{8})#((?:[0-9a-fA-F]{2}\.?){0,8}|R)$")


def parse_cansend(text: str) -> Tuple[int, bytes, bool]:
    """cansend's ``<can_id>#<data>`` (``77f#05``) -> (id, data, extended)."""
    m = _CANSEND_RE.match(text.strip())
    if not m:
        raise ValueError("%r is not in cansend format, e.g. '77f#05'" % text)
    can_id = int(m.group(1), 16)
    extended = len(m.group(1)) == 8
    if not extended and can_id > 0x7FF:
        raise ValueError("%r: standard CAN id 0x%X is above 0x7FF" % (text, can_id))
    if extended and can_id > 0x1FFFFFFF:
        raise ValueError("%r: extended CAN id 0x%X is above 0x1FFFFFFF" % (text, can_id))
    payload = m.group(2)
    if payload == "R":
        raise ValueError("%r: remote frames are not a heartbeat" % text)
    data = bytes.fromhex(payload.replace(".", ""))
    return can_id, data, extended


# --------------------------------------------------------------------------
# layers


def _load_bus(r: ParamReader, params: Mapping[str, Any]) -> BusConfig:
    bus = r.mapping(params.get("bus"), "bus")
    r.unknown(bus, _BUS_KEYS, "bus/")
    device = r.string(bus.get("device", "can0"), "bus/device")
    try:
        interface, _ = parse_device(device)
    except CanDeviceError as exc:
        raise r.fail("bus/device", str(exc))
    loopback = r.boolean(bus.get("loopback", False), "bus/loopback")
    plugin = r.string(bus.get("driver_plugin", SOCKETCAN_PLUGIN), "bus/driver_plugin")
    if plugin != SOCKETCAN_PLUGIN:
        r.warnings.append("%s: bus/driver_plugin %r ignored: bus/device chooses the adapter "
                          "(can0 for SocketCAN, INTERFACE:CHANNEL for others)" % (r.source, plugin))
    bitrate = None
    if "bitrate" in bus:
        bitrate = r.integer(bus.get("bitrate"), "bus/bitrate", _BITRATES[0], _BITRATES[-1])
        if bitrate not in _BITRATES:
            raise r.fail("bus/bitrate", "%d is not a CANopen bit rate (%s)"
                         % (bitrate, ", ".join(map(str, _BITRATES))))
        if interface == SOCKETCAN:
            r.warnings.append("%s: bus/bitrate ignored for %s: a SocketCAN interface's bit rate is set with "
                              "`ip link set %s type can bitrate %d`" % (r.source, device, device, bitrate))
    allocator = r.string(bus.get("master_allocator", BusConfig.master_allocator), "bus/master_allocator")
    return BusConfig(device, loopback, plugin, allocator, bitrate)


def _load_sync(r: ParamReader, params: Mapping[str, Any]) -> SyncConfig:
    sync = r.mapping(params.get("sync"), "sync")
    r.unknown(sync, _SYNC_KEYS, "sync/")
    # at most what a PDO's event timer (0x18xxsub5, UNSIGNED16 ms) can hold:
    # update_ms goes there when there is no SYNC
    interval = r.number(sync.get("interval_ms", 0), "sync/interval_ms", hi=MAX_PERIOD_MS)
    update = r.number(sync.get("update_ms", interval), "sync/update_ms", hi=MAX_PERIOD_MS)
    if update == 0:
        raise r.fail("sync/update_ms", "must be set (> 0) when sync/interval_ms is 0 or absent")
    overflow = r.integer(sync.get("overflow", 0), "sync/overflow", 0, 240)
    if overflow == 1:
        raise r.fail("sync/overflow", "1 is not allowed by CiA 301: use 0 (no counter) or 2..240")
    kernel_timer = r.boolean(sync.get("kernel_timer", SyncConfig.kernel_timer), "sync/kernel_timer")
    return SyncConfig(interval, update, overflow, kernel_timer)


def _load_realtime(r: ParamReader, params: Mapping[str, Any]) -> RealtimeConfig:
    rt = r.mapping(params.get("realtime"), "realtime")
    r.unknown(rt, _REALTIME_KEYS, "realtime/")
    return RealtimeConfig(r.boolean(rt.get("enabled", RealtimeConfig.enabled), "realtime/enabled"),
                          r.integer(rt.get("priority", RealtimeConfig.priority), "realtime/priority", 1, 99),
                          r.boolean(rt.get("lock_memory", RealtimeConfig.lock_memory), "realtime/lock_memory"))


def _load_shutdown_timeout(r: ParamReader, params: Mapping[str, Any]) -> float:
    """``timeouts/shutdown`` (s): the driver's own key (ros_canopen has
    none); other keys under ``timeouts`` are reported and ignored."""
    timeouts = r.mapping(params.get("timeouts"), "timeouts")
    r.unknown(timeouts, _TIMEOUT_KEYS, "timeouts/")
    value = r.number(timeouts.get("shutdown", DEFAULT_SHUTDOWN_TIMEOUT), "timeouts/shutdown",
                     hi=MAX_SHUTDOWN_TIMEOUT)
    if value <= 0:
        raise r.fail("timeouts/shutdown", "must be > 0 s")
    return value


def _load_heartbeat(r: ParamReader, params: Mapping[str, Any]) -> Optional[HeartbeatConfig]:
    if params.get("heartbeat") is None:
        return None
    hb = r.mapping(params["heartbeat"], "heartbeat")
    r.unknown(hb, _HEARTBEAT_KEYS, "heartbeat/")
    if not hb:
        return None
    if "rate" not in hb:
        raise r.fail("heartbeat/rate", "required when heartbeat is given")
    if "msg" not in hb:
        raise r.fail("heartbeat/msg", "required when heartbeat is given")
    rate = r.number(hb["rate"], "heartbeat/rate")
    if rate <= 0:
        raise r.fail("heartbeat/rate", "must be > 0 Hz")
    msg = r.string(hb["msg"], "heartbeat/msg")
    try:
        can_id, data, ext = parse_cansend(msg)
    except ValueError as e:
        raise r.fail("heartbeat/msg", str(e)) from None
    return HeartbeatConfig(rate, can_id, data, ext, msg)


def _overlay(r: ParamReader, value: Any, key: str) -> Tuple[Tuple[ObjectKey, str, str], ...]:
    overlay = r.mapping(value, key)
    out = []
    for k, v in overlay.items():
        sub = "%s/%s" % (key, k)
        try:
            okey = parse_object_key(k)
        except ObjectStringError as e:
            raise r.fail(sub, str(e)) from None
        if isinstance(v, bool) or not isinstance(v, (str, int, float)):
            raise r.fail(sub, "expected a value string like \"1000\" or \"0x7F0064\", got %r" % (v,))
        out.append((okey, str(v).strip(), str(k)))
    return tuple(out)


def _resolve_eds(r: ParamReader, node: Mapping[str, Any], prefix: str, resolver: Optional[Resolver]) -> Tuple[str, Optional[str]]:
    if "eds_file" not in node:
        raise r.fail(prefix + "eds_file", "required (path to the node's EDS/DCF file)")
    eds_file = os.path.expanduser(r.string(node["eds_file"], prefix + "eds_file"))
    pkg = node.get("eds_pkg")
    if pkg is not None:
        pkg = r.string(pkg, prefix + "eds_pkg")
    if os.path.isabs(eds_file):
        path = eds_file
    elif pkg:
        if resolver is None:
            raise r.fail(prefix + "eds_pkg", "cannot resolve package %r: no package resolver given" % pkg)
        try:
            base = resolver(pkg)
        except Exception as e:  # rospkg raises its own ResourceNotFound
            raise r.fail(prefix + "eds_pkg", "package %r not found (%s)" % (pkg, e)) from None
        path = os.path.join(base, eds_file)
    else:
        path = os.path.abspath(eds_file)
    if not os.path.isfile(path):
        raise r.fail(prefix + "eds_file", "file %r not found" % path)
    return path, pkg


def _units(r: ParamReader, node: Mapping[str, Any], prefix: str) -> Dict[str, Expression]:
    out = {}
    for k in _UNIT_KEYS:
        text = node.get(k, DEFAULT_UNITS[k])
        try:
            out[k] = compile_expression(text)
        except UnitExpressionError as e:
            raise r.fail(prefix + k, str(e)) from None
    for k in ("pos_to_device", "vel_to_device", "eff_to_device"):
        for v in out[k].variables:
            if v not in ("pos", "vel", "eff") and not v.startswith("obj"):
                raise r.fail(prefix + k, "unexpected variable %s" % v)
    return out


def _publish(r: ParamReader, value: Any, key: str, name: str) -> Tuple[PublishConfig, ...]:
    if value is None:
        return ()
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, (list, tuple)):
        raise r.fail(key, "expected a list of object strings like [\"6041\", \"1003sub0!\"], got %r" % (value,))
    out = []
    for i, spec in enumerate(value):
        try:
            okey, force = parse_publish_spec(spec)
        except ObjectStringError as e:
            raise r.fail("%s[%d]" % (key, i), str(e)) from None
        text = str(spec).strip().rstrip("!")
        out.append(PublishConfig(str(spec), okey, force, "%s_%s" % (name, text)))
    return tuple(out)


def _modes(r: ParamReader, value: Any, key: str) -> Tuple[int, ...]:
    """``modes: [CSP, 3]``: CiA 402 modes by number or short name."""
    if value is None:
        return ()
    if isinstance(value, (str, int)) and not isinstance(value, bool):
        value = [value]
    if not isinstance(value, (list, tuple)) or not value:
        raise r.fail(key, "expected a list of modes like [CSP] or [1, 3], got %r" % (value,))
    names = {v: k for k, v in SUPPORTED_DRIVE_MODES.items()}
    out: List[int] = []
    for i, m in enumerate(value):
        if isinstance(m, str) and m.strip().upper() in names:
            m = names[m.strip().upper()]
        if isinstance(m, bool) or not isinstance(m, int) or m not in SUPPORTED_DRIVE_MODES:
            raise r.fail("%s[%d]" % (key, i), "%r is not a supported mode; use one of %s" % (
                m, ", ".join("%d (%s)" % kv for kv in sorted(SUPPORTED_DRIVE_MODES.items()))))
        if m not in out:
            out.append(m)
    return tuple(out)


def _controller_modes(nodes: Tuple[NodeConfig, ...], controllers: Sequence[ControllerConfig],
                      r: ParamReader) -> Tuple[NodeConfig, ...]:
    """Give every node without a ``modes`` key the modes its controllers
    require; a compact PDO layout cannot be planned without any."""
    out = []
    for n in nodes:
        modes = n.modes
        if not modes:
            modes = tuple(sorted({c.required_drive_mode for c in controllers
                                  if c.required_drive_mode is not None and n.name in c.joints}))
            n = replace(n, modes=modes)
        if n.pdo_layout == "compact" and not modes:
            raise r.fail("nodes/%s/modes" % n.key, "pdo_layout compact maps only what the node's modes need: "
                         "give modes (e.g. [CSP]) or a controller with required_drive_mode for joint %r" % n.name)
        out.append(n)
    return tuple(out)


def _load_nodes(r: ParamReader, params: Mapping[str, Any], resolver: Optional[Resolver]) -> Tuple[NodeConfig, ...]:
    defaults = r.mapping(params.get("defaults"), "defaults")
    if "nodes" not in params or params["nodes"] in (None, {}, []):
        raise r.fail("nodes", "required: at least one node with id and eds_file")
    raw = params["nodes"]
    entries: List[Tuple[str, str, Any]] = []  # (key for messages, default name, value)
    if isinstance(raw, Mapping):
        for k, v in raw.items():
            entries.append(("nodes/%s/" % k, str(k), v))
    elif isinstance(raw, (list, tuple)):
        for i, v in enumerate(raw):
            entries.append(("nodes[%d]/" % i, "", v))
    else:
        raise r.fail("nodes", "expected a mapping or a list of nodes, got %s" % type(raw).__name__)

    nodes: List[NodeConfig] = []
    for prefix, default_name, value in entries:
        if value is None:
            # ros.yaml's "node2:  # ..." placeholder: nothing is configured there.
            r.warnings.append("%s: %s is empty and ignored" % (r.source, prefix.rstrip("/")))
            continue
        node = merge_params(defaults, r.mapping(value, prefix.rstrip("/"), allow_none=False))
        r.unknown(node, _NODE_KEYS, prefix)
        if "id" not in node:
            raise r.fail(prefix + "id", "required (CANopen node-ID 1..127)")
        node_id = r.integer(node["id"], prefix + "id", 1, 127)
        if "name" in node:
            name = r.string(node["name"], prefix + "name")
        elif default_name:
            name = default_name
        else:
            raise r.fail(prefix + "name", "required for nodes given as a list")
        if not name:
            raise r.fail(prefix + "name", "must not be empty")
        path, pkg = _resolve_eds(r, node, prefix, resolver)
        switching = r.integer(node.get("switching_state", 5), prefix + "switching_state")
        if switching not in SWITCHING_STATES:
            raise r.fail(prefix + "switching_state", "%d is not a state for mode switching; use one of %s"
                         % (switching, ", ".join("%d (%s)" % kv for kv in sorted(SWITCHING_STATES.items()))))
        units = _units(r, node, prefix)
        overlay = _overlay(r, node.get("dcf_overlay"), prefix + "dcf_overlay")
        publish = _publish(r, node.get("publish"), prefix + "publish", name)
        allocator = r.string(node.get("motor_allocator", NodeConfig.motor_allocator), prefix + "motor_allocator")
        pdo_layout = r.string(node.get("pdo_layout", PDO_LAYOUTS[0]), prefix + "pdo_layout")
        if pdo_layout not in PDO_LAYOUTS:
            raise r.fail(prefix + "pdo_layout", "%r is not a layout; use one of %s" % (pdo_layout, ", ".join(PDO_LAYOUTS)))
        modes = _modes(r, node.get("modes"), prefix + "modes")
        halt_mode = r.string(node.get("halt_mode", HALT_MODES[0]), prefix + "halt_mode")
        if halt_mode not in HALT_MODES:
            raise r.fail(prefix + "halt_mode", "%r is not a halt mode; use one of %s" % (halt_mode, ", ".join(HALT_MODES)))
        readings_every = r.integer(node.get("readings_every", 1), prefix + "readings_every", 1, 240)
        if readings_every > 1 and pdo_layout != "compact":
            raise r.fail(prefix + "readings_every", "needs pdo_layout: compact (a DCF layout keeps the DCF's "
                         "own transmission types)")
        extra = {k: v for k, v in node.items() if k not in _NODE_KEYS}
        if "motor_layer" in node:
            extra["motor_layer"] = node["motor_layer"]
            r.warnings.append("%s: %smotor_layer is accepted and not used" % (r.source, prefix))
        nodes.append(NodeConfig(
            key=prefix.split("/")[1] if prefix.startswith("nodes/") else name,
            node_id=node_id, name=name, eds_file=path, eds_pkg=pkg, dcf_overlay=overlay,
            switching_state=switching, publish=publish, motor_allocator=allocator,
            extra=MappingProxyType(extra), pdo_layout=pdo_layout, modes=modes, halt_mode=halt_mode,
            readings_every=readings_every,
            **units))
    if not nodes:
        raise r.fail("nodes", "no node configured")
    seen_ids: Dict[int, str] = {}
    seen_names: Dict[str, str] = {}
    for n in nodes:
        if n.node_id in seen_ids:
            raise r.fail("nodes/%s/id" % n.key, "node-ID %d is also used by %s" % (n.node_id, seen_ids[n.node_id]))
        if n.name in seen_names:
            raise r.fail("nodes/%s/name" % n.key, "name %r is also used by %s" % (n.name, seen_names[n.name]))
        seen_ids[n.node_id] = n.key
        seen_names[n.name] = n.key
    return tuple(nodes)


def _load_controllers(r: ParamReader, params: Mapping[str, Any], joints: Sequence[str]) -> Tuple[ControllerConfig, ...]:
    out = []
    for name, value in params.items():
        if name in _TOP_KEYS or not isinstance(value, Mapping) or "type" not in value:
            continue
        ctype = r.string(value["type"], name + "/type")
        if "/" not in ctype:
            raise r.fail(name + "/type", "expected 'package/Class' like position_controllers/JointPositionController")
        if "joint" in value and "joints" in value:
            raise r.fail(name, "give either joint or joints, not both")
        group = "joints" in value
        if "joint" in value:
            cjoints: Tuple[str, ...] = (r.string(value["joint"], name + "/joint"),)
        elif group:
            lst = value["joints"]
            if not isinstance(lst, (list, tuple)) or not lst:
                raise r.fail(name + "/joints", "expected a non-empty list of joint names")
            cjoints = tuple(r.string(j, "%s/joints[%d]" % (name, i)) for i, j in enumerate(lst))
        elif ctype.startswith("joint_state_controller/"):
            cjoints = tuple(joints)
        else:
            raise r.fail(name + "/joint", "required for controller type %s (or joints: [...])" % ctype)
        for j in cjoints:
            if j not in joints:
                r.warnings.append("%s: %s: joint %r is not a node on this bus" % (r.source, name, j))
        rate = None
        if "publish_rate" in value:
            rate = r.number(value["publish_rate"], name + "/publish_rate")
            if rate <= 0:
                raise r.fail(name + "/publish_rate", "must be > 0 Hz")
        mode = None
        if "required_drive_mode" in value:
            mode = r.integer(value["required_drive_mode"], name + "/required_drive_mode")
            if mode not in SUPPORTED_DRIVE_MODES:
                raise r.fail(name + "/required_drive_mode", "mode %d is not supported; use one of %s" % (
                    mode, ", ".join("%d (%s)" % kv for kv in sorted(SUPPORTED_DRIVE_MODES.items()))))
        constraints = MappingProxyType(dict(r.mapping(value.get("constraints"), name + "/constraints")))
        extra = MappingProxyType({k: v for k, v in value.items() if k not in _CONTROLLER_KEYS})
        out.append(ControllerConfig(name, ctype, cjoints, rate, mode, constraints, extra, group))
    return tuple(out)


def load_config(params: Mapping[str, Any], source: str, resolver: Optional[Resolver] = None) -> DriverConfig:
    """Read the node's parameter tree; raise ConfigError on the first mistake.

    source names where params came from (a file or a parameter namespace)
    and appears in every message. resolver maps a package name to its path
    (the node passes one built on rospkg); eds_file may also be absolute.
    """
    warnings: List[str] = []
    r = ParamReader(source, warnings)
    params = r.mapping(params, "(top level)", allow_none=False)
    bus = _load_bus(r, params)
    sync = _load_sync(r, params)
    heartbeat = _load_heartbeat(r, params)
    nodes = _load_nodes(r, params, resolver)
    node_names = [n.name for n in nodes]

    joint_names: Tuple[str, ...] = tuple(node_names)
    if "joint_names" in params:
        lst = params["joint_names"]
        if not isinstance(lst, (list, tuple)):
            raise r.fail("joint_names", "expected a list of joint names, got %r" % (lst,))
        joint_names = tuple(r.string(j, "joint_names[%d]" % i) for i, j in enumerate(lst))
        for j in joint_names:
            if j not in node_names:
                warnings.append("%s: joint_names: %r is not a node's name on this bus" % (source, j))
    controllers = _load_controllers(r, params, node_names)
    nodes = _controller_modes(nodes, controllers, r)
    for k, v in params.items():
        if k in _TOP_KEYS:
            continue
        if isinstance(v, Mapping) and "type" in v:
            continue
        warnings.append("%s: unknown option %s ignored" % (source, k))
    realtime = _load_realtime(r, params)
    shutdown_timeout = _load_shutdown_timeout(r, params)
    return DriverConfig(source, bus, sync, heartbeat, nodes, joint_names, controllers, tuple(warnings), realtime,
                        shutdown_timeout)
