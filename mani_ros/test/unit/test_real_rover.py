"""The real rover's protocol (docs/mani_protocol.md): what the rover's own
on-board code sends and reads, checked on python-can's virtual bus with the
package's config/mani.yaml (the real rover's figures)."""
import itertools
import math
import struct

import can
import pytest

from mani_ros import protocol as p
from mani_ros.can_link import CanLink
from mani_ros.config import WHEELS, load_config
from mani_ros.kinematics import MODE_ACKERMANN, MODE_VECTOR, Kinematics
from mani_ros.odometry import WheelOdometry

CONFIG = load_config()
_channels = itertools.count()


@pytest.fixture
def link_and_peer(request):
    channel = "mani_real_%s_%d" % (request.node.name, next(_channels))
    peer = can.Bus(interface="virtual", channel=channel)
    link = CanLink(channel, "virtual", command_data_length=CONFIG.can.command_data_length)
    yield link, peer
    link.shutdown()
    peer.shutdown()


def test_the_package_configuration_holds_the_real_rovers_figures():
    assert CONFIG.rover.wheel_base == 0.436
    assert CONFIG.rover.track == 0.4467
    assert 2.0 * CONFIG.rover.wheel_radius == pytest.approx(0.13677, abs=1e-12)
    assert CONFIG.DRIVE_ENC_PPR == CONFIG.STEER_ENC_PPR == 8384
    assert CONFIG.MAX_VEL == pytest.approx(math.pi)
    assert CONFIG.steering.max_angle == pytest.approx(math.pi / 2)
    assert CONFIG.steering.min_angle == pytest.approx(-math.pi / 2)
    assert CONFIG.can.bitrate == 500000
    assert CONFIG.can.command_data_length == 2
    assert CONFIG.power.max_current == {"battery": 25.0, "front_left": 12.0, "rear_left": 12.0,
                                        "rear_right": 12.0, "front_right": 12.0}


def test_straight_ahead_is_a_quarter_of_the_steering_encoder():
    k = Kinematics(CONFIG)
    for wheel in WHEELS:
        assert k.angle_to_pulses(wheel, 0.0) == 2096
        assert k.angle_to_pulses(wheel, math.pi / 2) == 4192
        assert k.angle_to_pulses(wheel, -math.pi / 2) == 0
        assert k.pulses_to_angle(wheel, 2096) == pytest.approx(0.0)
        assert k.pulses_to_angle(wheel, 0) == pytest.approx(-math.pi / 2)


def test_velocity_is_wheel_rate_over_two_pi_times_ppr_within_max_vel():
    k = Kinematics(CONFIG)
    omega = 0.2 / CONFIG.rover.wheel_radius
    assert k.speed_to_pps(0.2) == int(round(omega / (2 * math.pi) * 8384)) == 3902
    # max_vel pi rad/s = half a revolution a second
    assert k.speed_to_pps(10.0) == 4192 and k.speed_to_pps(-10.0) == -4192
    assert CONFIG.max_wheel_speed == pytest.approx(math.pi * 0.13677 / 2)


def test_straight_cmd_vel_frames_carry_one_int16_each(link_and_peer):
    link, peer = link_and_peer
    k = Kinematics(CONFIG)
    command = k.body_to_wheels(0.2, 0.0, 0.0, MODE_ACKERMANN)
    for message in k.command_messages(command):
        link.send(message)
    frames = [peer.recv(timeout=1.0) for _ in range(8)]
    orientation = [f for f in frames if f.arbitration_id & 0xFF0 == 0x0B0]
    velocity = [f for f in frames if f.arbitration_id & 0xFF0 == 0x0C0]
    assert sorted(f.arbitration_id for f in orientation) == [0x0B1, 0x0B2, 0x0B3, 0x0B4]
    assert sorted(f.arbitration_id for f in velocity) == [0x0C1, 0x0C2, 0x0C3, 0x0C4]
    for f in orientation:
        assert f.dlc == 2 and struct.unpack("<h", f.data)[0] == 2096
    for f in velocity:
        assert f.dlc == 2 and abs(struct.unpack("<h", f.data)[0]) == 3902


def test_the_seed_tables_four_byte_commands_remain_a_switch():
    assert p.encode(p.OrientationCmd(1, 2096), command_data_length=4) == (0x0B1, b"\x30\x08\x00\x00")
    assert p.encode(p.VelocityCmd(2, -3902), command_data_length=4)[1] == struct.pack("<h", -3902) + b"\0\0"
    assert p.encode(p.OrientationCmd(1, 2096)) == (0x0B1, b"\x30\x08")
    with pytest.raises(ValueError, match="command data length must be 2 or 4"):
        p.encode(p.VelocityCmd(1, 0), command_data_length=3)
    # both lengths decode, whoever sent them
    assert p.decode(0x0C3, struct.pack("<h", 3902)) == p.VelocityCmd(3, 3902)
    assert p.decode(0x0C3, struct.pack("<h", 3902) + b"\0\0") == p.VelocityCmd(3, 3902)


def original_odometry_frame(node_id, orientation, velocity, pulses, revolutions):
    """odometryFb as a drive node puts it on the bus: four int16 in a row."""
    return can.Message(arbitration_id=0x0E0 | node_id, is_extended_id=False,
                       data=struct.pack("<hhhh", orientation, velocity, pulses, revolutions))


def feed(odometry, frames, stamp):
    state = None
    for frame in frames:
        result = odometry.update(p.decode_can_message(frame), stamp)
        state = result or state
    return state


@pytest.mark.parametrize("orientation, expect", [
    (2096, (1.0, 0.0)),       # straight ahead
    (4192, (0.0, 1.0)),       # every wheel 90 deg to the left: crab left
    (0, (0.0, -1.0)),         # 90 deg to the right
])
def test_odometry_frames_in_the_original_encoding_integrate_to_the_pose(orientation, expect):
    odometry = WheelOdometry(CONFIG)
    feed(odometry, [original_odometry_frame(n, orientation, 0, 0, 0) for n in p.DRIVE_NODES], 0.0)
    # one metre: (pulses / PPR + revolutions) * pi * diameter, in 100 steps
    per_metre = 8384 / (math.pi * 0.13677)
    state = None
    for step in range(1, 101):
        count = int(round(step / 100.0 * per_metre))
        revolutions, pulses = divmod(count, 8384)
        frames = [original_odometry_frame(n, orientation, 500, pulses, revolutions)
                  for n in p.DRIVE_NODES]
        state = feed(odometry, frames, step * 0.05) or state
    assert state.x == pytest.approx(expect[0], abs=1e-3)
    assert state.y == pytest.approx(expect[1], abs=1e-3)
    assert state.yaw == pytest.approx(0.0, abs=1e-6)


def test_odometry_has_a_zero_pose_before_the_first_feedback():
    state = WheelOdometry(CONFIG).current(12.5)
    assert (state.x, state.y, state.yaw, state.vx, state.vy, state.wz) == (0, 0, 0, 0, 0, 0)
    assert state.stamp == 12.5


@pytest.mark.parametrize("index, value, sensor, amperes", [
    (0, 16384, "battery", 12.5),
    (0, 32768, "battery", 25.0),
    (1, 32768, "front_left", 12.0),
    (2, -8192, "rear_left", -3.0),
    (3, 0, "rear_right", 0.0),
    (4, 24576, "front_right", 9.0),
])
def test_current_feedback_is_normalised_to_the_sensors_maximum(index, value, sensor, amperes):
    frame = can.Message(arbitration_id=0x0E0, is_extended_id=False,
                        data=struct.pack("<ii", index, value))
    message = p.decode_can_message(frame)
    assert message.sensor == sensor
    assert message.amperes(CONFIG.power.max_current) == pytest.approx(amperes)


def test_five_current_sensors_battery_first_one_byte_each():
    assert p.EPS_SENSORS == ("battery", "front_left", "rear_left", "rear_right", "front_right")
    assert p.encode(p.ErrorWrn(battery=True)) == (0x010, b"\x01\0\0\0\0")
    assert p.decode(0x020, b"\0\0\0\0\x01") == p.CurrentWrn(front_right=True)
    with pytest.raises(p.ProtocolError, match="sensor_index = 5 is out of range"):
        p.decode(0x0E0, struct.pack("<ii", 5, 0))
    with pytest.raises(p.ProtocolError, match="out of range"):
        p.decode(0x0E0, struct.pack("<ii", 0, 40000))


def test_the_original_move_control_is_a_rigid_body_motion():
    k = Kinematics(CONFIG)
    # x and rz together: a turn about a centre on the lateral axis
    command = k.body_to_wheels(0.1, 0.0, 0.3, MODE_VECTOR)
    assert command.limited == ()
    vx, vy, wz, slip = k.wheels_to_body(
        {w: (c.speed * math.cos(c.angle), c.speed * math.sin(c.angle))
         for w, c in command.wheels.items()})
    assert (vx, vy, wz) == pytest.approx((0.1, 0.0, 0.3))
    # x, y and rz at once, which no other mode takes
    command = k.body_to_wheels(0.05, 0.04, 0.2, MODE_VECTOR)
    vx, vy, wz, _ = k.wheels_to_body(
        {w: (c.speed * math.cos(c.angle), c.speed * math.sin(c.angle))
         for w, c in command.wheels.items()})
    assert (vx, vy, wz) == pytest.approx((0.05, 0.04, 0.2))
    for c in command.wheels.values():
        assert -math.pi / 2 - 1e-9 <= c.angle <= math.pi / 2 + 1e-9


@pytest.mark.parametrize("length, data", [(2, "3e0f"), (4, "3e0f0000")])
def test_a_nodes_can_link_sends_the_configured_command_data_length(length, data):
    channel = "mani_real_length_%d_%d" % (length, next(_channels))
    peer = can.Bus(interface="virtual", channel=channel)
    link = CanLink(channel, "virtual", command_data_length=length)
    try:
        link.send(p.VelocityCmd(p.REAR_RIGHT, 3902))
        frame = peer.recv(timeout=1.0)
        assert (frame.arbitration_id, frame.dlc, bytes(frame.data).hex()) == (0x0C3, length, data)
    finally:
        link.shutdown()
        peer.shutdown()


def test_a_can_link_refuses_another_command_data_length():
    with pytest.raises(ValueError, match="command data length must be 2 or 4, got 3"):
        CanLink("unused", "virtual", command_data_length=3)
