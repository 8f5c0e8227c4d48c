"""The CANopen master of the EPOS4 driver (ROS-free).

``Driver(config, bus=None)`` with ``init/halt/recover/shutdown``,
``get_object/set_object``, ``switch_mode``, ``joints`` and the per-SYNC
cycle; see docs/driver.md.
"""
from .core import Driver
from .joint import COMMAND_KINDS, Joint, JointLimits
from .result import Result

__all__ = ["Driver", "Joint", "JointLimits", "Result", "COMMAND_KINDS"]
