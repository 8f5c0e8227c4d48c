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
from ..limits import JointLimits
from ..result import Result
from .snapshot import AxisSnapshot
from .core import Driver, DriverSnapshot, joint_states_stamp
from .modes import COMMAND_KINDS, MODES

__all__ = ["Driver", "DriverSnapshot", "joint_states_stamp", "AxisSnapshot", "JointLimits", "Result", "COMMAND_KINDS", "MODES"]
