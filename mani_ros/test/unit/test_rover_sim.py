"""The simulated rover over python-can's virtual bus: the frames an OBC sends
and the frames it gets back."""
import itertools
import random
import time

import can
import pytest

from mani_ros import protocol as p
from mani_ros.config import load_config
from mani_ros.kinematics import MODE_ACKERMANN, Kinematics
from mani_ros.odometry import WheelOdometry
from mani_ros.rover_sim import TICK, RoverSim, main

CONFIG = load_config()
SIM = CONFIG.simulation
# The simulated wheels start straight ahead: a quarter turn of the steering
# encoder, whose zero is at -90 deg on the rover.
STRAIGHT = CONFIG.STEER_ENC_PPR // 4
_channels = itertools.count()


@pytest.fixture
def buses(request):
    """(obc, sim) buses on a channel of their own."""
    channel = "mani_sim_%s_%d" % (request.node.name, next(_channels))
    obc = can.Bus(interface="virtual", channel=channel)
    sim = can.Bus(interface="virtual", channel=channel)
    yield obc, sim
    obc.shutdown()
    sim.shutdown()


@pytest.fixture
def rover(buses):
    obc, bus = buses
    return Obc(obc, RoverSim(bus, CONFIG))


class Obc:
    """Sends commands and steps the simulator, collecting what it sends."""

    def __init__(self, bus, sim):
        self.bus, self.sim = bus, sim
        self.received = []

    def send(self, message):
        frame = p.to_can_message(message)
        self.bus.send(frame)
        self.sim.handle(self.sim.bus.recv(timeout=1.0))

    def send_raw(self, can_id, data, **kwargs):
        self.bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False, **kwargs))
        self.sim.handle(self.sim.bus.recv(timeout=1.0))

    def run(self, seconds):
        """Advance the simulator; returns the decoded messages it sent."""
        got = []
        for _ in range(int(round(seconds / TICK))):
            self.sim.advance(TICK)
            got.extend(self.drain())
        return got

    def drain(self):
        got = []
        while True:
            frame = self.bus.recv(timeout=0)
            if frame is None:
                break
            got.append(p.decode_can_message(frame))
        self.received.extend(got)
        return got


def of(kind, messages, node_id=None):
    return [m for m in messages if isinstance(m, kind)
            and (node_id is None or getattr(m, "node_id", None) == node_id)]


def enable(rover, node_id, publish=True):
    rover.send(p.SwitchCmd(node_id, steer_mode=True, drive_mode=True, publisher_mode=publish))


def test_a_locomotion_command_is_reached_gradually_then_reported_once(rover):
    enable(rover, p.FRONT_LEFT)
    rover.send(p.OrientationCmd(p.FRONT_LEFT, STRAIGHT + 800))
    rover.send(p.VelocityCmd(p.FRONT_LEFT, 3000))
    got = rover.run(3.0)
    done = of(p.LocomotionFb, got)
    assert done == [p.LocomotionFb(p.FRONT_LEFT, True)]
    odometry = of(p.OdometryFb, got, p.FRONT_LEFT)
    orientations = [m.orientation for m in odometry]
    velocities = [m.velocity for m in odometry]
    # finite steering rate and acceleration: several intermediate values
    steer_step = SIM.steer_rate * CONFIG.STEER_ENC_PPR / 6.283185307 * SIM.odometry_period
    assert all(0 <= b - a <= steer_step + 1 for a, b in zip(orientations, orientations[1:]))
    assert len(set(orientations)) > 5 and len(set(velocities)) > 5
    assert orientations[-1] == STRAIGHT + 800 and velocities[-1] == 3000
    # the locomotionFb came after the set points were within tolerance
    index = rover.received.index(done[0])
    before = of(p.OdometryFb, rover.received[:index], p.FRONT_LEFT)
    assert abs(before[-1].orientation - STRAIGHT - 800) > SIM.orientation_tolerance or \
        abs(before[-1].velocity - 3000) > SIM.velocity_tolerance
    # the wheel turns: the drive counter advances at about 3000 pulses/s
    count = lambda m: m.revolutions * CONFIG.DRIVE_ENC_PPR + m.pulses
    later = of(p.OdometryFb, rover.run(1.0), p.FRONT_LEFT)
    assert count(later[-1]) - count(odometry[-1]) == pytest.approx(3000, rel=0.1)
    assert of(p.LocomotionFb, rover.received[index + 1:]) == []


def test_every_wheel_answers_for_itself(rover):
    for node in p.DRIVE_NODES:
        enable(rover, node, publish=False)
        rover.send(p.OrientationCmd(node, STRAIGHT - 100 * node))
        rover.send(p.VelocityCmd(node, 0))
    got = rover.run(1.0)
    assert sorted(m.node_id for m in of(p.LocomotionFb, got)) == [1, 2, 3, 4]
    assert of(p.OdometryFb, got) == []   # publisherMode off: no stream


def test_without_switch_command_nothing_moves_and_nothing_completes(rover):
    rover.send(p.OrientationCmd(p.REAR_LEFT, 500))
    rover.send(p.VelocityCmd(p.REAR_LEFT, 500))
    rover.send(p.SwitchCmd(p.REAR_LEFT, publisher_mode=True))
    got = rover.run(2.0)
    assert of(p.LocomotionFb, got) == []
    assert {(m.orientation, m.velocity) for m in of(p.OdometryFb, got)} == {(STRAIGHT, 0)}


def test_power_command_toggles_power_feedback_and_the_motors(rover):
    rover.send(p.PowerCmd(False))
    assert rover.drain() == [p.PowerFb(False)]
    enable(rover, p.REAR_RIGHT)
    rover.send(p.OrientationCmd(p.REAR_RIGHT, 300))
    got = rover.run(1.0)
    assert of(p.LocomotionFb, got) == []
    assert set(of(p.PowerFb, got)) == {p.PowerFb(False)}            # periodic report
    assert {m.orientation for m in of(p.OdometryFb, got)} == {STRAIGHT}
    rover.send(p.PowerCmd(True))
    assert rover.drain() == [p.PowerFb(True)]
    assert of(p.LocomotionFb, rover.run(1.0)) == [p.LocomotionFb(p.REAR_RIGHT, True)]


def test_power_off_lets_a_turning_wheel_coast_to_a_stop(rover):
    enable(rover, p.FRONT_RIGHT)
    rover.send(p.VelocityCmd(p.FRONT_RIGHT, 2000))
    rover.run(3.0)
    rover.send(p.PowerCmd(False))
    last = of(p.OdometryFb, rover.run(3.0), p.FRONT_RIGHT)[-1]
    assert last.velocity == 0


def test_zero_encoders_clears_orientation_and_counters(rover):
    enable(rover, p.FRONT_LEFT)
    rover.send(p.OrientationCmd(p.FRONT_LEFT, 400))
    rover.send(p.VelocityCmd(p.FRONT_LEFT, 3000))
    rover.run(3.0)
    rover.send(p.VelocityCmd(p.FRONT_LEFT, 0))
    rover.run(3.0)
    rover.send(p.SwitchCmd(p.FRONT_LEFT, True, True, True, zero_encoders=True))
    last = of(p.OdometryFb, rover.run(0.2), p.FRONT_LEFT)[-1]
    assert last == p.OdometryFb(p.FRONT_LEFT, 0, 0, 0, 0)


def test_revolutions_build_up_and_pulses_stay_within_a_revolution(rover):
    enable(rover, p.REAR_LEFT)
    rover.send(p.VelocityCmd(p.REAR_LEFT, -8000))
    odometry = of(p.OdometryFb, rover.run(4.0), p.REAR_LEFT)
    assert odometry[-1].revolutions <= -3
    assert all(abs(m.pulses) < CONFIG.DRIVE_ENC_PPR for m in odometry)


def test_a_silent_node_never_answers(rover):
    rover.sim.inject("silent", p.REAR_RIGHT, True)
    for node in p.DRIVE_NODES:
        enable(rover, node)
        rover.send(p.OrientationCmd(node, STRAIGHT + 100))
    got = rover.run(1.0)
    assert sorted(m.node_id for m in of(p.LocomotionFb, got)) == [1, 2, 4]
    assert of(p.OdometryFb, got, p.REAR_RIGHT) == []
    assert rover.sim.inject("clear", 255) == "all faults cleared"
    rover.send(p.OrientationCmd(p.REAR_RIGHT, STRAIGHT + 100))   # commands count again from now on
    enable(rover, p.REAR_RIGHT)
    assert of(p.LocomotionFb, rover.run(1.0)) == [p.LocomotionFb(p.REAR_RIGHT, True)]


def test_eps_reports_power_and_five_currents_periodically(rover):
    got = rover.run(SIM.eps_period * 2 + 0.05)
    assert len(of(p.PowerFb, got)) == 3
    readings = of(p.CurrentFb, got)
    assert len(readings) == 15 and {m.sensor_index for m in readings} == set(range(5))
    assert all(0 <= m.current < 0.8 * p.CURRENT_FULL_SCALE for m in readings)
    # nothing abnormal: one all-clear errorWrn/currentWrn at start, no repeats
    assert of(p.ErrorWrn, got) == [p.ErrorWrn()] and of(p.CurrentWrn, got) == [p.CurrentWrn()]


def test_injected_overcurrent_shows_as_error_warning_and_reading(rover):
    rover.run(0.1)
    rover.sim.inject("overcurrent", 2, True)      # rear_left
    got = rover.run(SIM.eps_period * 2)
    errors = of(p.ErrorWrn, got)
    assert errors[0] == p.ErrorWrn(rear_left=True) and len(errors) >= 2   # repeated while active
    assert errors[0].active() == ("rear_left",)
    assert of(p.CurrentWrn, got)[0] == p.CurrentWrn(rear_left=True)   # above 80 % too
    # beyond the maximum the normalised reading saturates at full scale
    assert all(m.current == p.CURRENT_FULL_SCALE for m in of(p.CurrentFb, got) if m.sensor_index == 2)
    rover.sim.inject("overcurrent", 2, False)
    got = rover.run(SIM.eps_period * 2)
    assert of(p.ErrorWrn, got) == [p.ErrorWrn()]   # the all-clear, once


def test_injected_current_warning_is_not_an_error(rover):
    rover.run(0.1)
    rover.sim.inject("current_warning", 0, True)
    got = rover.run(0.1)
    assert of(p.CurrentWrn, got) == [p.CurrentWrn(battery=True)]
    assert of(p.ErrorWrn, got) == []


def test_driving_wheels_draw_more_current(rover):
    idle = {m.sensor_index: m.current for m in of(p.CurrentFb, rover.run(SIM.eps_period + 0.05))}
    enable(rover, p.FRONT_LEFT)
    rover.send(p.VelocityCmd(p.FRONT_LEFT, CONFIG.max_velocity_pulses))
    busy = {m.sensor_index: m.current for m in of(p.CurrentFb, rover.run(2.0))}
    assert busy[1] > idle[1] and busy[0] > idle[0] and busy[4] == idle[4]


def test_fault_requests_are_checked():
    sim = RoverSim(can.Bus(interface="virtual", channel="mani_sim_faults"), CONFIG)
    with pytest.raises(ValueError, match="unknown fault 'melt'"):
        sim.inject("melt", 1)
    with pytest.raises(ValueError, match="node 7 is not 0 .EPS. or a drive node 1..4"):
        sim.inject("silent", 7)
    with pytest.raises(ValueError, match="sensor 6 is not 0..4"):
        sim.inject("overcurrent", 6)
    with pytest.raises(ValueError, match="clear needs"):
        sim.inject("clear", 9)
    sim.bus.shutdown()


def test_a_silent_eps_ignores_power_commands(rover):
    rover.sim.inject("silent", p.POWER_SUPPLY, True)
    rover.send(p.PowerCmd(False))
    assert rover.drain() == [] and rover.sim.motor_power is True
    assert rover.run(1.0) == []


def test_unknown_ids_and_bad_frames_are_ignored(rover):
    for can_id, data in [(0x123, b"\x01"), (0x0A0, b"\x01\x01\x01\x00"), (0x0B5, b"\x00\x01"),
                         (0x0B1, b"\x01"), (0x000, b"\x02"), (0x0D1, b"\x01"), (0x7FF, b"")]:
        rover.send_raw(can_id, data)
    rover.send_raw(0x000, b"\x00", is_remote_frame=False)
    stats = rover.sim.stats
    assert stats["invalid"] == 6 and stats["ignored"] == 1 and stats["handled"] == 1
    assert rover.drain() == [p.PowerFb(False)]   # only the valid powerCmd was answered
    assert all(not d.steer_mode for d in rover.sim.drives.values())


def random_frame(rng):
    can_id = rng.choice([rng.randrange(0x800), rng.randrange(0x0F0), 0x000,
                         0x0A0 | rng.randrange(1, 5), 0x0B0 | rng.randrange(1, 5)])
    return can.Message(arbitration_id=can_id, is_extended_id=rng.random() < 0.05,
                       data=bytes(rng.randrange(256) for _ in range(rng.randrange(9))))


def test_thousands_of_random_and_short_frames_never_crash_it(rover):
    rng = random.Random(1234)
    for i in range(5000):
        rover.sim.handle(random_frame(rng))
        if i % 50 == 0:
            rover.sim.advance(TICK)
            rover.drain()
    assert rover.sim.stats["received"] == 5000
    assert rover.sim.stats["invalid"] > 2500
    # still a working rover afterwards
    rover.send(p.PowerCmd(True))
    for node in p.DRIVE_NODES:
        enable(rover, node)
        rover.send(p.OrientationCmd(node, 0))
        rover.send(p.VelocityCmd(node, 0))
    assert rover.drain()[-1] == p.PowerFb(True)
    assert sorted(m.node_id for m in of(p.LocomotionFb, rover.run(3.0))) == [1, 2, 3, 4]


def wait_for(bus, predicate, deadline=10.0):
    """The first decodable message on bus that satisfies predicate, or None."""
    end = time.monotonic() + deadline
    while time.monotonic() < end:
        frame = bus.recv(timeout=0.1)
        if frame is None:
            continue
        try:
            message = p.decode_can_message(frame)
        except p.ProtocolError:
            continue
        if predicate(message):
            return message
    return None


def test_running_in_its_thread_survives_a_flood_and_still_answers(buses):
    obc, bus = buses
    sim = RoverSim(bus, CONFIG)
    sim.start()
    try:
        rng = random.Random(99)
        for _ in range(3000):
            obc.send(random_frame(rng))
        obc.send(p.to_can_message(p.PowerCmd(True)))
        obc.send(p.to_can_message(p.SwitchCmd(p.REAR_LEFT, True, True, True)))
        obc.send(p.to_can_message(p.OrientationCmd(p.REAR_LEFT, -400)))
        obc.send(p.to_can_message(p.VelocityCmd(p.REAR_LEFT, 800)))
        # the flood's random frames command other drives too; their feedback
        # may come first, depending on how the sim's thread was scheduled
        done = wait_for(obc, lambda m: isinstance(m, p.LocomotionFb) and m.node_id == p.REAR_LEFT)
        assert done == p.LocomotionFb(p.REAR_LEFT, True)
        moving = wait_for(obc, lambda m: isinstance(m, p.OdometryFb) and m.node_id == p.REAR_LEFT)
        assert abs(moving.orientation + 400) <= SIM.orientation_tolerance
        assert abs(moving.velocity - 800) <= SIM.velocity_tolerance
        assert sim._thread.is_alive()
        assert sim.stats["received"] >= 3004
    finally:
        sim.stop()
    assert sim._thread is None


def test_cli_refuses_bad_arguments_without_touching_a_bus(capsys):
    assert main(["--interface", "virtual", "--channel", "mani_cli", "--silent", "9"]) == 2
    assert main(["--interface", "no_such_interface", "--channel", "x"]) == 1
    assert main(["--config", "/nonexistent/mani.yaml"]) == 2


def test_closed_loop_kinematics_simulator_odometry_follows_the_commanded_arc(rover):
    """Set points from the kinematics, executed by the simulated drives, read
    back through odometryFb: the pose moves along the commanded arc."""
    kinematics = Kinematics(CONFIG)
    odometry = WheelOdometry(CONFIG)
    vx, wz = 0.15, 0.12   # within MAX_VEL (0.215 m/s at the rim)
    for node in p.DRIVE_NODES:
        enable(rover, node)
    for message in kinematics.command_messages(kinematics.body_to_wheels(vx, 0.0, wz, MODE_ACKERMANN)):
        rover.send(message)
    steering_time = 1.0   # the wheels reach their angles and speeds meanwhile
    state = None
    for message in rover.run(steering_time + 6.0):
        if isinstance(message, p.OdometryFb):
            state = odometry.update(message, rover.sim.time) or state
    assert len(of(p.LocomotionFb, rover.received)) == 4
    assert state.x > 0.8 and state.y > 0.1 and state.yaw > 0.2
    # curvature of the path: yaw per metre = wz / vx
    assert state.yaw / state.distance == pytest.approx(wz / vx, rel=0.05)
    assert state.vx == pytest.approx(vx, rel=0.02) and state.wz == pytest.approx(wz, rel=0.02)
