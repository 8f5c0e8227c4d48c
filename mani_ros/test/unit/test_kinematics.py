"""Four-wheel steering kinematics: the wheel angles and speeds obey the rover's
geometry (one common turn centre), stay within MAX_VEL and the steering
limits, and become the right set points in encoder pulses."""
import dataclasses
import math

import pytest

from mani_ros import protocol as p
from mani_ros.config import WHEELS, config_from_dict, load_config
from mani_ros.kinematics import (MODE_ACKERMANN, MODE_CRAB, MODE_FRONT_ACKERMANN, MODE_POINT_TURN,
                                 Kinematics, KinematicsError)

# The real rover's geometry and encoders with a faster MAX_VEL (20 rad/s,
# 26,687 pulses/s, still an int16), so the scenarios below may drive at
# up to 1 m/s.
CONFIG = dataclasses.replace(load_config(), MAX_VEL=20.0)
L, W = CONFIG.rover.wheel_base, CONFIG.rover.track
PULSES_PER_METRE = CONFIG.DRIVE_ENC_PPR / (2 * math.pi * CONFIG.rover.wheel_radius)


def kinematics(**changes):
    if not changes:
        return Kinematics(CONFIG)
    import yaml
    with open(CONFIG.source) as stream:
        data = yaml.safe_load(stream)
    data["MAX_VEL"] = CONFIG.MAX_VEL
    for path, value in changes.items():
        section, key = path.split("__")
        data[section][key] = value
    return Kinematics(config_from_dict(data))


def assert_turn_centre(command, centre, wz):
    """Each wheel rolls perpendicular to the line from the turn centre and as
    fast as wz times its distance from it."""
    for wheel, (x, y) in CONFIG.wheel_positions().items():
        c = command.wheels[wheel]
        rx, ry = x - centre[0], y - centre[1]
        direction = (math.cos(c.angle), math.sin(c.angle))
        assert direction[0] * rx + direction[1] * ry == pytest.approx(0.0, abs=1e-9), wheel
        velocity = (c.speed * direction[0], c.speed * direction[1])
        assert velocity[0] == pytest.approx(-wz * ry, abs=1e-9), wheel
        assert velocity[1] == pytest.approx(wz * rx, abs=1e-9), wheel


def test_straight_ahead_and_back():
    k = kinematics()
    for vx in (0.5, -0.3):
        command = k.body_to_wheels(vx, 0.0, 0.0, MODE_ACKERMANN)
        assert command.limited == ()
        for c in command.wheels.values():
            assert c.angle == pytest.approx(0.0, abs=1e-12) and c.speed == pytest.approx(vx)
        for orientation, velocity in k.set_points(command).values():
            # straight ahead is a quarter turn of the steering encoder
            assert orientation == CONFIG.STEER_ENC_PPR // 4 == 2096
            assert velocity == round(vx * PULSES_PER_METRE)


def test_double_ackermann_turn_has_its_centre_on_the_lateral_axis():
    k = kinematics()
    vx, wz = 0.5, 0.8
    command = k.body_to_wheels(vx, 0.0, wz, MODE_ACKERMANN)
    assert command.limited == ()
    assert_turn_centre(command, (0.0, vx / wz), wz)
    w = command.wheels
    # front and rear steer opposite; the inner (left) wheels steer more and roll slower
    assert w["front_left"].angle == pytest.approx(-w["rear_left"].angle)
    assert w["front_right"].angle == pytest.approx(-w["rear_right"].angle)
    assert w["front_left"].angle > w["front_right"].angle > 0
    assert 0 < w["front_left"].speed < w["front_right"].speed
    # inner front wheel: tan(angle) = (L/2) / (R - W/2)
    assert math.tan(w["front_left"].angle) == pytest.approx((L / 2) / (vx / wz - W / 2))


def test_the_same_arc_backwards_reverses_only_the_speeds():
    k = kinematics()
    forwards = k.body_to_wheels(0.4, 0.0, 0.5, MODE_ACKERMANN).wheels
    backwards = k.body_to_wheels(-0.4, 0.0, -0.5, MODE_ACKERMANN).wheels
    for wheel in WHEELS:
        assert backwards[wheel].angle == pytest.approx(forwards[wheel].angle)
        assert backwards[wheel].speed == pytest.approx(-forwards[wheel].speed)


def test_front_ackermann_keeps_the_rear_wheels_straight():
    k = kinematics()
    vx, wz = 0.5, 0.6
    command = k.body_to_wheels(vx, 0.0, wz, MODE_FRONT_ACKERMANN)
    assert command.wheels["rear_left"].angle == 0.0 and command.wheels["rear_right"].angle == 0.0
    assert_turn_centre(command, (-L / 2, vx / wz), wz)


def test_point_turn_rolls_every_wheel_round_the_centre():
    k = kinematics()
    wz = 0.7
    command = k.body_to_wheels(0.3, 0.2, wz, MODE_POINT_TURN)   # point turn ignores vx, vy
    assert_turn_centre(command, (0.0, 0.0), wz)
    radius = math.hypot(L / 2, W / 2)
    for c in command.wheels.values():
        assert abs(c.speed) == pytest.approx(wz * radius)
    # counter-clockwise: the left wheels roll backward, the right ones forward
    # (with the angles folded into the steering range)
    assert command.wheels["front_left"].speed < 0 < command.wheels["front_right"].speed


def test_point_turn_without_rotation_still_sets_the_wheels():
    command = kinematics().body_to_wheels(0.0, 0.0, 0.0, MODE_POINT_TURN)
    expected = math.atan2(L / 2, W / 2)
    assert command.wheels["front_right"].angle == pytest.approx(expected)
    assert command.wheels["front_left"].angle == pytest.approx(-expected)
    assert all(c.speed == 0.0 for c in command.wheels.values())


def test_crab_drives_all_wheels_parallel():
    command = kinematics().body_to_wheels(0.3, -0.3, 1.0, MODE_CRAB)   # crab ignores wz
    for c in command.wheels.values():
        assert c.angle == pytest.approx(-math.pi / 4)
        assert c.speed == pytest.approx(math.hypot(0.3, 0.3))


def test_speeds_are_scaled_together_to_max_vel():
    k = kinematics()
    slow = k.body_to_wheels(0.2, 0.0, 0.5, MODE_ACKERMANN)
    fast = k.body_to_wheels(2.0, 0.0, 5.0, MODE_ACKERMANN)
    assert fast.limited and "MAX_VEL" in fast.limited[0]
    top = max(abs(c.speed) for c in fast.wheels.values())
    assert top == pytest.approx(CONFIG.max_wheel_speed)
    for wheel in WHEELS:   # same curvature: same angles, same speed ratios
        assert fast.wheels[wheel].angle == pytest.approx(slow.wheels[wheel].angle)
        assert fast.wheels[wheel].speed / top == pytest.approx(
            slow.wheels[wheel].speed / max(abs(c.speed) for c in slow.wheels.values()))
    assert max(abs(v) for _, v in k.set_points(fast).values()) == CONFIG.max_velocity_pulses


def test_tight_steering_limits_reduce_the_turn_rate_not_the_geometry():
    k = kinematics(steering__min_angle=-0.4, steering__max_angle=0.4)
    vx = 0.5
    command = k.body_to_wheels(vx, 0.0, 3.0, MODE_ACKERMANN)
    assert any("turn rate reduced" in reason for reason in command.limited)
    angles = [c.angle for c in command.wheels.values()]
    assert max(abs(a) for a in angles) == pytest.approx(0.4, abs=1e-6)
    # still one turn centre on the lateral axis: recover wz from the inner wheel
    inner = command.wheels["front_left"]
    radius = (L / 2) / math.tan(inner.angle) + W / 2
    assert_turn_centre(command, (0.0, radius), vx / radius)


def test_point_turn_beyond_the_steering_limits_is_refused():
    k = kinematics(steering__min_angle=-0.4, steering__max_angle=0.4)
    with pytest.raises(KinematicsError, match="point turn needs a steering angle .* outside the steering limits"):
        k.body_to_wheels(0.0, 0.0, 1.0, MODE_POINT_TURN)


def test_crab_beyond_the_limits_reduces_the_sideways_part():
    k = kinematics(steering__min_angle=-0.4, steering__max_angle=0.4)
    command = k.body_to_wheels(0.3, 0.3, 0.0, MODE_CRAB)
    assert any("sideways" in reason for reason in command.limited)
    assert all(c.angle == pytest.approx(0.4, abs=1e-6) for c in command.wheels.values())


def test_a_stopped_wheel_keeps_its_angle():
    previous = {"front_left": 0.3, "rear_left": -0.3, "rear_right": 0.1, "front_right": 0.2}
    command = kinematics().body_to_wheels(0.0, 0.0, 0.0, MODE_ACKERMANN, previous)
    assert {w: c.angle for w, c in command.wheels.items()} == previous
    assert all(c.speed == 0.0 for c in command.wheels.values())


def test_of_two_equivalent_angles_the_nearer_one_is_chosen():
    k = kinematics(steering__min_angle=-1.745, steering__max_angle=1.745)   # +-100 deg
    # turn centre 0.25 m left of base_link: the inner front wheel needs 83 deg,
    # or the equivalent -97 deg rolling backwards; both are within the limits
    ahead = k.body_to_wheels(0.25, 0.0, 1.0, MODE_ACKERMANN).wheels["front_left"]
    assert ahead.angle == pytest.approx(math.atan2(L / 2, 0.25 - W / 2))
    flipped = k.body_to_wheels(0.25, 0.0, 1.0, MODE_ACKERMANN,
                               {"front_left": -1.7}).wheels["front_left"]
    assert flipped.angle == pytest.approx(ahead.angle - math.pi)
    assert flipped.speed == pytest.approx(-ahead.speed)


@pytest.mark.parametrize("mode", [MODE_ACKERMANN, MODE_FRONT_ACKERMANN, MODE_CRAB, MODE_POINT_TURN])
def test_wheels_to_body_recovers_the_command(mode):
    k = kinematics()
    vx, vy, wz = 0.3, (0.1 if mode == MODE_CRAB else 0.0), (0.0 if mode == MODE_CRAB else 0.4)
    command = k.body_to_wheels(vx, vy, wz, mode)
    vectors = {w: (c.speed * math.cos(c.angle), c.speed * math.sin(c.angle))
               for w, c in command.wheels.items()}
    fx, fy, fwz, residual = k.wheels_to_body(vectors)
    expected = {MODE_POINT_TURN: (0.0, 0.0, wz), MODE_FRONT_ACKERMANN: (vx, wz * L / 2, wz)}
    assert (fx, fy, fwz) == pytest.approx(expected.get(mode, (vx, vy, wz)), abs=1e-9)
    assert residual == pytest.approx(0.0, abs=1e-9)


def test_per_wheel_commands_are_checked():
    k = kinematics(steering__min_angle=-1.0, steering__max_angle=1.0)
    command = k.wheels_command([0.2, 3.0, 0.0, -0.1], [0.1, 0.1, 0.1, 0.1])
    # 3.0 rad is outside [-1, 1] but 3.0 - pi fits with the wheel reversed
    assert command.wheels["rear_left"].angle == pytest.approx(3.0 - math.pi)
    assert command.wheels["rear_left"].speed == pytest.approx(-0.1)
    with pytest.raises(KinematicsError, match="steering angle 1.500 rad of front_left is outside"):
        k.wheels_command([1.5, 0, 0, 0], [0, 0, 0, 0])
    with pytest.raises(KinematicsError, match="need 4 steering angles and 4 wheel speeds"):
        k.wheels_command([0, 0, 0], [0, 0, 0, 0])
    with pytest.raises(KinematicsError, match="wheel speed of rear_right must be a finite number"):
        k.wheels_command([0, 0, 0, 0], [0, 0, float("inf"), 0])
    fast = k.wheels_command([0, 0, 0, 0], [5.0, 2.5, 0, 0])
    assert fast.wheels["front_left"].speed == pytest.approx(CONFIG.max_wheel_speed)
    assert fast.wheels["rear_left"].speed == pytest.approx(CONFIG.max_wheel_speed / 2)


def test_bad_commands_are_refused():
    k = kinematics()
    with pytest.raises(KinematicsError, match="unknown steering mode 'skid'"):
        k.body_to_wheels(0.1, 0, 0, "skid")
    with pytest.raises(KinematicsError, match="wz must be a finite number"):
        k.body_to_wheels(0.1, 0, float("nan"))


def test_units_and_offsets():
    k = kinematics(steering__offsets={"front_left": 0.1, "rear_left": 0.0,
                                      "rear_right": 0.0, "front_right": -0.2})
    ppr = CONFIG.STEER_ENC_PPR
    assert k.angle_to_pulses("rear_left", math.pi / 2) == ppr // 4
    assert k.angle_to_pulses("front_left", 0.1) == 0          # the offset is pulse 0
    assert k.angle_to_pulses("front_right", 0.0) == round(0.2 * ppr / (2 * math.pi))
    assert k.pulses_to_angle("front_right", k.angle_to_pulses("front_right", 0.5)) == pytest.approx(0.5, abs=1e-3)
    assert k.speed_to_pps(1.0) == round(PULSES_PER_METRE)
    top = CONFIG.max_velocity_pulses
    assert k.speed_to_pps(100.0) == top and k.speed_to_pps(-100.0) == -top
    assert k.pps_to_speed(CONFIG.DRIVE_ENC_PPR) == pytest.approx(2 * math.pi * CONFIG.rover.wheel_radius)


def test_command_messages_address_every_drive_node():
    k = kinematics()
    messages = k.command_messages(k.body_to_wheels(0.5, 0.0, 0.8, MODE_ACKERMANN))
    frames = [p.encode(m) for m in messages]
    assert [can_id for can_id, _ in frames] == [0x0B1, 0x0C1, 0x0B2, 0x0C2, 0x0B3, 0x0C3, 0x0B4, 0x0C4]
    front_left = k.body_to_wheels(0.5, 0.0, 0.8, MODE_ACKERMANN).wheels["front_left"]
    offset = CONFIG.steering.offsets["front_left"]
    assert messages[0].orientation == round((front_left.angle - offset) * CONFIG.STEER_ENC_PPR / (2 * math.pi))
    assert messages[1].velocity == round(front_left.speed * PULSES_PER_METRE)
