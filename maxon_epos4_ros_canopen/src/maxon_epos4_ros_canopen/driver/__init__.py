"""The CANopen master of the EPOS4 driver (ROS-free).

The ownership rule: every mutable field has one owner thread. An axis's
state, and everything else the cycle works with, belongs to the driver's
cycle thread alone; every other thread sends it messages through the
cycle's inbox and reads it only as the immutable snapshot the cycle
publishes once per cycle. cycle.py lists who owns which field.

``Driver(config, bus=None)`` with ``init/halt/recover/shutdown``,
``get_object/set_object``, ``switch_mode``, ``set_command``, ``joints``
(the snapshots) and the per-SYNC cycle; see docs/driver.md.
"""
from __future__ import annotations

import importlib
from typing import Any

# The package's names, each from the module that defines it, imported when
# first used: a tool that needs one part (epos4_settings needs sdo.py) does
# not pay for loading the whole driver at every start.
_HOMES = {
    "Driver": ".core", "DriverSnapshot": ".core", "joint_states_stamp": ".core",
    "AxisSnapshot": ".snapshot", "COMMAND_KINDS": ".modes", "MODES": ".modes",
    "JointLimits": "..limits", "Result": "..result",
}

__all__ = list(_HOMES)


def __getattr__(name: str) -> Any:
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError("module %r has no attribute %r" % (__name__, name))
    value = getattr(importlib.import_module(home, __name__), name)
    globals()[name] = value  # the next lookup finds it here
    return value


def __dir__() -> list:
    return sorted(set(globals()) | set(_HOMES))
