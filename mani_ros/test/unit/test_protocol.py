"""The MANI CAN codec: the bytes on the wire, round trips, and the reasons
given for frames that are not MANI protocol (docs/mani_protocol.md)."""
import os
import random
import re

import can
import pytest

from mani_ros import protocol as p


def frame(message):
    can_id, data = p.encode(message)
    return can_id, data.hex()


# Exact frames a firmware author would put on the bus (little-endian int16).
@pytest.mark.parametrize("message, can_id, data", [
    (p.PowerCmd(True), 0x000, "01"),
    (p.PowerCmd(False), 0x000, "00"),
    (p.PowerFb(True), 0x030, "01"),
    (p.ErrorWrn(battery=True), 0x010, "0100000000"),
    (p.ErrorWrn(front_left=True), 0x010, "0001000000"),
    (p.ErrorWrn(front_left=True, front_right=True), 0x010, "0001000001"),
    (p.CurrentWrn(True, True, True, True, True), 0x020, "0101010101"),
    (p.CurrentWrn(rear_left=True), 0x020, "0000010000"),
    (p.CurrentWrn(rear_right=True), 0x020, "0000000100"),
    (p.CurrentFb(2, 1500), 0x0E0, "02000000dc050000"),
    (p.CurrentFb(0, -32768), 0x0E0, "000000000080ffff"),
    (p.CurrentFb(4, 32768), 0x0E0, "0400000000800000"),
    (p.SwitchCmd(p.FRONT_LEFT, steer_mode=True), 0x0A1, "01000000"),
    (p.SwitchCmd(p.FRONT_RIGHT, zero_encoders=True), 0x0A4, "00000001"),
    (p.SwitchCmd(p.REAR_LEFT, False, True, True, False), 0x0A2, "00010100"),
    (p.OrientationCmd(p.REAR_RIGHT, 1000), 0x0B3, "e803"),
    (p.OrientationCmd(p.FRONT_LEFT, -1), 0x0B1, "ffff"),
    (p.VelocityCmd(p.REAR_LEFT, -32768), 0x0C2, "0080"),
    (p.VelocityCmd(p.FRONT_RIGHT, 32767), 0x0C4, "ff7f"),
    (p.LocomotionFb(p.REAR_RIGHT, True), 0x0D3, "01"),
    (p.OdometryFb(p.FRONT_LEFT, 256, -2, 32767, -32768), 0x0E1, "0001feffff7f0080"),
])
def test_frames_on_the_wire(message, can_id, data):
    assert frame(message) == (can_id, data)
    assert p.decode(can_id, bytes.fromhex(data)) == message


EDGES = (-32768, -1, 0, 1, 32767)


def all_messages():
    yield p.PowerCmd(False)
    yield p.PowerCmd(True)
    yield p.PowerFb(False)
    yield p.PowerFb(True)
    for bits in range(32):
        flags = [bool(bits & (1 << i)) for i in range(5)]
        yield p.ErrorWrn(*flags)
        yield p.CurrentWrn(*flags)
    for index in range(5):
        for current in (-32768, 0, 1, 16384, 32768):
            yield p.CurrentFb(index, current)
    for node in p.DRIVE_NODES:
        for bits in range(16):
            yield p.SwitchCmd(node, *[bool(bits & (1 << i)) for i in range(4)])
        for value in EDGES:
            yield p.OrientationCmd(node, value)
            yield p.VelocityCmd(node, value)
            yield p.OdometryFb(node, value, -value if value > -32768 else 0, value, value)
        yield p.LocomotionFb(node, False)
        yield p.LocomotionFb(node, True)
        yield p.OdometryFb(node, -32768, 32767, -32768, 32767)


def test_every_message_round_trips_through_a_can_frame():
    count = 0
    for message in all_messages():
        can_frame = p.to_can_message(message)
        assert not can_frame.is_extended_id
        assert can_frame.arbitration_id == p.arbitration_id(message)
        assert p.decode_can_message(can_frame) == message
        count += 1
    assert count == 229


def test_every_id_of_the_table_decodes_and_nothing_else_does():
    known = {0x000, 0x010, 0x020, 0x030, 0x0E0}
    for base in (0x0A0, 0x0B0, 0x0C0, 0x0D0, 0x0E0):
        known.update(base | node for node in (1, 2, 3, 4))
    lengths = {0x000: 1, 0x010: 5, 0x020: 5, 0x030: 1, 0x0A: 4, 0x0B: 2, 0x0C: 2, 0x0D: 1, 0x0E: 8}
    for can_id in range(0x800):
        length = lengths.get(can_id, lengths.get(can_id >> 4, 8))
        if can_id in known:
            p.decode(can_id, bytes(length))
        else:
            with pytest.raises(p.ProtocolError, match="0x%03X is not a MANI message" % can_id):
                p.decode(can_id, bytes(length))


def test_current_fb_and_odometry_fb_share_the_0x0e_range_by_node_number():
    assert isinstance(p.decode(0x0E0, bytes(8)), p.CurrentFb)
    for node in p.DRIVE_NODES:
        assert p.decode(0x0E0 | node, bytes(8)) == p.OdometryFb(node, 0, 0, 0, 0)


def test_orientation_and_velocity_commands_accept_four_byte_frames_too():
    assert p.decode(0x0B1, bytes.fromhex("3412")) == p.OrientationCmd(1, 0x1234)
    assert p.decode(0x0C4, bytes.fromhex("feff")) == p.VelocityCmd(4, -2)
    # the reserved bytes 3-4 are not part of the value
    assert p.decode(0x0C4, bytes.fromhex("feffaabb")) == p.VelocityCmd(4, -2)


@pytest.mark.parametrize("can_id, data, reason", [
    (0x000, "", "powerCmd needs 1 data bytes, got 0"),
    (0x000, "0100", "powerCmd needs 1 data bytes, got 2"),
    (0x000, "02", "powerCmd byte 1 must be 0 or 1, got 0x02"),
    (0x030, "ff", "powerFb byte 1 must be 0 or 1, got 0xFF"),
    (0x010, "00000000", "errorWrn needs 5 data bytes, got 4"),
    (0x010, "000000000000", "errorWrn needs 5 data bytes, got 6"),
    (0x010, "0200000000", "errorWrn byte 1 must be 0 or 1, got 0x02"),
    (0x020, "0000020000", "currentWrn byte 3 must be 0 or 1, got 0x02"),
    (0x0E0, "00000000", "currentFb needs 8 data bytes, got 4"),
    (0x0E0, "0500000000000000", r"CurrentFb.sensor_index = 5 is out of range \[0, 4\]"),
    (0x0E0, "0000000001800000", r"CurrentFb.current = 32769 is out of range \[-32768, 32768\]"),
    (0x0E0, "00000000ff7fffff", r"CurrentFb.current = -32769 is out of range"),
    (0x0A1, "010101", "switchCmd needs 4 data bytes, got 3"),
    (0x0A2, "01010103", "switchCmd byte 4 must be 0 or 1, got 0x03"),
    (0x0B1, "01", "orientationCmd needs 2 or 4 data bytes, got 1"),
    (0x0B1, "010203", "orientationCmd needs 2 or 4 data bytes, got 3"),
    (0x0C3, "0102030405", "velocityCmd needs 2 or 4 data bytes, got 5"),
    (0x0D4, "", "locomotionFb needs 1 data bytes, got 0"),
    (0x0D4, "07", "locomotionFb byte 1 must be 0 or 1, got 0x07"),
    (0x0E2, "00000000000000", "odometryFb needs 8 data bytes, got 7"),
    (0x0A0, "00000000", "0x0A0 is not a MANI message"),
    (0x0B5, "0000", "0x0B5 is not a MANI message"),
    (0x0E5, bytes(8).hex(), "0x0E5 is not a MANI message"),
    (0x800, "", "not an 11-bit CAN id"),
    (-1, "", "not an 11-bit CAN id"),
])
def test_bad_frames_are_rejected_with_the_reason(can_id, data, reason):
    with pytest.raises(p.ProtocolError, match=reason):
        p.decode(can_id, bytes.fromhex(data))


def test_protocol_error_is_a_value_error():
    assert issubclass(p.ProtocolError, ValueError)


@pytest.mark.parametrize("make, reason", [
    (lambda: p.OrientationCmd(1, 32768), r"OrientationCmd.orientation = 32768 is out of range \[-32768, 32767\]"),
    (lambda: p.VelocityCmd(2, -32769), r"VelocityCmd.velocity = -32769 is out of range"),
    (lambda: p.VelocityCmd(2, 10.5), "VelocityCmd.velocity must be an integer, got 10.5"),
    (lambda: p.VelocityCmd(2, True), "must be an integer, got True"),
    (lambda: p.OdometryFb(3, 0, 0, 40000, 0), "OdometryFb.pulses = 40000 is out of range"),
    (lambda: p.OrientationCmd(0, 0), "node_id must be a drive node 1..4"),
    (lambda: p.SwitchCmd(5), "node_id must be a drive node 1..4"),
    (lambda: p.LocomotionFb(1.0, True), "node_id must be a drive node 1..4"),
    (lambda: p.PowerCmd(2), r"PowerCmd.motor_power must be a boolean \(0 or 1\), got 2"),
    (lambda: p.ErrorWrn(front_left="yes"), "ErrorWrn.front_left must be a boolean"),
    (lambda: p.CurrentFb(-1, 0), "CurrentFb.sensor_index = -1 is out of range"),
    (lambda: p.CurrentFb(0, 32769), "CurrentFb.current = 32769 is out of range"),
])
def test_out_of_range_messages_cannot_be_built(make, reason):
    with pytest.raises(p.ProtocolError, match=reason):
        make()


def test_encode_refuses_what_is_not_a_mani_message():
    with pytest.raises(p.ProtocolError, match="not a MANI message"):
        p.encode("powerCmd on")


def test_booleans_given_as_0_1_become_bool():
    assert p.SwitchCmd(1, 1, 0, 1, 0) == p.SwitchCmd(1, True, False, True, False)
    assert p.encode(p.PowerCmd(1)) == (0, b"\x01")


def test_warning_flags_name_the_active_sensors():
    warning = p.decode(0x010, bytes.fromhex("0101000001"))
    assert warning.active() == ("battery", "front_left", "front_right")
    assert p.CurrentFb(3, 10).sensor == "rear_right"


def test_frames_that_are_not_data_frames_are_refused():
    with pytest.raises(p.ProtocolError, match="extended id"):
        p.decode_can_message(can.Message(arbitration_id=0x0E1, data=bytes(8), is_extended_id=True))
    with pytest.raises(p.ProtocolError, match="remote frame 0x0D1"):
        p.decode_can_message(can.Message(arbitration_id=0x0D1, is_remote_frame=True,
                                         is_extended_id=False, dlc=1))
    with pytest.raises(p.ProtocolError, match="error frame"):
        p.decode_can_message(can.Message(is_error_frame=True))


def test_thousands_of_random_frames_decode_or_raise_protocol_error_only():
    rng = random.Random(6)
    decoded = 0
    for _ in range(20000):
        can_id = rng.choice([rng.randrange(0x800), rng.randrange(0x0F0)])
        data = bytes(rng.randrange(256) for _ in range(rng.randrange(9)))
        try:
            message = p.decode(can_id, data)
        except p.ProtocolError:
            continue
        decoded += 1
        # whatever decodes encodes back to the same id and value bytes
        again_id, again = p.encode(message)
        assert again_id == can_id
        assert p.decode(again_id, again) == message
    assert decoded > 100


def test_describe_names_the_message_and_the_wheel():
    assert p.describe(p.LocomotionFb(2, True)) == "locomotionFb[rear_left] task_completed=True"
    assert p.describe(p.PowerFb(False)) == "powerFb motor_power=False"


def test_the_candump_example_of_the_specification_decodes_as_described():
    spec = os.path.join(os.path.dirname(__file__), "..", "..", "..", "docs", "mani_protocol.md")
    with open(spec) as stream:
        lines = re.findall(r"^    can0  ([0-9A-F]{3})   \[(\d)\]  ((?:[0-9A-F]{2} ?)+)", stream.read(), re.M)
    messages = [p.decode(int(can_id, 16), bytes.fromhex(data)) for can_id, length, data in lines]
    assert [len(bytes.fromhex(data)) for _, _, data in lines] == [int(n) for _, n, _ in lines]
    assert messages == [
        p.PowerCmd(True), p.PowerFb(True), p.SwitchCmd(1, True, True, True, False),
        p.OrientationCmd(1, 2096), p.VelocityCmd(1, 3902), p.LocomotionFb(1, True),
        p.OdometryFb(1, 2096, 3902, 300, 5), p.ErrorWrn(front_left=True),
        p.CurrentFb(0, 16384)]
