"""The CiA 402 modes of operation the driver runs, one object each.

A mode says which command it takes (position, velocity, effort or none),
which object that command goes to, whether the target must reach the drive
every SYNC (cyclic modes), the controlword bits it adds in Operation
Enabled, and how the axis stops in it when the driver stops it (halt or an
error): with the drive's own means where the mode has them (the halt bit in
the profile modes), otherwise by holding a target the driver itself sent.

The mode numbers are cia402.OperationMode's; nothing else defines them.
"""
from __future__ import annotations

from typing import Dict, Optional

from .. import cia402
from ..cia402 import OperationMode
from ..objects import ObjectKey

# The CiA 402 objects the driver exchanges every cycle.
CONTROLWORD = ObjectKey(0x6040)
MODES_OF_OPERATION = ObjectKey(0x6060)
TARGET_POSITION = ObjectKey(0x607A)
TARGET_VELOCITY = ObjectKey(0x60FF)
TARGET_TORQUE = ObjectKey(0x6071)
STATUSWORD = ObjectKey(0x6041)
MODES_DISPLAY = ObjectKey(0x6061)
POSITION_ACTUAL = ObjectKey(0x6064)
VELOCITY_ACTUAL = ObjectKey(0x606C)

COMMAND_KINDS = ("position", "velocity", "effort")
TARGET_OF_KIND = {"position": TARGET_POSITION, "velocity": TARGET_VELOCITY, "effort": TARGET_TORQUE}


class Mode:
    """One mode of operation, as the driver's cycle runs it."""

    number: int = 0
    command_kind: Optional[str] = None   # what a controller commands in it
    cyclic = False                       # the target goes out every SYNC

    @property
    def name(self) -> str:
        return cia402.mode_name(self.number)

    @property
    def target(self) -> Optional[ObjectKey]:
        return TARGET_OF_KIND.get(self.command_kind or "")

    def stops_with_halt_bit(self) -> bool:
        """Whether the drive itself decelerates on the halt bit in this mode
        (profile modes and homing); cyclic modes hold a target instead."""
        return not self.cyclic

    def __repr__(self) -> str:
        return "<mode %d %s>" % (self.number, self.name)


class ProfilePosition(Mode):
    number = int(OperationMode.PROFILE_POSITION)
    command_kind = "position"


class ProfileVelocity(Mode):
    number = int(OperationMode.PROFILE_VELOCITY)
    command_kind = "velocity"


class Homing(Mode):
    number = int(OperationMode.HOMING)


class CyclicSyncPosition(Mode):
    number = int(OperationMode.CYCLIC_SYNC_POSITION)
    command_kind = "position"
    cyclic = True


class CyclicSyncVelocity(Mode):
    number = int(OperationMode.CYCLIC_SYNC_VELOCITY)
    command_kind = "velocity"
    cyclic = True


class CyclicSyncTorque(Mode):
    number = int(OperationMode.CYCLIC_SYNC_TORQUE)
    command_kind = "effort"
    cyclic = True


MODES: Dict[int, Mode] = {m.number: m for m in (
    ProfilePosition(), ProfileVelocity(), Homing(), CyclicSyncPosition(), CyclicSyncVelocity(),
    CyclicSyncTorque())}
PROFILE_POSITION = MODES[int(OperationMode.PROFILE_POSITION)]
HOMING = MODES[int(OperationMode.HOMING)]


def mode_of(number: Optional[int]) -> Optional[Mode]:
    """The Mode for a 0x6060/0x6061 value, None for any other value."""
    if number is None:
        return None
    return MODES.get(number)


def supported_modes_text() -> str:
    return ", ".join("%d %s" % (n, m.name) for n, m in sorted(MODES.items()))
