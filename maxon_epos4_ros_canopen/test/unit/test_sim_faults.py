"""EMCY, error objects, fault reset and every fault injection of the virtual EPOS4."""
import struct

import pytest
from canopen.sdo.exceptions import SdoCommunicationError

from sim_support import NODE1, NODE2, NodeConfig, enable
from maxon_epos4_ros_canopen import epos4_errors

# The simulator times an SDO delay from its node's last advance (up to one
# tick before the request came). A few ms cover it.
CLOCK_SLACK = 0.01


@pytest.fixture
def rig(sim_rig):
    return sim_rig([NodeConfig(1, NODE1), NodeConfig(2, NODE2)])


def test_injected_emcy_faults_drive_and_fills_error_objects(rig):
    node = rig.remote(1)
    enable(node, 1)
    rig.drain()
    assert "Following error" in rig.sim.inject_fault(1, "emcy", error_code=0x8611)
    msg = rig.expect(lambda m: m.arbitration_id == 0x081)
    assert bytes(msg.data) == struct.pack("<HB5s", 0x8611, 0x81, bytes(5))
    assert rig.wait(lambda: node.sdo[0x6041].raw & 0x6F == 0x08)
    assert node.sdo[0x6041].raw == 0x0218
    assert node.sdo[0x603F].raw == 0x8611
    assert node.sdo[0x1001].raw == 0x81
    rig.sim.inject_fault(1, "emcy", error_code=0x3210)
    assert node.sdo[0x1003][0].raw == 2
    assert node.sdo[0x1003][1].raw == 0x3210  # newest first
    assert node.sdo[0x1003][2].raw == 0x8611
    # fault reset needs the rising edge of bit 7
    node.sdo[0x6040].raw = 0x0000
    rig.drain()
    node.sdo[0x6040].raw = 0x0080
    msg = rig.expect(lambda m: m.arbitration_id == 0x081)
    assert bytes(msg.data) == bytes(8)  # error reset EMCY
    assert node.sdo[0x6041].raw == 0x0250 and node.sdo[0x603F].raw == 0
    assert node.sdo[0x1001].raw == 0
    node.sdo[0x1003][0].raw = 0  # clear history
    assert node.sdo[0x1003][0].raw == 0 and node.sdo[0x1003][1].raw == 0


def test_fault_reaction_uses_quick_stop_ramp(rig):
    node = rig.remote(1)
    enable(node, 3)
    node.sdo[0x60FF].raw = 1000
    assert rig.wait(lambda: node.sdo[0x606C].raw > 950)
    node.sdo[0x6085].raw = 1000
    rig.sim.inject_fault(1, "emcy", error_code=0x2310)
    assert node.sdo[0x6041].raw & 0x4F == 0x0F  # fault reaction active, still braking
    assert rig.wait(lambda: node.sdo[0x6041].raw & 0x4F == 0x08)
    assert abs(node.sdo[0x606C].raw) < 5


def test_silent_node_sends_nothing_then_recovers(rig):
    node = rig.remote(1)
    node.sdo[0x1017].raw = 20
    node.sdo.RESPONSE_TIMEOUT = 0.3
    node.sdo.MAX_RETRIES = 1  # canopen: 1 = a single attempt
    rig.sim.inject_fault(1, "silent", duration=0.0)
    rig.drain()
    with pytest.raises(SdoCommunicationError):
        node.sdo[0x6041].raw
    node_frames = {0x081, 0x181, 0x281, 0x381, 0x481, 0x581, 0x701}
    assert not [m for m in rig.handled(0.3) if m.arbitration_id in node_frames]  # 15 heartbeat periods
    rig.sim.inject_fault(1, "clear")
    assert node.sdo[0x6041].raw == 0x0250
    assert rig.expect(lambda m: m.arbitration_id == 0x701)


def test_heartbeat_stop_keeps_sdo_alive(rig):
    node = rig.remote(1)
    node.sdo[0x1017].raw = 20
    assert rig.expect(lambda m: m.arbitration_id == 0x701)
    rig.sim.inject_fault(1, "heartbeat_stop")
    rig.drain()
    assert not [m for m in rig.handled(0.3) if m.arbitration_id == 0x701]  # 15 heartbeat periods
    assert node.sdo[0x6041].raw == 0x0250


def test_reboot_boots_up_with_power_on_values(rig):
    node = rig.remote(1)
    enable(node, 3)
    node.sdo[0x6081].raw = 123
    rig.drain()
    rig.sim.inject_fault(1, "reboot")
    assert rig.expect(lambda m: m.arbitration_id == 0x701 and bytes(m.data) == b"\x00")
    assert node.sdo[0x6081].raw == 1000
    assert node.sdo[0x6041].raw == 0x0250
    assert node.sdo[0x6061].raw == 1


def test_sdo_delay_delays_answers(rig):
    node = rig.remote(1)
    rig.sim.inject_fault(1, "sdo_delay", duration=0.4)
    rig.drain()
    sent = rig.clock.wall()  # what the rig's clock stamps frames with
    rig.send(0x601, bytes([0x40, 0x41, 0x60, 0, 0, 0, 0, 0]))
    answer = rig.expect(lambda m: m.arbitration_id == 0x581)
    # a loaded host can only make the answer later, never earlier
    assert answer is not None and answer.timestamp - sent >= 0.4 - CLOCK_SLACK, answer.timestamp - sent
    rig.sim.inject_fault(1, "clear")
    assert node.sdo[0x6041].raw == 0x0250


def test_corrupt_frame_flips_the_next_frame_only(rig):
    rig.sim.inject_fault(2, "corrupt_frame")
    rig.drain()
    rig.send(0x602, bytes([0x40, 0x41, 0x60, 0, 0, 0, 0, 0]))
    bad = rig.expect(lambda m: m.arbitration_id == 0x582)
    assert bytes(bad.data) == bytes(b ^ 0xFF for b in bytes([0x4B, 0x41, 0x60, 0, 0x50, 0x02, 0, 0]))
    rig.send(0x602, bytes([0x40, 0x41, 0x60, 0, 0, 0, 0, 0]))
    good = rig.expect(lambda m: m.arbitration_id == 0x582)
    assert bytes(good.data) == bytes([0x4B, 0x41, 0x60, 0, 0x50, 0x02, 0, 0])


def test_bad_injection_requests_raise_clear_errors(rig):
    with pytest.raises(ValueError, match="unknown fault"):
        rig.sim.inject_fault(1, "explode")
    with pytest.raises(ValueError, match="no simulated node 9"):
        rig.sim.inject_fault(9, "reboot")
    with pytest.raises(ValueError, match="error_code"):
        rig.sim.inject_fault(1, "emcy", error_code=0)
    with pytest.raises(ValueError, match="duration"):
        rig.sim.inject_fault(1, "silent", duration=-1.0)
    with pytest.raises(ValueError, match="duration"):
        rig.sim.inject_fault(1, "sdo_delay", duration=-1.0)
    node = rig.remote(1)
    assert node.sdo[0x6041].raw == 0x0250  # still serving


def test_describe_error_codes():
    assert epos4_errors.describe(0x8611) == "0x8611 Following error"
    assert epos4_errors.describe(0x8120) == "0x8120 CAN passive mode error"
    assert epos4_errors.describe(0x1234) == "0x1234 unknown EPOS4 error"
    assert epos4_errors.error_register(0x3210) == 0x05
    assert epos4_errors.error_register(0x8120) == 0x11
    assert epos4_errors.error_register(0x2999) == 0x03  # by error class


def test_timed_silence_ends_by_itself(rig):
    rig.sim.inject_fault(2, "silent", duration=2.0)
    rig.drain()
    rig.send(0x602, bytes([0x40, 0x41, 0x60, 0, 0, 0, 0, 0]))
    assert not [m for m in rig.handled() if m.arbitration_id == 0x582]  # the request met a silent node

    def answers():
        rig.send(0x602, bytes([0x40, 0x41, 0x60, 0, 0, 0, 0, 0]))
        return rig.expect(lambda m: m.arbitration_id == 0x582, timeout=0.1) is not None
    assert rig.wait(answers, timeout=5.0)


@pytest.mark.parametrize("step", [0.001, 0.01, 0.02, 0.05])
def test_a_fault_reaction_ends_at_standstill_however_coarse_the_steps(rig, step):
    """The power stage goes off (Fault) only with the motor at rest, also
    when the simulating loop is starved and advances in coarse steps: the
    position then stays where the ramp ended, as a real drive's does."""
    node = rig.remote(1)
    from sim_support import spin_up
    spin_up(node, rig, 500)
    drive = rig.sim.nodes[1]

    def fault_in_steps_of(dt):
        # in the loop thread: nothing else advances the drive meanwhile
        t = drive.t
        drive.raise_fault(0x8611, t)
        for _ in range(int(2.0 / dt)):
            t += dt
            drive.tick(t)
            if drive.statusword() & 0x6F == 0x08:
                break
        stopped_at = drive.position
        for _ in range(int(5.0 / dt)):  # five more seconds in Fault
            t += dt
            drive.tick(t)
        return drive.statusword(), stopped_at, drive.position, drive.motor.velocity
    statusword, stopped_at, position, velocity = rig.sim.call(lambda: fault_in_steps_of(step))
    assert statusword & 0x6F == 0x08  # fault
    assert velocity == 0.0
    assert abs(position - stopped_at) < 1.0, "the rotor moved %.1f inc after the power stage went off" % (
        position - stopped_at)


def test_a_drive_goes_on_turning_while_its_interface_is_down(rig):
    """A bus that goes down (the interface, not the drive) stops no drive's
    control loop: a drive turning at 500 rpm turns on, and the simulator
    still serves its own calls (fault injection) meanwhile."""
    import can
    from sim_support import spin_up
    node = rig.remote(1)
    spin_up(node, rig, 500)
    receive = rig.sim.bus.recv

    def interface_down(timeout=None):
        raise can.CanOperationError("Network is down")
    rig.sim.bus.recv = interface_down
    try:
        first = rig.sim.call(lambda: rig.sim.nodes[1].position)
        assert rig.wait(lambda: rig.sim.call(lambda: rig.sim.nodes[1].position) - first > 3200)  # a turn
        assert "silent" in rig.sim.inject_fault(1, "silent", duration=0.0)
        rig.sim.inject_fault(1, "clear")
    finally:
        rig.sim.bus.recv = receive
    assert rig.wait(lambda: node.sdo[0x606C].raw > 450)
