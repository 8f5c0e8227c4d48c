"""Codec of the MANI rover CAN protocol (ROS-free).

The MANI protocol is a small private protocol (11-bit ids, no CANopen), so no
library implements it: this module is the one place that knows its bytes.
docs/mani_protocol.md is the specification; the decisions taken where the
seed's table is ambiguous are written there and tested in
test/unit/test_protocol.py.

Wire rules in short:

- id = message type base | node number (0 = EPS, 1..4 = drive nodes);
- integers are two's complement, little-endian (the rover's OBC packs them
  natively on a little-endian Jetson, the STM32 nodes read them as is);
- a boolean takes one byte, 0 or 1;
- orientationCmd/velocityCmd carry one int16: 2 data bytes as the rover's
  code sends them, or 4 (the seed table's length, bytes 3-4 zero) when
  can.command_data_length says so.

Every message is a frozen dataclass that validates itself on construction,
so an out-of-range message can neither be encoded nor come out of decode().
"""
from __future__ import annotations

import struct
from dataclasses import dataclass, fields
from typing import Dict, Mapping, Tuple, Type, Union

import can

# Node numbers (the last hex digit of an id).
POWER_SUPPLY = 0
FRONT_LEFT = 1
REAR_LEFT = 2
REAR_RIGHT = 3
FRONT_RIGHT = 4
DRIVE_NODES: Tuple[int, ...] = (FRONT_LEFT, REAR_LEFT, REAR_RIGHT, FRONT_RIGHT)
NODE_NAMES: Dict[int, str] = {
    POWER_SUPPLY: "power_supply",
    FRONT_LEFT: "front_left",
    REAR_LEFT: "rear_left",
    REAR_RIGHT: "rear_right",
    FRONT_RIGHT: "front_right",
}

# Message type ids (EPS messages) and bases (drive messages, | node number).
POWER_CMD_ID = 0x000
ERROR_WRN_ID = 0x010
CURRENT_WRN_ID = 0x020
POWER_FB_ID = 0x030
CURRENT_FB_ID = 0x0E0
SWITCH_CMD_BASE = 0x0A0
ORIENTATION_CMD_BASE = 0x0B0
VELOCITY_CMD_BASE = 0x0C0
LOCOMOTION_FB_BASE = 0x0D0
ODOMETRY_FB_BASE = 0x0E0

# The EPS current sensors in the order of errorWrn/currentWrn, which is also
# the meaning of CurrentFb.sensor_index (the rover's code names these five).
EPS_SENSORS: Tuple[str, ...] = (
    "battery", "front_left", "rear_left", "rear_right", "front_right")

# currentFb carries a reading normalised so that this value is the sensor's
# maximum current.
CURRENT_FULL_SCALE = 32768

# Data lengths of orientationCmd/velocityCmd: what the rover's code sends (2)
# and what the seed's table says (4).
COMMAND_DATA_LENGTHS: Tuple[int, ...] = (2, 4)

INT16_MIN = -32768
INT16_MAX = 32767
INT32_MAX = 2147483647

_INT16 = struct.Struct("<h")
_CURRENT_FB = struct.Struct("<ii")
_ODOMETRY_FB = struct.Struct("<hhhh")


class ProtocolError(ValueError):
    """A frame or message that is not valid MANI protocol; the text says why."""


def _check_bool(owner: object, name: str) -> None:
    value = getattr(owner, name)
    if isinstance(value, bool):
        return
    if isinstance(value, int) and value in (0, 1):
        object.__setattr__(owner, name, bool(value))
        return
    raise ProtocolError("%s.%s must be a boolean (0 or 1), got %r"
                        % (type(owner).__name__, name, value))


def _check_int(owner: object, name: str, low: int, high: int) -> None:
    value = getattr(owner, name)
    if isinstance(value, bool) or not isinstance(value, int):
        raise ProtocolError("%s.%s must be an integer, got %r"
                            % (type(owner).__name__, name, value))
    if not low <= value <= high:
        raise ProtocolError("%s.%s = %d is out of range [%d, %d]"
                            % (type(owner).__name__, name, value, low, high))


def _check_drive_node(owner: object) -> None:
    node_id = getattr(owner, "node_id")
    if isinstance(node_id, bool) or not isinstance(node_id, int) or node_id not in DRIVE_NODES:
        raise ProtocolError("%s.node_id must be a drive node 1..4 (front_left, rear_left, "
                            "rear_right, front_right), got %r"
                            % (type(owner).__name__, node_id))


@dataclass(frozen=True)
class PowerCmd:
    """0x000 OBC -> EPS: switch the power of all motors."""
    motor_power: bool

    def __post_init__(self) -> None:
        _check_bool(self, "motor_power")


@dataclass(frozen=True)
class PowerFb:
    """0x030 EPS -> OBC: state of the motor power switch."""
    motor_power: bool

    def __post_init__(self) -> None:
        _check_bool(self, "motor_power")


@dataclass(frozen=True)
class _SensorFlags:
    battery: bool = False
    front_left: bool = False
    rear_left: bool = False
    rear_right: bool = False
    front_right: bool = False

    def __post_init__(self) -> None:
        for name in EPS_SENSORS:
            _check_bool(self, name)

    def active(self) -> Tuple[str, ...]:
        """Names of the sensors whose flag is set, in EPS_SENSORS order."""
        return tuple(name for name in EPS_SENSORS if getattr(self, name))


@dataclass(frozen=True)
class ErrorWrn(_SensorFlags):
    """0x010 EPS -> OBC: over-current error per EPS current sensor."""


@dataclass(frozen=True)
class CurrentWrn(_SensorFlags):
    """0x020 EPS -> OBC: critical current (over 80 % of max) per EPS sensor."""


@dataclass(frozen=True)
class CurrentFb:
    """0x0E0 EPS -> OBC: one current reading; sensor_index into EPS_SENSORS,
    current normalised: CURRENT_FULL_SCALE is the sensor's maximum current."""
    sensor_index: int
    current: int

    def __post_init__(self) -> None:
        _check_int(self, "sensor_index", 0, len(EPS_SENSORS) - 1)
        _check_int(self, "current", -CURRENT_FULL_SCALE, CURRENT_FULL_SCALE)

    @property
    def sensor(self) -> str:
        return EPS_SENSORS[self.sensor_index]

    def amperes(self, max_current: Mapping[str, float]) -> float:
        """The reading in amperes, given each sensor's maximum current [A]."""
        return self.current / float(CURRENT_FULL_SCALE) * max_current[self.sensor]

    @classmethod
    def from_amperes(cls, sensor_index: int, amperes: float, maximum: float) -> "CurrentFb":
        """The reading an EPS sends for a current [A] of a sensor with the
        given maximum; beyond the maximum it saturates."""
        value = int(round(amperes / maximum * CURRENT_FULL_SCALE))
        return cls(sensor_index, max(-CURRENT_FULL_SCALE, min(CURRENT_FULL_SCALE, value)))


@dataclass(frozen=True)
class SwitchCmd:
    """0x0AX OBC -> drive node: steering/drive motor enable, odometryFb
    publishing, zeroing of the encoders."""
    node_id: int
    steer_mode: bool = False
    drive_mode: bool = False
    publisher_mode: bool = False
    zero_encoders: bool = False

    def __post_init__(self) -> None:
        _check_drive_node(self)
        for name in ("steer_mode", "drive_mode", "publisher_mode", "zero_encoders"):
            _check_bool(self, name)


@dataclass(frozen=True)
class OrientationCmd:
    """0x0BX OBC -> drive node: steering set point (the seed's set_orientation)
    in steering encoder pulses."""
    node_id: int
    orientation: int

    def __post_init__(self) -> None:
        _check_drive_node(self)
        _check_int(self, "orientation", INT16_MIN, INT16_MAX)


@dataclass(frozen=True)
class VelocityCmd:
    """0x0CX OBC -> drive node: wheel set point (the seed's set_velocity) in
    drive encoder pulses/s."""
    node_id: int
    velocity: int

    def __post_init__(self) -> None:
        _check_drive_node(self)
        _check_int(self, "velocity", INT16_MIN, INT16_MAX)


@dataclass(frozen=True)
class LocomotionFb:
    """0x0DX drive node -> OBC: the commanded orientation and velocity are reached."""
    node_id: int
    task_completed: bool

    def __post_init__(self) -> None:
        _check_drive_node(self)
        _check_bool(self, "task_completed")


@dataclass(frozen=True)
class OdometryFb:
    """0x0EX drive node -> OBC: steering position [steer pulses], wheel velocity
    [drive pulses/s], and the drive encoder count as revolutions * DRIVE_ENC_PPR
    + pulses (both 16-bit counters that wrap around)."""
    node_id: int
    orientation: int
    velocity: int
    pulses: int
    revolutions: int

    def __post_init__(self) -> None:
        _check_drive_node(self)
        for name in ("orientation", "velocity", "pulses", "revolutions"):
            _check_int(self, name, INT16_MIN, INT16_MAX)


Message = Union[PowerCmd, PowerFb, ErrorWrn, CurrentWrn, CurrentFb, SwitchCmd,
                OrientationCmd, VelocityCmd, LocomotionFb, OdometryFb]

_EPS_IDS: Dict[Type, int] = {
    PowerCmd: POWER_CMD_ID, ErrorWrn: ERROR_WRN_ID, CurrentWrn: CURRENT_WRN_ID,
    PowerFb: POWER_FB_ID, CurrentFb: CURRENT_FB_ID,
}
_DRIVE_BASES: Dict[Type, int] = {
    SwitchCmd: SWITCH_CMD_BASE, OrientationCmd: ORIENTATION_CMD_BASE,
    VelocityCmd: VELOCITY_CMD_BASE, LocomotionFb: LOCOMOTION_FB_BASE,
    OdometryFb: ODOMETRY_FB_BASE,
}


def arbitration_id(message: Message) -> int:
    """The 11-bit CAN id of a message."""
    kind = type(message)
    if kind in _EPS_IDS:
        return _EPS_IDS[kind]
    if kind in _DRIVE_BASES:
        return _DRIVE_BASES[kind] | message.node_id  # type: ignore[union-attr]
    raise ProtocolError("not a MANI message: %r" % (message,))


def check_command_data_length(length: int) -> int:
    """length if it is one of COMMAND_DATA_LENGTHS, else ValueError."""
    if isinstance(length, bool) or length not in COMMAND_DATA_LENGTHS:
        raise ValueError("command data length must be 2 or 4, got %r" % (length,))
    return length


def encode(message: Message, command_data_length: int = 2) -> Tuple[int, bytes]:
    """(arbitration id, data) of a message; see docs/mani_protocol.md.
    command_data_length: 2 (the rover's code) or 4 (the seed's table) bytes
    for orientationCmd and velocityCmd."""
    padding = b"\x00" * (check_command_data_length(command_data_length) - 2)
    can_id = arbitration_id(message)
    if isinstance(message, (PowerCmd, PowerFb)):
        data = bytes([message.motor_power])
    elif isinstance(message, _SensorFlags):
        data = bytes(getattr(message, name) for name in EPS_SENSORS)
    elif isinstance(message, CurrentFb):
        data = _CURRENT_FB.pack(message.sensor_index, message.current)
    elif isinstance(message, SwitchCmd):
        data = bytes([message.steer_mode, message.drive_mode,
                      message.publisher_mode, message.zero_encoders])
    elif isinstance(message, OrientationCmd):
        data = _INT16.pack(message.orientation) + padding
    elif isinstance(message, VelocityCmd):
        data = _INT16.pack(message.velocity) + padding
    elif isinstance(message, LocomotionFb):
        data = bytes([message.task_completed])
    else:  # OdometryFb; arbitration_id() rejected everything else
        data = _ODOMETRY_FB.pack(message.orientation, message.velocity,
                                 message.pulses, message.revolutions)
    return can_id, data


def to_can_message(message: Message, command_data_length: int = 2) -> can.Message:
    """A python-can frame (standard 11-bit id) carrying the message."""
    can_id, data = encode(message, command_data_length)
    return can.Message(arbitration_id=can_id, data=data, is_extended_id=False)


def _need_length(name: str, data: bytes, *allowed: int) -> None:
    if len(data) not in allowed:
        raise ProtocolError("%s needs %s data bytes, got %d"
                            % (name, " or ".join(str(n) for n in allowed), len(data)))


def _bool_at(name: str, data: bytes, index: int) -> bool:
    value = data[index]
    if value not in (0, 1):
        raise ProtocolError("%s byte %d must be 0 or 1, got 0x%02X" % (name, index + 1, value))
    return bool(value)


def _decode_flags(kind: Type[_SensorFlags], name: str, data: bytes) -> _SensorFlags:
    _need_length(name, data, len(EPS_SENSORS))
    return kind(*(_bool_at(name, data, i) for i in range(len(EPS_SENSORS))))


def decode(can_id: int, data: Union[bytes, bytearray]) -> Message:
    """The message in a frame; ProtocolError (a ValueError) says why a frame
    is not one: unknown id, wrong length or a value out of range."""
    data = bytes(data)
    if isinstance(can_id, bool) or not isinstance(can_id, int) or not 0 <= can_id <= 0x7FF:
        raise ProtocolError("id %r is not an 11-bit CAN id" % (can_id,))
    if can_id == POWER_CMD_ID:
        _need_length("powerCmd", data, 1)
        return PowerCmd(_bool_at("powerCmd", data, 0))
    if can_id == POWER_FB_ID:
        _need_length("powerFb", data, 1)
        return PowerFb(_bool_at("powerFb", data, 0))
    if can_id == ERROR_WRN_ID:
        return _decode_flags(ErrorWrn, "errorWrn", data)  # type: ignore[return-value]
    if can_id == CURRENT_WRN_ID:
        return _decode_flags(CurrentWrn, "currentWrn", data)  # type: ignore[return-value]
    if can_id == CURRENT_FB_ID:
        # 0x0E0 is the odometryFb range's node 0, i.e. the EPS: currentFb.
        _need_length("currentFb", data, 8)
        return CurrentFb(*_CURRENT_FB.unpack(data))
    base, node_id = can_id & ~0x00F, can_id & 0x00F
    if base not in _DRIVE_BASES.values() or node_id not in DRIVE_NODES:
        raise ProtocolError("id 0x%03X is not a MANI message" % can_id)
    if base == SWITCH_CMD_BASE:
        _need_length("switchCmd", data, 4)
        return SwitchCmd(node_id, *(_bool_at("switchCmd", data, i) for i in range(4)))
    if base == ORIENTATION_CMD_BASE:
        # Both data lengths in use carry the value in bytes 1-2.
        _need_length("orientationCmd", data, 2, 4)
        return OrientationCmd(node_id, _INT16.unpack_from(data)[0])
    if base == VELOCITY_CMD_BASE:
        _need_length("velocityCmd", data, 2, 4)
        return VelocityCmd(node_id, _INT16.unpack_from(data)[0])
    if base == LOCOMOTION_FB_BASE:
        _need_length("locomotionFb", data, 1)
        return LocomotionFb(node_id, _bool_at("locomotionFb", data, 0))
    _need_length("odometryFb", data, 8)
    return OdometryFb(node_id, *_ODOMETRY_FB.unpack(data))


def decode_can_message(frame: can.Message) -> Message:
    """decode() for a python-can frame; extended-id, remote and error frames
    are not MANI messages."""
    if frame.is_error_frame:
        raise ProtocolError("error frame")
    if frame.is_extended_id:
        raise ProtocolError("extended id 0x%08X is not a MANI message" % frame.arbitration_id)
    if frame.is_remote_frame:
        raise ProtocolError("remote frame 0x%03X is not a MANI message" % frame.arbitration_id)
    return decode(frame.arbitration_id, frame.data)


def describe(message: Message) -> str:
    """One line for logs: 'odometryFb[front_left] orientation=... velocity=...'."""
    name = type(message).__name__
    name = name[0].lower() + name[1:]
    values = []
    for field in fields(message):
        if field.name == "node_id":
            name += "[%s]" % NODE_NAMES[message.node_id]  # type: ignore[union-attr]
        else:
            values.append("%s=%s" % (field.name, getattr(message, field.name)))
    return " ".join([name] + values)
