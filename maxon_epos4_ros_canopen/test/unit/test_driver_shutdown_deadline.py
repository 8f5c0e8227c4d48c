"""Shutdown's one overall deadline, on the stepped clock: a drive that stops
answering SDO (or whose answer channel is disturbed by forged frames) while
the driver shuts down does not hold the shutdown for minutes. The drives
the cycle hears are still brought to rest and disabled, NMT stop still goes
to every node, the bus is still closed, and the answer says which steps the
deadline cut short."""
import logging
import struct

import can
import pytest

from maxon_epos4_ros_canopen.cia402 import CW_DISABLE_VOLTAGE, CW_QUICK_STOP, State
from maxon_epos4_ros_canopen.clock import SteppedClock
from maxon_epos4_ros_canopen.driver.deadline import Deadline, DeadlinePassed
from maxon_epos4_ros_canopen.objects import ObjectKey

from driver_support import DCF1, DCF2, J1, J2

# The driver's default shutdown deadline (s): shutdown and close end within it.
SHUTDOWN_DEADLINE = 5.0
TWO_DRIVES = ((1, DCF1, J1), (2, DCF2, J2))
VELOCITY = 500.0  # rpm, both drives, when shutdown begins


@pytest.fixture
def rig(driver_rig):
    return driver_rig


def _two_drives_turning(rig, **top):
    d = rig.start(nodes=TWO_DRIVES, **top)
    r = d.init()
    assert r.success, r.message
    assert d.switch_mode([J1, J2], 3).success
    for name in (J1, J2):
        assert d.set_command(name, "velocity", VELOCITY).success
    assert rig.until(lambda: rig.read(0x606C, node=1) > 450 and rig.read(0x606C, node=2) > 450)
    return d


def _sdo_server_stops_answering(rig, node_id):
    """The drive's SDO server takes no request any more; its PDOs, heartbeat
    and state machine run on (what an overloaded or wedged SDO server, or a
    channel another client keeps busy, looks like to the driver)."""
    rig.sim.nodes[node_id].sdo.on_request = lambda data, now: None


def _forge_answers(rig, node_id, period):
    """Frames on the drive's SDO answer COB-ID every ``period`` s: an upload
    answer for another object (0x1018), as another client's transfer on the
    same channel would put there. Returns a stop function."""
    forger = can.Bus(interface="virtual", channel=rig.channel)
    frame = can.Message(arbitration_id=0x580 + node_id, data=b"\x43\x18\x10\x01\x92\x01\x00\x00",
                        is_extended_id=False)
    task = rig.clock.send_periodic(forger, [frame], period, "sdo_forger")

    def stop():
        task.stop()
        forger.shutdown()
    return stop


def _controlwords(rig, cob_id):
    return [struct.unpack_from("<H", p)[0] for p in rig.sent(cob_id)]


def _assert_left_safe(rig, d):
    """Node 1 (no SDO answers) quick-stopped and at rest, node 2 disabled,
    each as the simulated drive itself has it and as its last controlword on
    the bus says; NMT stop to both; the bus closed."""
    assert rig.state(node=2) == State.SWITCH_ON_DISABLED
    assert rig.state(node=1) in (State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED)
    assert rig.read(0x606C, node=1) == 0 and rig.read(0x606C, node=2) == 0
    cw1, cw2 = _controlwords(rig, 0x201), _controlwords(rig, 0x202)
    assert cw1 and cw1[-1] & 0x0087 in (CW_QUICK_STOP, CW_DISABLE_VOLTAGE), ["0x%04X" % w for w in cw1[-5:]]
    assert cw2 and cw2[-1] & 0x0087 == CW_DISABLE_VOLTAGE, ["0x%04X" % w for w in cw2[-5:]]
    nmt = rig.sent(0x000)
    assert b"\x02\x01" in nmt and b"\x02\x02" in nmt, nmt
    assert d.bus is None and d.network is None and not d.initialized
    # the consumer of the drive that answers is released: no heartbeat fault
    # once the master's heartbeat ends
    assert rig.read(0x1016, 1, node=2) == 0


@pytest.mark.parametrize("disturbance", ["silent", "forged_answers"])
@pytest.mark.parametrize("how", ["shutdown", "close"])
def test_a_drive_that_stops_answering_sdo_does_not_hold_shutdown_past_its_deadline(rig, caplog, disturbance, how):
    d = _two_drives_turning(rig)
    rig.drain()
    _sdo_server_stops_answering(rig, 1)
    stop_forging = _forge_answers(rig, 1, 0.3) if disturbance == "forged_answers" else (lambda: None)
    start = rig.clock.now()
    try:
        with caplog.at_level(logging.WARNING, logger="maxon_epos4_ros_canopen.driver"):
            if how == "shutdown":
                message = d.shutdown().message
            else:
                d.close()
                message = " ".join(r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR)
        took = rig.clock.now() - start
    finally:
        stop_forging()
    assert took <= SHUTDOWN_DEADLINE, "%s took %.3f s of the clock: %s" % (how, took, message)
    _assert_left_safe(rig, d)
    # the answer (shutdown) or the log (close) names the deadline and what it cut short
    assert "shutdown deadline (%g s)" % SHUTDOWN_DEADLINE in message, message
    assert "%s (node 1)" % J1 in message, message
    assert "%s (node 2)" % J2 not in message, message


def test_the_shutdown_deadline_is_a_setting_of_the_configuration(rig):
    """``timeouts/shutdown`` (s) at the top level of any layer sets the
    deadline; the driver's own setting overrides it."""
    d = _two_drives_turning(rig, timeouts={"shutdown": 2.0, "not_a_timeout": 1})
    assert d.shutdown_timeout == 2.0
    assert any("timeouts/not_a_timeout" in w for w in d.config.warnings), d.config.warnings
    rig.drain()
    _sdo_server_stops_answering(rig, 1)
    start = rig.clock.now()
    r = d.shutdown()
    took = rig.clock.now() - start
    assert took <= 2.0, "shutdown took %.3f s of the clock: %s" % (took, r.message)
    assert "shutdown deadline (2 s)" in r.message, r.message
    _assert_left_safe(rig, d)


class _HeldForever:
    """A lock as a thread stuck while holding it (a service, a transfer)
    leaves it: every try to take it fails. A wait for it without a bound
    would never end: here it fails the test at once instead."""

    def acquire(self, blocking=True, timeout=-1):
        if blocking and (timeout is None or timeout < 0):
            raise AssertionError("waited for a lock without a bound")
        return False

    def release(self):
        raise AssertionError("released a lock it never had")

    def __enter__(self):
        return self.acquire()

    def __exit__(self, *exc):
        return False


def test_close_while_a_service_never_lets_go_still_stops_the_drives_within_the_deadline(rig, caplog):
    """At node exit a service (an init stuck on a silent bus, say) may hold
    the driver. close() waits for it only until the deadline, then stops the
    drives through the cycle and NMT and closes the bus all the same."""
    d = _two_drives_turning(rig)
    real_lock = d._lifecycle.service
    d._lifecycle.service = _HeldForever()
    rig.drain()
    start = rig.clock.now()
    try:
        with caplog.at_level(logging.WARNING, logger="maxon_epos4_ros_canopen.driver"):
            d.close()
        took = rig.clock.now() - start
    finally:
        d._lifecycle.service = real_lock
    assert took <= SHUTDOWN_DEADLINE, "close took %.3f s of the clock" % took
    for node in (1, 2):
        assert rig.state(node=node) in (State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED), node
    assert rig.until(lambda: rig.read(0x606C, node=1) == 0 and rig.read(0x606C, node=2) == 0, 2.0)
    for cob_id in (0x201, 0x202):
        words = _controlwords(rig, cob_id)
        assert words and words[-1] & 0x0087 == CW_QUICK_STOP, ["0x%04X" % w for w in words[-5:]]
    nmt = rig.sent(0x000)
    assert b"\x02\x01" in nmt and b"\x02\x02" in nmt, nmt
    assert d.bus is None and d.network is None
    logged = " ".join(r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR)
    assert "shutdown deadline (%g s)" % SHUTDOWN_DEADLINE in logged and "service" in logged, logged


# ------------------------------------------------------------ the parts

def test_an_sdo_transfer_given_a_deadline_waits_no_longer_and_tries_no_more(rig):
    """Without a deadline a transfer nobody answers waits 1, 2 and 3 times
    the SDO timeout (test_driver.py); with one, its last attempt ends at
    the deadline, and past it no request goes out at all."""
    d = rig.start()
    assert d.init().success
    _sdo_server_stops_answering(rig, 1)
    waits = []

    def read_device_type(client):
        waits.append(client.RESPONSE_TIMEOUT)
        return client.upload(0x1000, 0)
    until = Deadline(rig.clock, 1.5)
    start = rig.clock.now()
    with pytest.raises(DeadlinePassed, match=r"shutdown deadline \(1.5 s\) passed: no answer in time"):
        d._access.sdo_transfer(J1, read_device_type, until)
    assert rig.clock.now() - start == pytest.approx(1.5)
    assert waits == pytest.approx([d.sdo_timeout, 1.5 - d.sdo_timeout])
    rig.drain()
    with pytest.raises(DeadlinePassed, match="not sent"):
        d._access.sdo_transfer(J1, read_device_type, until)
    assert len(waits) == 2 and rig.sent(0x601) == []


def test_an_sdo_transfer_given_a_deadline_waits_for_a_busy_channel_only_until_it(rig):
    d = rig.start()
    assert d.init().success
    locks = d._access._sdo_locks
    lock, locks[J1] = locks[J1], _HeldForever()  # another thread's transfer on the node, one that does not end
    try:
        start = rig.clock.now()
        with pytest.raises(DeadlinePassed, match="stayed busy"):
            d._access.upload(J1, ObjectKey(0x1000), Deadline(rig.clock, 0.3))
        assert rig.clock.now() - start == pytest.approx(0.3)
    finally:
        locks[J1] = lock


def test_a_deadline_shares_its_time_and_collects_what_it_cut_short():
    clock = SteppedClock()
    deadline = Deadline(clock, 4.0)
    first = deadline.share(4)
    assert first.at == pytest.approx(1.0) and deadline.earlier(1.0).at == pytest.approx(3.0)
    clock.advance(1.0)
    assert first.passed and not deadline.passed and deadline.left() == pytest.approx(3.0)
    assert "its share of the shutdown deadline (4 s) ran out: x" in str(first.passed_error("x"))
    assert deadline.report() is None
    first.note("a step")
    deadline.note("another")
    deadline.note("a step")
    assert deadline.report() == "shutdown deadline (4 s) reached: cut short or skipped: a step; another"
    clock.advance(3.0)
    assert deadline.passed and deadline.share(2).passed and deadline.left() == 0.0
    assert str(deadline.passed_error("y")) == "shutdown deadline (4 s) passed: y"


def test_a_mode_switch_that_asks_to_enable_after_shutdown_began_is_refused(rig):
    """The node stops the drives before the controllers (a controller switch
    under way would hold the node's exit for as long as its mode switch
    takes): a mode switch still running then may ask the cycle to enable
    its drive after shutdown disabled it. The cycle takes only requests
    towards a stop once shutdown began."""
    d = rig.start()
    assert d.init().success and d.switch_mode([J1], 3).success
    cycle = d._cycle
    real_stop = cycle.stop
    asked = []

    def stop_after_a_late_enable(*args, **kwargs):
        # what the end of Lifecycle._switch_steps does, after shutdown's disable
        asked.append(cycle.go([J1], State.OPERATION_ENABLED, timeout=0.5))
        return real_stop(*args, **kwargs)
    cycle.stop = stop_after_a_late_enable
    rig.drain()
    r = d.shutdown()
    assert r.success, r.message
    assert asked and asked[0] is not None  # the enable was not reached
    assert rig.state() == State.SWITCH_ON_DISABLED
    words = _controlwords(rig, 0x201)
    assert words and not any(w & 0x000F == 0x000F for w in words[words.index(CW_DISABLE_VOLTAGE):]), \
        ["0x%04X" % w for w in words]


def _rxpdos_stop_reaching(rig, node_id):
    """The drive takes none of the driver's RxPDOs any more (its receive
    mapping changed by another tool, or frames lost on the way); its
    TxPDOs, heartbeat and SDO server run on. The cycle still hears it, so
    shutdown first tries to stop it through the cycle."""
    rig.sim.nodes[node_id]._on_rpdo = lambda rpdo, data, now: None


@pytest.mark.parametrize("how", ["shutdown", "close"])
def test_a_drive_that_takes_no_rxpdo_is_stopped_over_sdo_within_the_deadline(rig, how):
    """Quick stop through the cycle is never confirmed by a drive that
    takes no RxPDO. Shutdown must not spend its whole deadline waiting for
    that: the drive still turning is stopped and disabled over SDO, as a
    drive the cycle does not hear would be."""
    d = _two_drives_turning(rig)
    rig.drain()
    _rxpdos_stop_reaching(rig, 1)
    start = rig.clock.now()
    answer = d.shutdown() if how == "shutdown" else None
    if answer is None:
        d.close()
    message = answer.message if answer is not None else ""
    took = rig.clock.now() - start
    assert took <= SHUTDOWN_DEADLINE, "%s took %.3f s of the clock: %s" % (how, took, message)
    # the SDO way had time for it: nothing was cut short by the deadline
    assert answer is None or answer.success, message
    for node in (1, 2):
        assert rig.read(0x606C, node=node) == 0, (node, message)
        assert rig.state(node=node) == State.SWITCH_ON_DISABLED, (node, rig.state(node=node), message)
    nmt = rig.sent(0x000)
    assert b"\x02\x01" in nmt and b"\x02\x02" in nmt, nmt
