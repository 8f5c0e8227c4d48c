"""The CANopen master of the EPOS4 driver (ROS-free).

The ownership rule: an axis's state belongs to the driver's cycle thread
alone; every other thread sends it messages through the driver's inbox and
reads it only as the immutable snapshot the cycle publishes once per cycle.

``Driver(config, bus=None)`` with ``init/halt/recover/shutdown``,
``get_object/set_object``, ``switch_mode``, ``set_command``, ``joints``
(the snapshots) and the per-SYNC cycle; see docs/driver.md.
"""
from ..limits import JointLimits
from ..result import Result
from .axis import AxisSnapshot
from .core import Driver, DriverSnapshot
from .modes import COMMAND_KINDS, MODES

__all__ = ["Driver", "DriverSnapshot", "AxisSnapshot", "JointLimits", "Result", "COMMAND_KINDS", "MODES"]
