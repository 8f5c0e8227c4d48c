"""Quick stop (0x605A), shutdown (0x605B) and disable operation (0x605C)
option codes of the virtual EPOS4: the slow-down the motor really performs,
measured from the drive's own TxPDO3, and the state it ends in."""
import pytest
from canopen.sdo.exceptions import SdoAbortedError

from sim_support import NODE1, NodeConfig, RampRecorder, spin_up

PROFILE_DECEL = 6000  # rpm/s, 0x6084
QUICK_STOP_DECEL = 2000  # rpm/s, 0x6085: far enough apart to tell which one ramped

SWITCH_ON_DISABLED, READY_TO_SWITCH_ON, SWITCHED_ON = 0x0250, 0x0231, 0x0233
OPERATION_ENABLED = 0x0237
QUICK_STOP_DONE = 0x0617  # quick stop active with target reached (options 5, 6)


@pytest.fixture
def rig(sim_rig):
    return sim_rig([NodeConfig(1, NODE1)])


def _moving(rig):
    node = rig.remote(1)
    node.sdo[0x6084].raw = PROFILE_DECEL
    node.sdo[0x6085].raw = QUICK_STOP_DECEL
    return node


def _stop_and_measure(rig, node, controlword):
    spin_up(node, rig)
    recorder = RampRecorder(rig)
    try:
        rig.drain()
        node.sdo[0x6040].raw = controlword
        samples = recorder.record_until_rest()
    finally:
        recorder.stop()
    assert samples and samples[-1][1] == 0, "the motor did not come to rest: %s" % samples[-5:]
    return recorder


@pytest.mark.parametrize("option, decel, final", [
    (1, PROFILE_DECEL, SWITCH_ON_DISABLED),
    (2, QUICK_STOP_DECEL, SWITCH_ON_DISABLED),
    (5, PROFILE_DECEL, QUICK_STOP_DONE),
    (6, QUICK_STOP_DECEL, QUICK_STOP_DONE),
])
def test_quick_stop_ramps_with_the_option_codes_deceleration(rig, option, decel, final):
    node = _moving(rig)
    node.sdo[0x605A].raw = option
    recorder = _stop_and_measure(rig, node, 0x0002)
    assert recorder.deceleration() == pytest.approx(decel, rel=0.15)
    assert rig.wait(lambda: node.sdo[0x6041].raw == final)


def test_disable_operation_option_1_slows_down_then_switches_off(rig):
    node = _moving(rig)
    assert node.sdo[0x605C].raw == 1  # the EPOS4's default
    spin_up(node, rig)
    node.sdo[0x6040].raw = 0x0007
    # still operation enabled while the profile deceleration brakes the motor
    assert node.sdo[0x6041].raw & 0x6F == 0x27
    assert rig.wait(lambda: node.sdo[0x6041].raw == SWITCHED_ON)
    assert abs(node.sdo[0x606C].raw) < 5


def test_disable_operation_ramp_uses_the_profile_deceleration(rig):
    node = _moving(rig)
    recorder = _stop_and_measure(rig, node, 0x0007)
    assert recorder.deceleration() == pytest.approx(PROFILE_DECEL, rel=0.15)
    assert rig.wait(lambda: node.sdo[0x6041].raw == SWITCHED_ON)


def test_shutdown_option_1_slows_down_to_ready_to_switch_on(rig):
    node = _moving(rig)
    node.sdo[0x605B].raw = 1
    recorder = _stop_and_measure(rig, node, 0x0006)
    assert recorder.deceleration() == pytest.approx(PROFILE_DECEL, rel=0.15)
    assert rig.wait(lambda: node.sdo[0x6041].raw == READY_TO_SWITCH_ON)


@pytest.mark.parametrize("index, controlword, final", [
    (0x605A, 0x0002, SWITCH_ON_DISABLED),
    (0x605B, 0x0006, READY_TO_SWITCH_ON),  # 0 is the EPOS4's default for shutdown
    (0x605C, 0x0007, SWITCHED_ON),
])
def test_option_0_disables_at_once_and_the_motor_coasts(rig, index, controlword, final):
    node = _moving(rig)
    node.sdo[index].raw = 0
    spin_up(node, rig)
    node.sdo[0x6040].raw = controlword
    assert node.sdo[0x6041].raw == final
    assert node.sdo[0x606C].raw > 500  # no braking: friction only


def test_enable_operation_during_the_slow_down_cancels_it(rig):
    node = _moving(rig)
    node.sdo[0x6084].raw = 500  # a long ramp, so the command lands in it
    spin_up(node, rig)
    node.sdo[0x6040].raw = 0x0007
    assert rig.wait(lambda: node.sdo[0x606C].raw < 950)
    node.sdo[0x6040].raw = 0x000F
    assert node.sdo[0x6041].raw & 0x6F == 0x27
    assert rig.wait(lambda: node.sdo[0x606C].raw > 990)  # the target velocity again


@pytest.mark.parametrize("index, value", [
    (0x605A, 3), (0x605A, 7), (0x605B, 2), (0x605C, -1), (0x605E, 3), (0x6007, 4), (0x6007, -1),
])
def test_option_codes_the_epos4_lacks_are_refused(rig, index, value):
    node = rig.remote(1)
    before = node.sdo[index].raw
    with pytest.raises(SdoAbortedError) as err:
        node.sdo[index].raw = value
    assert err.value.code in (0x06090030, 0x06090031, 0x06090032)
    assert node.sdo[index].raw == before
