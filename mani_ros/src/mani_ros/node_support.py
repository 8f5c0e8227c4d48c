"""What every mani_ros node does at start, kept ROS-free: checked parameters,
the rover configuration, the CAN device.

The nodes pass ``rospy.get_param`` and a logger in, so the checks are plain
Python and testable without a ROS master. A bad parameter value never stops
a node: it is reported with the parameter's name and replaced by the default.
"""
from __future__ import annotations

import math
from typing import Any, Callable, Optional, Sequence, Tuple

from .config import ManiConfig, config_from_dict, load_config

Getter = Callable[[str, Any], Any]
Logger = Callable[[str], None]


def _problem(value: Any, kind: type, minimum: Optional[float], maximum: Optional[float],
             choices: Optional[Sequence[Any]]) -> Optional[str]:
    """Why ``value`` is not acceptable, or None when it is."""
    # bool is an int in Python; a YAML 'true' where a number belongs is a mistake.
    if kind is bool:
        if not isinstance(value, bool):
            return "is not true/false"
    elif kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            return "is not an integer"
    elif kind is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return "is not a number"
        if not math.isfinite(value):
            return "is not finite"
    elif kind is str:
        if not isinstance(value, str):
            return "is not a string"
    if choices is not None and value not in choices:
        return "is not one of %s" % ", ".join(repr(c) for c in choices)
    if minimum is not None and kind in (int, float) and value < minimum:
        return "is below %s" % minimum
    if maximum is not None and kind in (int, float) and value > maximum:
        return "is above %s" % maximum
    return None


def read_param(get: Getter, name: str, default: Any, kind: type = float,
               minimum: Optional[float] = None, maximum: Optional[float] = None,
               choices: Optional[Sequence[Any]] = None,
               log_error: Optional[Logger] = None) -> Any:
    """Read parameter ``name`` through ``get(name, default)`` and check it.

    Returns the value (ints widened to float when ``kind`` is float) or, with
    an error logged that names the parameter, the default.
    """
    value = get(name, default)
    problem = _problem(value, kind, minimum, maximum, choices)
    if problem is not None:
        if log_error is not None:
            log_error("parameter %s: %r %s; using %r" % (name, value, problem, default))
        return default
    if kind is float:
        return float(value)
    return value


def node_config(get: Getter) -> ManiConfig:
    """The rover configuration of a node: the file in ``~config`` if set,
    else the ROS parameters under ``mani`` (what the launch files load from
    config/mani.yaml), else the package's config/mani.yaml.
    Raises ConfigError naming the key and its source."""
    path = get("~config", "")
    if path:
        return load_config(str(path))
    data = get("mani", None)
    if data is not None:
        return config_from_dict(data, "the ROS parameters under 'mani'")
    return load_config()


def can_settings(get: Getter, config: ManiConfig,
                 log_error: Optional[Logger] = None) -> Tuple[str, str]:
    """(python-can interface, channel): ``~can_interface``/``~can_device`` if
    set, else the configuration's; ``~use_sim_device: true`` picks
    can.sim_device (the simulated rover's bus, vcan0)."""
    use_sim = read_param(get, "~use_sim_device", False, bool, log_error=log_error)
    device = config.can.sim_device if use_sim else config.can.device
    interface = read_param(get, "~can_interface", config.can.interface, str, log_error=log_error)
    device = read_param(get, "~can_device", device, str, log_error=log_error)
    return interface or config.can.interface, device or (config.can.sim_device if use_sim else config.can.device)


class ParamReader:
    """``read_param`` for a node's private parameters:
    ``p = ParamReader(rospy.get_param, rospy.logerr); p("timeout", 2.0, minimum=0)``."""

    def __init__(self, get: Getter, log_error: Optional[Logger] = None) -> None:
        self.get = get
        self.log_error = log_error

    def __call__(self, name: str, default: Any, kind: type = float, **checks: Any) -> Any:
        return read_param(self.get, "~" + name, default, kind, log_error=self.log_error, **checks)
