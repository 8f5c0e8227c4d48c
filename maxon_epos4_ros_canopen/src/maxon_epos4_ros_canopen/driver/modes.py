"""The CiA 402 modes of operation the driver runs, one class each.

A mode knows its part of driving an axis; the axis asks it rather than
telling modes apart:
- which command it takes (position, velocity, effort or none) and which
  object that command goes to, and whether that target must reach the drive
  every SYNC (the cyclic modes);
- its controlword bits in Operation Enabled: the profile position
  new-set-point handshake, the homing start;
- how it holds: the targets "stay where you are" at a position the driver
  read itself, and, in profile position, a set-point of that position
  acknowledged by the drive before the axis lets the drive move;
- how it stops when the driver stops it (halt, an error): with the halt bit
  in the profile modes and homing (the drive decelerates on its profile),
  and with the drive's own quick stop in the cyclic modes, where the EPOS4
  has no halt bit and a held target would brake as hard as the motor can:
  the quick stop ramps at the drive's configured deceleration (0x6085).

``MODES`` holds one description of each mode (number, name, command, target)
for anyone to read. An axis runs its own instances (``Mode.fresh()``): the
profile position handshake and the homing bit are per drive.

The mode numbers are cia402.OperationMode's; nothing else defines them.
"""
from __future__ import annotations

from typing import Dict, Optional, Protocol

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
QUICK_STOP_OPTION_CODE = ObjectKey(0x605A)

COMMAND_KINDS = ("position", "velocity", "effort")
TARGET_OF_KIND = {"position": TARGET_POSITION, "velocity": TARGET_VELOCITY, "effort": TARGET_TORQUE}


class Axis(Protocol):
    """What a mode uses of the axis it runs on."""
    statusword: int
    homing: bool

    def send_target(self, kind: str, value: int) -> None:
        """Set a target and send its RxPDO this cycle, changed or not."""

    def stop_with_quick_stop(self) -> None:
        """Hold the drive with the quick stop command until a state is requested."""


class Mode:
    """One mode of operation as the driver's cycle runs it (no per-drive
    state: see the subclasses that have some)."""

    number: int = 0
    command_kind: Optional[str] = None   # what a controller commands in it
    cyclic = False                       # the target goes out every SYNC

    def fresh(self) -> "Mode":
        """An instance for one axis."""
        return type(self)()

    @property
    def name(self) -> str:
        return cia402.mode_name(self.number)

    @property
    def target(self) -> Optional[ObjectKey]:
        return TARGET_OF_KIND.get(self.command_kind or "")

    def stops_with_halt_bit(self) -> bool:
        """Whether the drive itself decelerates on the halt bit in this mode
        (profile modes and homing); the cyclic modes stop with quick stop."""
        return not self.cyclic

    # ----------------------------------------------------------- behaviour
    def command(self, axis: Axis, raw: int) -> None:
        """A command's device value was accepted. It goes out even when the
        driver sent the same value before: the drive may hold another (a
        frame someone else sent on the driver's RxPDO)."""
        if self.command_kind is not None and not self.cyclic:
            axis.send_target(self.command_kind, raw)

    def hold(self, axis: Axis, raw_position: int) -> None:
        """The axis holds still at ``raw_position`` (read over SDO); the
        targets of every kind are sent already (see Axis.hold)."""

    def holding(self) -> bool:
        """Whether the drive may still act on a target that is not the
        driver's own (the axis keeps the halt bit, or enables with it, until
        this is False)."""
        return False

    def enabled(self, axis: Axis) -> None:
        """The drive just came to Operation Enabled from another state."""

    def controlword_bits(self, axis: Axis) -> int:
        """The mode's controlword bits in Operation Enabled (not halted)."""
        return 0

    def stop(self, axis: Axis) -> None:
        """The driver stops the axis (halt, error); the axis has set its
        halt bit and dropped its command."""
        if not self.stops_with_halt_bit():
            axis.stop_with_quick_stop()

    def __repr__(self) -> str:
        return "<mode %d %s>" % (self.number, self.name)


class ProfilePosition(Mode):
    """Profile position: a target becomes motion only through the
    new-set-point handshake (change set immediately).

    The target goes out, sent whether it changed or not, one cycle before
    the new-set-point edge: a drive may apply the RPDO with the controlword
    before the one with 0x607A at the same SYNC, and would then take the
    old target. Stages: 0 idle, 3 target sent, 1 edge sent (wait for the
    set-point acknowledge, statusword bit 12), 2 edge cleared (wait for the
    acknowledge to drop).
    A hold in Operation Enabled (a halt released, a mode switched) is a
    set-point too: until the drive acknowledged the driver's own position,
    a set-point someone else gave it (a forged frame) may be pending, and
    the axis keeps the halt bit (``holding``). A drive that comes to
    Operation Enabled from another state has no set-point: it holds the
    position it is at then (the enable is given with the halt bit, see
    Axis._keeps_halt), and a set-point of a position read before the enable
    would move an unpowered shaft that crept meanwhile back to it."""

    number = int(OperationMode.PROFILE_POSITION)
    command_kind = "position"

    def __init__(self) -> None:
        self.pending: Optional[int] = None
        self.stage = 0
        self._hold_in_flight = False

    def command(self, axis: Axis, raw: int) -> None:
        self.pending = raw

    def hold(self, axis: Axis, raw_position: int) -> None:
        self.pending = raw_position
        self._hold_in_flight = True

    def holding(self) -> bool:
        return self._hold_in_flight

    def controlword_bits(self, axis: Axis) -> int:
        ack = axis.statusword & cia402.SW_SET_POINT_ACKNOWLEDGE
        bits = cia402.CW_CHANGE_SET_IMMEDIATELY
        stage = self.stage
        if stage == 3:
            self.stage = 1
            return bits | cia402.CW_NEW_SET_POINT | self._halt()
        if stage == 1:
            if not ack:
                return bits | cia402.CW_NEW_SET_POINT | self._halt()
            self.stage = stage = 2
        if stage == 2:
            if ack:
                return bits | self._halt()
            self.stage = 0
            if self.pending is None:
                self._hold_in_flight = False  # the drive took the driver's own set-point
        if self.pending is not None:
            axis.send_target("position", self.pending)
            self.pending = None
            self.stage = 3
        return bits | self._halt()

    def enabled(self, axis: Axis) -> None:
        if self._hold_in_flight:
            self.pending = None
            self.stage = 0
            self._hold_in_flight = False

    def _halt(self) -> int:
        return cia402.CW_HALT if self._hold_in_flight else 0

    def stop(self, axis: Axis) -> None:
        # what was not yet sent is dropped; a hold (recover) sends a new one
        self.pending = None
        self.stage = 0


class ProfileVelocity(Mode):
    number = int(OperationMode.PROFILE_VELOCITY)
    command_kind = "velocity"


class Homing(Mode):
    """Homing: bit 4 starts it and stays set while it runs (the axis's
    ``homing``, set and cleared by the homing service); clearing it
    interrupts it."""

    number = int(OperationMode.HOMING)

    def controlword_bits(self, axis: Axis) -> int:
        return cia402.CW_HOMING_START if axis.homing else 0


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
