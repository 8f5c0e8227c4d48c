"""CiA 402 power state machine: the one implementation shared by the driver
(master side) and the virtual EPOS4 (drive side).

Public API
----------
``State``
    The eight power states of CiA 402 (maxon EPOS4 Firmware Specification,
    "Device Control": state machine and its transitions).
``OperationMode``
    Modes of operation the EPOS4 supports over CANopen (0x6060/0x6061):
    PROFILE_POSITION 1, PROFILE_VELOCITY 3, HOMING 6, CYCLIC_SYNC_POSITION 8,
    CYCLIC_SYNC_VELOCITY 9, CYCLIC_SYNC_TORQUE 10.  ``mode_name(value)``
    gives a readable name for any int8 value.
``SW_*``
    Statusword (0x6041) bit masks.
``CW_*``
    Controlword (0x6040) bit masks and the complete device-control commands
    ``CW_SHUTDOWN`` 0x0006, ``CW_SWITCH_ON`` 0x0007, ``CW_DISABLE_VOLTAGE``
    0x0000, ``CW_QUICK_STOP`` 0x0002, ``CW_DISABLE_OPERATION`` 0x0007,
    ``CW_ENABLE_OPERATION`` 0x000F, ``CW_FAULT_RESET`` 0x0080 (acts on the
    rising edge of bit 7: send a controlword with bit 7 clear first).
``state_from_statusword(sw) -> State``
    Master side: decode a statusword; raises ``ValueError`` for bit patterns
    CiA 402 does not define.
``next_controlword(current_state, target_state, quick_stop_option_code=None) -> Optional[int]``
    Master side: the controlword that moves the drive one transition closer
    to ``target_state``, or ``None`` when the drive is already there or no
    command can help right now (it moves on its own out of
    NOT_READY_TO_SWITCH_ON and FAULT_REACTION_ACTIVE, and out of
    QUICK_STOP_ACTIVE with option codes 0-4; FAULT and FAULT_REACTION_ACTIVE
    and NOT_READY_TO_SWITCH_ON are not command targets). With option codes
    5-8 enable operation leaves QUICK_STOP_ACTIVE (transition 16).
``apply_controlword(state, cw, previous_cw=0, quick_stop_option_code=2) -> State``
    Drive side: the state after the drive receives controlword ``cw``.
    Automatic transitions (0, 1, 13, 14, and the end of a quick stop for
    option codes 1-4) belong to the drive model, not to this function.
``statusword_state_bits(state) -> int``
    Drive side: statusword bits 0-3, 5 and 6 that encode ``state``; the drive
    adds voltage-enabled, warning, remote and the mode-specific bits.
"""
from __future__ import annotations

import enum
from collections import deque
from typing import Dict, List, Optional, Tuple

__all__ = [
    "State", "OperationMode", "MODE_SHORT_NAMES", "mode_name", "state_from_statusword", "state_or_none",
    "next_controlword", "apply_controlword", "statusword_state_bits",
    "COMMANDS", "stays_in_quick_stop",
]


class State(enum.Enum):
    NOT_READY_TO_SWITCH_ON = "not_ready_to_switch_on"
    SWITCH_ON_DISABLED = "switch_on_disabled"
    READY_TO_SWITCH_ON = "ready_to_switch_on"
    SWITCHED_ON = "switched_on"
    OPERATION_ENABLED = "operation_enabled"
    QUICK_STOP_ACTIVE = "quick_stop_active"
    FAULT_REACTION_ACTIVE = "fault_reaction_active"
    FAULT = "fault"


class OperationMode(enum.IntEnum):
    PROFILE_POSITION = 1
    PROFILE_VELOCITY = 3
    HOMING = 6
    CYCLIC_SYNC_POSITION = 8
    CYCLIC_SYNC_VELOCITY = 9
    CYCLIC_SYNC_TORQUE = 10


# The short names ros_canopen users write (node layer ``modes``, docs).
MODE_SHORT_NAMES = {
    OperationMode.PROFILE_POSITION: "PPM", OperationMode.PROFILE_VELOCITY: "PVM", OperationMode.HOMING: "HM",
    OperationMode.CYCLIC_SYNC_POSITION: "CSP", OperationMode.CYCLIC_SYNC_VELOCITY: "CSV",
    OperationMode.CYCLIC_SYNC_TORQUE: "CST",
}


def mode_name(value: int) -> str:
    """Readable name of a modes-of-operation value (0x6060/0x6061)."""
    try:
        return OperationMode(value).name.lower()
    except ValueError:
        return "no_mode" if value == 0 else "unknown_mode_%d" % value


# --- statusword 0x6041 -------------------------------------------------------
SW_READY_TO_SWITCH_ON = 0x0001
SW_SWITCHED_ON = 0x0002
SW_OPERATION_ENABLED = 0x0004
SW_FAULT = 0x0008
SW_VOLTAGE_ENABLED = 0x0010
SW_QUICK_STOP = 0x0020  # 0 = a quick stop is being executed (active low)
SW_SWITCH_ON_DISABLED = 0x0040
SW_WARNING = 0x0080
SW_REMOTE = 0x0200  # EPOS4 sets it once it is controlled over CANopen
SW_TARGET_REACHED = 0x0400
SW_INTERNAL_LIMIT_ACTIVE = 0x0800
# Bit 12 and 13 depend on the mode of operation.
SW_SET_POINT_ACKNOWLEDGE = 0x1000  # profile position
SW_SPEED = 0x1000  # profile velocity: 1 = speed is zero
SW_HOMING_ATTAINED = 0x1000  # homing
SW_DRIVE_FOLLOWS_COMMAND = 0x1000  # cyclic synchronous modes
SW_FOLLOWING_ERROR = 0x2000  # profile position, CSP, CSV
SW_HOMING_ERROR = 0x2000  # homing
SW_POSITION_REFERENCED = 0x8000  # EPOS4: position referenced to home position

# Masks that pick out the state-encoding bits (CiA 402 statusword table).
_MASK_WITH_QS = 0x006F
_MASK_WITHOUT_QS = 0x004F
_STATE_PATTERNS: List[Tuple[int, int, State]] = [
    (_MASK_WITHOUT_QS, 0x0000, State.NOT_READY_TO_SWITCH_ON),
    (_MASK_WITHOUT_QS, 0x0040, State.SWITCH_ON_DISABLED),
    (_MASK_WITH_QS, 0x0021, State.READY_TO_SWITCH_ON),
    (_MASK_WITH_QS, 0x0023, State.SWITCHED_ON),
    (_MASK_WITH_QS, 0x0027, State.OPERATION_ENABLED),
    (_MASK_WITH_QS, 0x0007, State.QUICK_STOP_ACTIVE),
    (_MASK_WITHOUT_QS, 0x000F, State.FAULT_REACTION_ACTIVE),
    (_MASK_WITHOUT_QS, 0x0008, State.FAULT),
]

_STATE_BITS: Dict[State, int] = {
    State.NOT_READY_TO_SWITCH_ON: 0x0000,
    State.SWITCH_ON_DISABLED: 0x0040,
    State.READY_TO_SWITCH_ON: 0x0021,
    State.SWITCHED_ON: 0x0023,
    State.OPERATION_ENABLED: 0x0027,
    State.QUICK_STOP_ACTIVE: 0x0007,
    State.FAULT_REACTION_ACTIVE: 0x000F,
    State.FAULT: 0x0008,
}

# --- controlword 0x6040 ------------------------------------------------------
CW_SWITCH_ON_BIT = 0x0001
CW_ENABLE_VOLTAGE = 0x0002
CW_QUICK_STOP_BIT = 0x0004  # 0 = quick stop (active low)
CW_ENABLE_OPERATION_BIT = 0x0008
CW_NEW_SET_POINT = 0x0010  # profile position: rising edge takes 0x607A
CW_HOMING_START = 0x0010  # homing: 1 starts/continues homing
CW_CHANGE_SET_IMMEDIATELY = 0x0020  # profile position
CW_RELATIVE = 0x0040  # profile position: target is relative
CW_FAULT_RESET_BIT = 0x0080
CW_HALT = 0x0100
CW_ENDLESS_MOVEMENT = 0x8000  # EPOS4 profile position

CW_SHUTDOWN = 0x0006
CW_SWITCH_ON = 0x0007
CW_DISABLE_VOLTAGE = 0x0000
CW_QUICK_STOP = 0x0002
CW_DISABLE_OPERATION = 0x0007
CW_ENABLE_OPERATION = 0x000F
CW_FAULT_RESET = 0x0080

COMMANDS: Dict[str, int] = {
    "shutdown": CW_SHUTDOWN,
    "switch_on": CW_SWITCH_ON,
    "disable_voltage": CW_DISABLE_VOLTAGE,
    "quick_stop": CW_QUICK_STOP,
    "disable_operation": CW_DISABLE_OPERATION,
    "enable_operation": CW_ENABLE_OPERATION,
    "fault_reset": CW_FAULT_RESET,
}

# Bits that select a device-control command; the others are mode specific.
_CW_COMMAND_MASK = 0x008F


def state_from_statusword(sw: int) -> State:
    """Decode the power state of a statusword (0x6041).

    Raises ValueError when bits 0-3, 5, 6 form no CiA 402 state.
    """
    for mask, value, state in _STATE_PATTERNS:
        if sw & mask == value:
            return state
    raise ValueError("statusword 0x%04X encodes no CiA 402 state" % (sw & 0xFFFF))


def state_or_none(sw: int) -> Optional[State]:
    """The power state of a statusword, or None when it encodes none (a
    frame that lies, a drive mid-reset): for callers that must go on."""
    try:
        return state_from_statusword(sw)
    except ValueError:
        return None


def statusword_state_bits(state: State) -> int:
    """Statusword bits 0-3, 5, 6 for ``state`` (drive side)."""
    return _STATE_BITS[state]


# Commanded transitions only (CiA 402 transitions 2-12, 15, 16); automatic
# ones are the drive's business. What Quick Stop Active allows depends on the
# quick stop option code (0x605A), see _quick_stop_edges.
_EDGES: Dict[State, List[Tuple[int, State]]] = {
    State.SWITCH_ON_DISABLED: [(CW_SHUTDOWN, State.READY_TO_SWITCH_ON)],
    State.READY_TO_SWITCH_ON: [(CW_SWITCH_ON, State.SWITCHED_ON),
                               (CW_DISABLE_VOLTAGE, State.SWITCH_ON_DISABLED)],
    State.SWITCHED_ON: [(CW_ENABLE_OPERATION, State.OPERATION_ENABLED),
                        (CW_SHUTDOWN, State.READY_TO_SWITCH_ON),
                        (CW_DISABLE_VOLTAGE, State.SWITCH_ON_DISABLED)],
    State.OPERATION_ENABLED: [(CW_DISABLE_OPERATION, State.SWITCHED_ON),
                              (CW_QUICK_STOP, State.QUICK_STOP_ACTIVE),
                              (CW_SHUTDOWN, State.READY_TO_SWITCH_ON),
                              (CW_DISABLE_VOLTAGE, State.SWITCH_ON_DISABLED)],
    State.QUICK_STOP_ACTIVE: [(CW_DISABLE_VOLTAGE, State.SWITCH_ON_DISABLED)],
    State.FAULT: [(CW_FAULT_RESET, State.SWITCH_ON_DISABLED)],
    State.NOT_READY_TO_SWITCH_ON: [],
    State.FAULT_REACTION_ACTIVE: [],
}


def stays_in_quick_stop(quick_stop_option_code: Optional[int]) -> bool:
    """Whether a drive with this 0x605A stays in Quick Stop Active after its
    ramp (codes 5-8), where enable operation takes it back (transition 16)."""
    return quick_stop_option_code is not None and 5 <= quick_stop_option_code <= 8


def _quick_stop_edges(quick_stop_option_code: Optional[int]) -> List[Tuple[int, State]]:
    """Commands out of Quick Stop Active that keep a moving drive powered.

    Codes 5-8: enable operation (transition 16) back to Operation Enabled,
    disable voltage only for a target beyond it. Codes 0-4: none; the drive
    ends its ramp in Switch On Disabled by itself (disable voltage in the
    ramp would let it coast). Unknown (None): disable voltage, the one
    command every drive takes there."""
    if stays_in_quick_stop(quick_stop_option_code):
        return [(CW_ENABLE_OPERATION, State.OPERATION_ENABLED), (CW_DISABLE_VOLTAGE, State.SWITCH_ON_DISABLED)]
    if quick_stop_option_code is None:
        return _EDGES[State.QUICK_STOP_ACTIVE]
    return []


def next_controlword(current_state: State, target_state: State,
                     quick_stop_option_code: Optional[int] = None) -> Optional[int]:
    """Controlword for the first transition on the shortest path from
    ``current_state`` to ``target_state`` (master side).

    Returns None when ``current_state == target_state`` or when no command
    leads there from ``current_state`` (wait for the drive, or the target is
    a state only the drive itself enters, such as FAULT).
    ``quick_stop_option_code`` is the drive's 0x605A: it decides the way out
    of QUICK_STOP_ACTIVE (see _quick_stop_edges).
    """
    if current_state == target_state:
        return None

    def edges(state: State) -> List[Tuple[int, State]]:
        if state == State.QUICK_STOP_ACTIVE:
            return _quick_stop_edges(quick_stop_option_code)
        return _EDGES[state]
    seen = {current_state}
    queue = deque((cw, nxt) for cw, nxt in edges(current_state))
    while queue:
        first_cw, state = queue.popleft()
        if state == target_state:
            return first_cw
        if state in seen:
            continue
        seen.add(state)
        queue.extend((first_cw, nxt) for _, nxt in edges(state))
    return None


def _command(cw: int) -> Optional[str]:
    """Device-control command encoded by bits 0-3 and 7 (bit 7 must be 0)."""
    if cw & CW_FAULT_RESET_BIT:
        return None
    if not cw & CW_ENABLE_VOLTAGE:
        return "disable_voltage"
    if not cw & CW_QUICK_STOP_BIT:
        return "quick_stop"
    if not cw & CW_SWITCH_ON_BIT:
        return "shutdown"
    if not cw & CW_ENABLE_OPERATION_BIT:
        return "switch_on"  # also "disable_operation"
    return "enable_operation"


def apply_controlword(state: State, cw: int, previous_cw: int = 0,
                      quick_stop_option_code: int = 2) -> State:
    """Drive side: the power state after receiving controlword ``cw``.

    ``previous_cw`` is the controlword received before, for the fault reset
    edge.  ``quick_stop_option_code`` (0x605A) decides whether enable
    operation leaves QUICK_STOP_ACTIVE (codes 5-8, transition 16).
    """
    if state == State.FAULT:
        if cw & CW_FAULT_RESET_BIT and not previous_cw & CW_FAULT_RESET_BIT:
            return State.SWITCH_ON_DISABLED  # transition 15
        return state
    if state in (State.NOT_READY_TO_SWITCH_ON, State.FAULT_REACTION_ACTIVE):
        return state
    command = _command(cw)
    if command is None:
        return state
    if state == State.SWITCH_ON_DISABLED:
        return State.READY_TO_SWITCH_ON if command == "shutdown" else state
    if state == State.READY_TO_SWITCH_ON:
        if command == "switch_on":
            return State.SWITCHED_ON  # 3
        if command == "enable_operation":
            return State.OPERATION_ENABLED  # 3 + 4
        if command in ("disable_voltage", "quick_stop"):
            return State.SWITCH_ON_DISABLED  # 7
        return state
    if state == State.SWITCHED_ON:
        if command == "enable_operation":
            return State.OPERATION_ENABLED  # 4
        if command == "shutdown":
            return State.READY_TO_SWITCH_ON  # 6
        if command in ("disable_voltage", "quick_stop"):
            return State.SWITCH_ON_DISABLED  # 10
        return state
    if state == State.OPERATION_ENABLED:
        if command == "switch_on":
            return State.SWITCHED_ON  # 5 (disable operation)
        if command == "shutdown":
            return State.READY_TO_SWITCH_ON  # 8
        if command == "disable_voltage":
            return State.SWITCH_ON_DISABLED  # 9
        if command == "quick_stop":
            return State.QUICK_STOP_ACTIVE  # 11
        return state
    # QUICK_STOP_ACTIVE
    if command == "disable_voltage":
        return State.SWITCH_ON_DISABLED  # 12
    if command == "enable_operation" and stays_in_quick_stop(quick_stop_option_code):
        return State.OPERATION_ENABLED  # 16
    return state
