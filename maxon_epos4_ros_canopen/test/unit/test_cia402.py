"""CiA 402 state machine against statusword values an EPOS4 reports."""
import itertools

import pytest

from maxon_epos4_ros_canopen import cia402
from maxon_epos4_ros_canopen.cia402 import State, apply_controlword, next_controlword, state_from_statusword


@pytest.mark.parametrize("sw, state", [
    (0x0000, State.NOT_READY_TO_SWITCH_ON),
    (0x0250, State.SWITCH_ON_DISABLED),
    (0x0240, State.SWITCH_ON_DISABLED),
    (0x0231, State.READY_TO_SWITCH_ON),
    (0x0233, State.SWITCHED_ON),
    (0x0237, State.OPERATION_ENABLED),
    (0x1637, State.OPERATION_ENABLED),  # PPM: target reached + set-point ack
    (0x8637, State.OPERATION_ENABLED),  # referenced to home
    (0x0217, State.QUICK_STOP_ACTIVE),
    (0x021F, State.FAULT_REACTION_ACTIVE),
    (0x0218, State.FAULT),
    (0x0208, State.FAULT),
    (0x0298, State.FAULT),  # fault + warning
])
def test_recorded_statuswords_decode(sw, state):
    assert state_from_statusword(sw) == state


@pytest.mark.parametrize("sw", [0x0001, 0x0003, 0x0023 & ~0x20, 0x0061, 0x0067])
def test_undefined_patterns_raise(sw):
    with pytest.raises(ValueError, match="0x%04X" % sw):
        state_from_statusword(sw)


@pytest.mark.parametrize("sw", [0x0001, 0x0003, 0x0061, 0x0067])
def test_state_or_none_gives_none_for_undefined_patterns(sw):
    assert cia402.state_or_none(sw) is None
    assert cia402.state_or_none(0x0637) == State.OPERATION_ENABLED


def test_state_bits_round_trip():
    for state in State:
        bits = cia402.statusword_state_bits(state)
        assert state_from_statusword(bits | cia402.SW_VOLTAGE_ENABLED | cia402.SW_REMOTE) == state


def test_enable_sequence_from_switch_on_disabled():
    state = State.SWITCH_ON_DISABLED
    sent = []
    while state != State.OPERATION_ENABLED:
        cw = next_controlword(state, State.OPERATION_ENABLED)
        sent.append(cw)
        state = apply_controlword(state, cw)
    assert sent == [0x0006, 0x0007, 0x000F]


def test_fault_to_operation_enabled_starts_with_fault_reset():
    assert next_controlword(State.FAULT, State.OPERATION_ENABLED) == 0x0080
    assert next_controlword(State.QUICK_STOP_ACTIVE, State.OPERATION_ENABLED) == 0x0000
    assert next_controlword(State.OPERATION_ENABLED, State.SWITCH_ON_DISABLED) == 0x0000
    assert next_controlword(State.OPERATION_ENABLED, State.SWITCHED_ON) == 0x0007
    assert next_controlword(State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE) == 0x0002
    assert next_controlword(State.SWITCHED_ON, State.READY_TO_SWITCH_ON) == 0x0006


def test_no_command_reaches_drive_only_states():
    assert next_controlword(State.OPERATION_ENABLED, State.OPERATION_ENABLED) is None
    assert next_controlword(State.OPERATION_ENABLED, State.FAULT) is None
    assert next_controlword(State.FAULT_REACTION_ACTIVE, State.SWITCH_ON_DISABLED) is None
    assert next_controlword(State.NOT_READY_TO_SWITCH_ON, State.OPERATION_ENABLED) is None


def test_every_planned_path_arrives():
    targets = [State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON, State.SWITCHED_ON,
               State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE]
    starts = targets + [State.FAULT]
    for start, target in itertools.product(starts, targets):
        state, previous, steps = start, 0, 0
        while state != target:
            cw = next_controlword(state, target)
            assert cw is not None, (start, target, state)
            state, previous = apply_controlword(state, cw, previous), cw
            steps += 1
            assert steps < 6, (start, target)


def test_fault_reset_needs_rising_edge():
    assert apply_controlword(State.FAULT, 0x0080, previous_cw=0x0080) == State.FAULT
    assert apply_controlword(State.FAULT, 0x0080, previous_cw=0x0000) == State.SWITCH_ON_DISABLED
    assert apply_controlword(State.FAULT, 0x000F) == State.FAULT


@pytest.mark.parametrize("state, cw, after", [
    (State.SWITCH_ON_DISABLED, 0x000F, State.SWITCH_ON_DISABLED),
    (State.SWITCH_ON_DISABLED, 0x0007, State.SWITCH_ON_DISABLED),
    (State.READY_TO_SWITCH_ON, 0x000F, State.OPERATION_ENABLED),  # 3 + 4
    (State.READY_TO_SWITCH_ON, 0x0002, State.SWITCH_ON_DISABLED),
    (State.SWITCHED_ON, 0x0002, State.SWITCH_ON_DISABLED),
    (State.OPERATION_ENABLED, 0x0006, State.READY_TO_SWITCH_ON),
    (State.OPERATION_ENABLED, 0x000B, State.QUICK_STOP_ACTIVE),
    (State.OPERATION_ENABLED, 0x001F, State.OPERATION_ENABLED),  # mode bits ignored
    (State.OPERATION_ENABLED, 0x008F, State.OPERATION_ENABLED),  # bit 7 set: no command
    (State.QUICK_STOP_ACTIVE, 0x000F, State.QUICK_STOP_ACTIVE),
    (State.QUICK_STOP_ACTIVE, 0x0000, State.SWITCH_ON_DISABLED),
    (State.FAULT_REACTION_ACTIVE, 0x0080, State.FAULT_REACTION_ACTIVE),
    (State.NOT_READY_TO_SWITCH_ON, 0x0006, State.NOT_READY_TO_SWITCH_ON),
])
def test_drive_side_transitions(state, cw, after):
    assert apply_controlword(state, cw) == after


def test_quick_stop_option_5_allows_enable_operation():
    assert apply_controlword(State.QUICK_STOP_ACTIVE, 0x000F, quick_stop_option_code=6) == State.OPERATION_ENABLED


def test_operation_modes():
    assert [int(m) for m in cia402.OperationMode] == [1, 3, 6, 8, 9, 10]
    assert cia402.mode_name(8) == "cyclic_sync_position"
    assert cia402.mode_name(0) == "no_mode"
    assert cia402.mode_name(-1) == "unknown_mode_-1"


@pytest.mark.parametrize("code", [5, 6, 7, 8])
def test_quick_stop_options_5_to_8_leave_quick_stop_powered(code):
    """Transition 16: enable operation, never disable voltage, out of Quick
    Stop Active to Operation Enabled and to every state beyond it."""
    assert next_controlword(State.QUICK_STOP_ACTIVE, State.OPERATION_ENABLED, code) == 0x000F
    assert next_controlword(State.QUICK_STOP_ACTIVE, State.SWITCHED_ON, code) == 0x000F
    assert next_controlword(State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED, code) == 0x0000


@pytest.mark.parametrize("code", [0, 1, 2, 3, 4])
def test_quick_stop_options_0_to_4_wait_for_the_drive(code):
    """The drive ends its ramp in Switch On Disabled by itself: no command
    (disable voltage would let a moving drive coast)."""
    for target in (State.OPERATION_ENABLED, State.SWITCHED_ON, State.SWITCH_ON_DISABLED):
        assert next_controlword(State.QUICK_STOP_ACTIVE, target, code) is None
    # and from there on the walk is the usual one
    assert next_controlword(State.SWITCH_ON_DISABLED, State.OPERATION_ENABLED, code) == 0x0006


@pytest.mark.parametrize("code", [None, 1, 2, 5, 6])
def test_every_planned_path_arrives_with_each_quick_stop_option(code):
    targets = [State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON, State.SWITCHED_ON,
               State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE]
    for start, target in itertools.product(targets + [State.FAULT], targets):
        state, previous, steps = start, 0, 0
        while state != target:
            cw = next_controlword(state, target, code)
            if cw is None:  # options 0-4: the drive's own transition 12
                assert state == State.QUICK_STOP_ACTIVE and code is not None and code <= 4
                state = State.SWITCH_ON_DISABLED
                continue
            after = apply_controlword(state, cw, previous, 2 if code is None else code)
            assert after != state, (start, target, state, cw)
            state, previous = after, cw
            steps += 1
            assert steps < 6, (start, target)
