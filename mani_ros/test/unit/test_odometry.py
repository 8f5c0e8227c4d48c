"""Wheel odometry from odometryFb: known wheel motions give the known pose,
a square path returns to its start, 16-bit counters wrap without a jump."""
import dataclasses
import math

import pytest

from mani_ros import protocol as p
from mani_ros.config import WHEELS, load_config
from mani_ros.kinematics import MODE_ACKERMANN, MODE_POINT_TURN, NODE_OF_WHEEL, Kinematics
from mani_ros.odometry import (UNOBSERVED_VARIANCE, WheelOdometry, counters_from_count, wrap16,
                               yaw_to_quaternion)

# The real rover's geometry and encoders with a faster MAX_VEL (20 rad/s,
# 26,687 pulses/s, still an int16), so the scenarios below may drive at
# up to 1 m/s.
CONFIG = dataclasses.replace(load_config(), MAX_VEL=20.0)
PPR = CONFIG.DRIVE_ENC_PPR


class Wheels:
    """Four drive nodes whose encoders follow a commanded motion exactly, and
    report odometryFb like the firmware (orientation, velocity, counters)."""

    def __init__(self, odometry, start_count=0, report=WHEELS):
        self.odometry = odometry
        self.kinematics = Kinematics(CONFIG)
        self.count = {wheel: float(start_count) for wheel in WHEELS}
        self.angle = {wheel: 0.0 for wheel in WHEELS}
        self.speed = {wheel: 0.0 for wheel in WHEELS}
        self.report = report
        self.time = 0.0
        self.state = None

    def feedback(self, wheel):
        pulses, revolutions = counters_from_count(int(round(self.count[wheel])), PPR)
        return p.OdometryFb(NODE_OF_WHEEL[wheel],
                            self.kinematics.angle_to_pulses(wheel, self.angle[wheel]),
                            self.kinematics.speed_to_pps(self.speed[wheel]), pulses, revolutions)

    def publish(self):
        for wheel in self.report:
            state = self.odometry.update(self.feedback(wheel), self.time)
            if state is not None:
                self.state = state

    def move(self, vx, vy, wz, mode, duration, period=0.02):
        command = self.kinematics.body_to_wheels(vx, vy, wz, mode, self.angle)
        assert command.limited == ()
        # steer first (standing), then roll
        for wheel, c in command.wheels.items():
            self.angle[wheel] = c.angle
        self.publish()
        steps = int(round(duration / period))
        for _ in range(steps):
            self.time += period
            for wheel, c in command.wheels.items():
                self.speed[wheel] = c.speed
                self.count[wheel] += c.speed * period / self.kinematics.metres_per_pulse
            self.publish()
        for wheel in WHEELS:
            self.speed[wheel] = 0.0
        self.publish()
        return self.state


def started(start_count=0):
    """Wheels that have sent their reference frames to a new WheelOdometry."""
    wheels = Wheels(WheelOdometry(CONFIG), start_count=start_count)
    wheels.publish()
    return wheels


def test_wrap16_takes_the_short_way_round():
    assert wrap16(-32768 - 32767) == 1
    assert wrap16(32767 - (-32768)) == -1
    assert wrap16(5 - 3) == 2 and wrap16(3 - 5) == -2
    assert wrap16(0x8000) == -32768


def test_counters_carry_pulses_into_revolutions_like_the_firmware():
    assert counters_from_count(2 * PPR + 5, PPR) == (5, 2)
    assert counters_from_count(-(2 * PPR + 5), PPR) == (-5, -2)
    assert counters_from_count(32768 * PPR + 7, PPR) == (7, -32768)   # revolutions wrapped


def test_the_first_frames_are_the_reference():
    wheels = started(12345)
    state = wheels.state
    assert (state.x, state.y, state.yaw) == (0.0, 0.0, 0.0)
    assert state.pose_covariance[0] == 0.0


def test_straight_metre_forward_and_back():
    wheels = started()
    state = wheels.move(0.5, 0.0, 0.0, MODE_ACKERMANN, 2.0)
    assert state.x == pytest.approx(1.0, abs=2e-3) and state.y == pytest.approx(0.0, abs=1e-9)
    state = wheels.move(-0.25, 0.0, 0.0, MODE_ACKERMANN, 2.0)
    assert state.x == pytest.approx(0.5, abs=2e-3)
    assert state.distance == pytest.approx(1.5, abs=4e-3)


def test_twist_is_the_wheels_velocity_and_covariance_grows_with_distance():
    wheels = started()
    wheels.move(0.4, 0.0, 0.0, MODE_ACKERMANN, 1.0)
    command = wheels.kinematics.body_to_wheels(0.4, 0.0, 0.0, MODE_ACKERMANN)
    for wheel, c in command.wheels.items():
        wheels.speed[wheel] = c.speed
    wheels.publish()
    state = wheels.state
    assert state.vx == pytest.approx(0.4, abs=1e-3) and state.wz == pytest.approx(0.0, abs=1e-9)
    assert state.pose_covariance[0] == pytest.approx(CONFIG.odometry.xy_variance_per_m * state.distance)
    assert state.pose_covariance[7] == state.pose_covariance[0]
    assert state.pose_covariance[14] == UNOBSERVED_VARIANCE
    assert state.twist_covariance[0] == pytest.approx(CONFIG.odometry.twist_variance_linear, rel=1e-3)


def test_quarter_circle_in_double_ackermann():
    wheels = started()
    radius, speed = 1.0, 0.5
    state = wheels.move(speed, 0.0, speed / radius, MODE_ACKERMANN, (math.pi / 2) * radius / speed,
                        period=0.01)
    # a quarter of a circle of 1 m round (0, 1): ends at (1, 1) facing +y
    assert state.x == pytest.approx(1.0, abs=0.01)
    assert state.y == pytest.approx(1.0, abs=0.01)
    assert state.yaw == pytest.approx(math.pi / 2, abs=0.01)


# Stated error of the square test: 1 m sides and point turns of 90 degrees
# bring the pose back within 1 cm and 0.2 degrees. The wheels do not slip
# here, so what remains is the quantisation of the steering encoder (4096
# pulses per turn) and of the drive encoder (measured: 0.1 mm, 0.001 deg).
SQUARE_POSITION_ERROR = 0.01
SQUARE_YAW_ERROR = math.radians(0.2)


@pytest.mark.parametrize("start_count", [0, 32760 * PPR])   # the second wraps revolutions
def test_square_path_returns_to_the_start(start_count):
    wheels = started(start_count)
    corners = []
    for _ in range(4):
        wheels.move(0.5, 0.0, 0.0, MODE_ACKERMANN, 2.0)
        state = wheels.move(0.0, 0.0, math.pi / 4, MODE_POINT_TURN, 2.0)
        corners.append((round(state.x, 1), round(state.y, 1)))
    assert corners == [(1.0, 0.0), (1.0, 1.0), (0.0, 1.0), (0.0, 0.0)]
    assert math.hypot(state.x, state.y) < SQUARE_POSITION_ERROR
    assert abs(math.atan2(math.sin(state.yaw), math.cos(state.yaw))) < SQUARE_YAW_ERROR
    assert state.distance == pytest.approx(4.0, abs=0.02)


def test_revolution_counter_wrap_is_no_jump():
    wheels = started(32767 * PPR - 10)
    state = wheels.move(0.5, 0.0, 0.0, MODE_ACKERMANN, 1.0)
    assert wheels.feedback("front_left").revolutions < 0   # the counter did wrap
    assert state.x == pytest.approx(0.5, abs=2e-3)


def test_pulse_counter_wrap_is_no_jump():
    # A drive whose pulse counter runs free past 32767 (revolutions unchanged)
    odometry = WheelOdometry(CONFIG)
    for pulses in (32700, -32700):
        for node in p.DRIVE_NODES:
            # orientation STEER_ENC_PPR / 4: straight ahead
            odometry.update(p.OdometryFb(node, CONFIG.STEER_ENC_PPR // 4, 100, pulses, 0), 0.0)
    state = odometry.state
    assert state.x == pytest.approx(136 * Kinematics(CONFIG).metres_per_pulse)


def test_a_silent_wheel_does_not_stop_the_odometry():
    wheels = started()
    wheels.report = ("front_left", "rear_left", "rear_right")
    state = wheels.move(0.5, 0.0, 0.0, MODE_ACKERMANN, 2.0)
    assert state.x == pytest.approx(1.0, abs=5e-3)


def test_reset_starts_again_at_a_pose():
    wheels = started()
    wheels.move(0.5, 0.0, 0.0, MODE_ACKERMANN, 1.0)
    wheels.odometry.reset(2.0, 3.0, math.pi / 2)
    wheels.publish()
    state = wheels.move(0.5, 0.0, 0.0, MODE_ACKERMANN, 1.0)
    assert (state.x, state.y) == pytest.approx((2.0, 3.5), abs=3e-3)
    assert wheels.odometry.wheel_angles()["front_left"] == pytest.approx(0.0)


def test_yaw_quaternion():
    assert yaw_to_quaternion(0.0) == (0.0, 0.0, 0.0, 1.0)
    x, y, z, w = yaw_to_quaternion(math.pi / 2)
    assert (z, w) == pytest.approx((math.sqrt(0.5), math.sqrt(0.5)))


def test_a_zeroed_or_restarted_counter_is_no_jump():
    wheels = started()
    wheels.move(0.5, 0.0, 0.0, MODE_ACKERMANN, 2.0)
    for wheel in WHEELS:   # switchCmd zeroEncoders: every counter starts at 0 again
        wheels.count[wheel] = 0.0
    wheels.time += 0.02
    wheels.publish()
    assert wheels.odometry.counter_resets == 4
    state = wheels.move(0.5, 0.0, 0.0, MODE_ACKERMANN, 1.0)
    assert state.x == pytest.approx(1.5, abs=3e-3)


def test_fast_travel_after_a_long_silence_still_counts():
    wheels = started()
    wheels.time += 5.0   # five seconds without frames, at full speed meanwhile
    full = wheels.kinematics.pps_to_speed(CONFIG.MAX_VEL)
    for wheel in WHEELS:
        wheels.count[wheel] += CONFIG.MAX_VEL * 5.0
        wheels.speed[wheel] = full
    wheels.publish()
    assert wheels.odometry.counter_resets == 0
    assert wheels.state.x == pytest.approx(full * 5.0, rel=1e-3)
