"""One joint's cycle without a bus: statuswords in (as TxPDO bytes), the
RxPDO frames the cycle sends out. Covers the CiA 402 transitions the driver
commands and the profile position handshake, frame by frame."""
import math
import os
import struct
import time

import pytest

from maxon_epos4_ros_canopen.cia402 import State
from maxon_epos4_ros_canopen.config import load_config
from maxon_epos4_ros_canopen.driver.axis import Axis, Binding, holding_controlword
from maxon_epos4_ros_canopen.driver.outputs import REFRESH_CYCLES
from maxon_epos4_ros_canopen.driver.pdo import RxPdo, TpdoReceiver, TxPdo, enabled_maps
from maxon_epos4_ros_canopen.driver.plan import plan_node
from maxon_epos4_ros_canopen.limits import JointLimits
from maxon_epos4_ros_canopen.objects import load_dictionary

DCF = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "config", "epos4_node1.dcf")

# Statuswords as the EPOS4 (and the virtual EPOS4) send them: remote (bit 9),
# target reached (bit 10), referenced (bit 15) besides the state bits.
SW_SWITCH_ON_DISABLED = 0x0240
SW_READY = 0x0221
SW_SWITCHED_ON = 0x0233
SW_ENABLED = 0x0637
SW_ENABLED_ACK = 0x1637        # profile position: set-point acknowledge
SW_FAULT = 0x0208
SW_QUICK_STOP = 0x0617


class Harness:
    """One axis fed with TPDO frames through the receiver, as the CAN
    notifier would; what it sends is recorded frame by frame."""

    def __init__(self, configured_at=0.0, receive_times=None, **node):
        params = {"sync": {"interval_ms": 10},
                  "nodes": {"n1": dict({"id": 1, "name": "j", "eds_file": DCF, "pos_to_device": "pos",
                                        "pos_from_device": "obj6064", "vel_to_device": "vel",
                                        "vel_from_device": "obj606C"}, **node)}}
        cfg = load_config(params, "test")
        od = load_dictionary(DCF, 1)  # parsed once for every test, as the driver's
        plan = plan_node(cfg.nodes[0], od, cfg.sync, "test")
        rx = tuple(RxPdo(od, m) for m in enabled_maps(plan.rx))
        tx = tuple(TxPdo(od, m) for m in enabled_maps(plan.tx))
        self.axis = Axis(cfg.nodes[0], od, plan, JointLimits())
        self.axis.attach(Binding(rx, tx, {k: 0 for r in rx for k in r.keys}, {}, 0, 0, configured_at), 0, 0.0)
        self.receiver = TpdoReceiver({t.cob_id: t.length for t in tx}, *([receive_times] if receive_times else []))
        self.payload = {0x181: struct.pack("<Hb", SW_SWITCH_ON_DISABLED, 1), 0x281: struct.pack("<ii", 0, 0),
                        0x381: struct.pack("<ii", 0, 0)}
        self.frames = []
        self.last = {}
        self.n = 0

    def tpdo(self, sw=None, mode=None, pos=None, vel=None):
        """What the drive's TxPDOs 1-3 carry (mapping of the project's DCF)."""
        if sw is not None:
            old_mode = struct.unpack_from("<b", self.payload[0x181], 2)[0]
            self.payload[0x181] = struct.pack("<Hb", sw, mode if mode is not None else old_mode)
        if vel is not None:
            self.payload[0x281] = struct.pack("<ii", 0, vel)
        if pos is not None:
            self.payload[0x381] = struct.pack("<ii", pos, 0)

    def cycle(self, **tpdo):
        self.n += 1
        if tpdo:
            self.tpdo(**tpdo)
        for cob, data in self.payload.items():
            self.receiver.on_frame(cob, data, 0.0)  # a fresh frame every SYNC
        self.axis.read(self.receiver, float(self.n), self.n)
        sent = []
        self.axis.write(lambda cob, data: sent.append((cob, data)))
        self.frames.extend(sent)
        self.last.update(sent)
        return dict(sent)

    def controlword(self):
        return struct.unpack_from("<H", self.last[0x201])[0]

    def target(self):
        return struct.unpack_from("<i", self.last[0x301])[0]


@pytest.fixture
def h():
    return Harness()


def test_enable_walks_the_state_machine(h):
    j = h.axis
    j.request_state(State.OPERATION_ENABLED)
    expected = [(SW_SWITCH_ON_DISABLED, 0x0006), (SW_READY, 0x0007), (SW_SWITCHED_ON, 0x000F)]
    for sw, cw in expected:
        h.cycle(sw=sw)
        assert h.controlword() == cw, hex(sw)
    h.cycle(sw=SW_ENABLED)
    assert j.state == State.OPERATION_ENABLED and j.error is None
    assert h.controlword() & 0x000F == 0x000F


def test_fault_reset_only_when_asked_and_as_a_rising_edge(h):
    j = h.axis
    j.request_state(State.OPERATION_ENABLED)
    h.cycle(sw=SW_FAULT)
    assert h.controlword() == 0x0000  # no fault reset unless recover/init asks
    j.request_state(State.OPERATION_ENABLED, fault_reset=True)
    words = []
    for _ in range(4):
        h.cycle(sw=SW_FAULT)
        words.append(h.controlword())
    assert words == [0x0080, 0x0000, 0x0080, 0x0000]
    h.cycle(sw=SW_SWITCH_ON_DISABLED)
    assert h.controlword() == 0x0006


def test_leaving_the_reached_state_is_an_error_not_a_retry(h):
    j = h.axis
    j.request_state(State.OPERATION_ENABLED)
    for sw in (SW_SWITCH_ON_DISABLED, SW_READY, SW_SWITCHED_ON, SW_ENABLED):
        h.cycle(sw=sw, pos=1234)
    h.cycle(sw=SW_QUICK_STOP, pos=1300)
    assert j.error and "quick_stop_active" in j.error
    assert j.target_state is None and j.halted
    h.cycle(sw=SW_SWITCH_ON_DISABLED)
    # quick stop: neither re-enables by itself (no shutdown 0x0006, no enable
    # operation) nor cuts the power of a drive that may move (no 0x0000)
    assert h.controlword() == 0x0002


def ppm_enabled(h):
    j = h.axis
    j.request_state(State.OPERATION_ENABLED)
    for sw in (SW_SWITCH_ON_DISABLED, SW_READY, SW_SWITCHED_ON, SW_ENABLED):
        h.cycle(sw=sw, mode=1, pos=500)
    j.ready = True
    j.active_mode = 1
    j.hold(500)
    # the hold targets go out (halt bit on), then the held position goes
    # through the handshake once, and the halt bit drops after it
    for sw in (SW_ENABLED, SW_ENABLED, SW_ENABLED, SW_ENABLED_ACK, SW_ENABLED):
        h.cycle(sw=sw)
    assert h.controlword() == 0x002F
    h.frames.clear()
    return j


def test_profile_position_handshake_frame_by_frame(h):
    j = ppm_enabled(h)
    assert j.apply_command("position", 1000).success
    out = h.cycle(sw=SW_ENABLED)
    # 1: the target goes out first (RxPDO 2 = 0x607A + 0x6081), no edge yet
    assert struct.unpack_from("<i", out[0x301])[0] == 1000
    assert h.controlword() & 0x0010 == 0
    # 2: new set-point edge with change set immediately
    h.cycle(sw=SW_ENABLED)
    assert h.controlword() & 0x0030 == 0x0030
    # 3: held until the drive acknowledges
    h.cycle(sw=SW_ENABLED)
    assert h.controlword() & 0x0010
    h.cycle(sw=SW_ENABLED_ACK)
    assert h.controlword() & 0x0010 == 0
    # a new target waits for the acknowledge to drop
    assert j.apply_command("position", 2000).success
    h.cycle(sw=SW_ENABLED_ACK)
    assert h.target() == 1000
    h.cycle(sw=SW_ENABLED)
    assert h.target() == 2000


def test_controlword_pdo_every_cycle_others_on_change_and_refresh(h):
    ppm_enabled(h)
    h.cycle(sw=SW_ENABLED)
    h.cycle(sw=SW_ENABLED)
    assert [cob for cob, _ in h.frames] == [0x201, 0x201]
    h.frames.clear()
    for _ in range(REFRESH_CYCLES):
        h.cycle(sw=SW_ENABLED)
    cobs = [cob for cob, _ in h.frames]
    assert cobs.count(0x201) == REFRESH_CYCLES
    assert cobs.count(0x301) == cobs.count(0x401) == cobs.count(0x501) == 1


def test_cyclic_target_goes_out_every_cycle(h):
    j = h.axis
    j.request_state(State.OPERATION_ENABLED)
    for sw in (SW_SWITCH_ON_DISABLED, SW_READY, SW_SWITCHED_ON, SW_ENABLED):
        h.cycle(sw=sw, mode=8, pos=0)
    j.ready, j.active_mode = True, 8
    assert j.apply_command("position", 10).success
    for _ in range(3):
        out = h.cycle(sw=SW_ENABLED)
        assert struct.unpack_from("<i", out[0x301])[0] == 10


def test_halt_sets_bit_8_and_refuses_commands(h):
    j = ppm_enabled(h)
    j.halted = True
    h.cycle(sw=SW_ENABLED)
    assert h.controlword() & 0x0100
    r = j.apply_command("position", 5)
    assert not r.success and "halted" in r.message


def test_a_tpdo_that_arrived_before_the_drive_was_configured_is_not_taken_however_late_it_is_read():
    """A receive backlog (a loaded host) hands the cycle frames late: one
    that reached the host before the drive was (re)configured, by init or
    recover, tells of the drive before that, however late it is read.
    Taken, a statusword of before recover put the joint back in error."""
    times = [(100.0, 50.0)]  # (read, arrived): read after the configuration at 60 s, arrived before it
    h = Harness(configured_at=60.0, receive_times=lambda: times[0])
    h.cycle(sw=SW_QUICK_STOP)
    assert h.axis.state is None and h.axis.error is None
    times[0] = (101.0, 61.0)
    h.cycle(sw=SW_SWITCH_ON_DISABLED)
    assert h.axis.state == State.SWITCH_ON_DISABLED


def test_a_statusword_that_arrived_before_a_state_request_does_not_confirm_it():
    """A receive backlog hands the cycle statuswords seconds after they
    arrived: one that arrived before a state was requested says nothing of
    the drive's answer to the request. Taken, `recover` answered
    "recovered" for a drive that had quick-stopped meanwhile."""
    lag = [0.0]
    h = Harness(receive_times=lambda: (time.monotonic(), time.monotonic() - lag[0]))
    h.cycle(sw=SW_SWITCH_ON_DISABLED)
    lag[0] = 5.0   # what is read from now on arrived 5 s ago, before the request
    h.axis.request_state(State.OPERATION_ENABLED)
    h.cycle(sw=SW_ENABLED)
    h.cycle(sw=SW_ENABLED)
    assert h.axis.target_state == State.OPERATION_ENABLED
    assert h.axis.held_state != State.OPERATION_ENABLED
    lag[0] = 0.0   # the backlog is read: the drive's own answer
    h.cycle(sw=SW_ENABLED)
    assert h.axis.target_state is None
    assert h.axis.held_state == State.OPERATION_ENABLED


def test_readings_follow_the_from_device_expressions():
    h = Harness(pos_from_device="obj6064/2", vel_from_device="smooth(obj606C, vel, 0.5)")
    h.cycle(pos=1000, vel=100)
    assert h.axis.position == 500
    assert h.axis.velocity == 100      # the first value passes (old is NaN)
    h.cycle(vel=200)
    assert h.axis.velocity == 150
    assert math.isclose(h.axis.effort, 0.0)


def test_short_pdo_keeps_the_last_readings(h):
    h.cycle(pos=1000)
    h.payload[0x381] = b"\x01"
    h.cycle()
    assert h.axis.position == 1000
    assert h.axis.counters["bad_tpdo"] == 1


def test_a_short_frame_overtaken_by_a_good_one_is_still_counted(h):
    # a forger's short TPDO followed by the drive's own before the cycle reads:
    # the short one must neither replace the last good frame nor go unseen
    h.cycle(pos=1000)
    h.receiver.on_frame(0x381, b"\x01", 0.0)
    assert h.receiver.latest(0x381)[0] == struct.pack("<ii", 1000, 0)
    h.cycle(pos=1200)
    assert h.axis.position == 1200
    assert h.axis.counters["bad_tpdo"] == 1


def enabled(h, mode=1):
    j = h.axis
    j.request_state(State.OPERATION_ENABLED)
    for sw in (SW_SWITCH_ON_DISABLED, SW_READY, SW_SWITCHED_ON, SW_ENABLED):
        h.cycle(sw=sw, mode=mode, pos=0)
    j.ready = True
    j.set_mode(mode, 0)
    return j


def test_one_forged_fault_statusword_never_cuts_the_power(h):
    j = enabled(h, mode=3)
    assert j.apply_command("velocity", 900).success
    h.cycle(sw=SW_ENABLED, vel=900)
    h.cycle(sw=SW_FAULT)              # one frame says fault
    assert j.error and "fault" in j.error
    words = [h.controlword()]
    for _ in range(5):                # the drive goes on reporting enabled
        h.cycle(sw=SW_ENABLED)
        words.append(h.controlword())
    # no disable voltage (0x0000) nor any other power-off: halt bit, enabled
    assert words == [0x010F] * 6
    assert not j.apply_command("velocity", 900).success


def test_a_forged_position_never_becomes_a_target(h):
    j = enabled(h, mode=8)
    assert j.apply_command("position", 100).success
    h.cycle(sw=SW_ENABLED, pos=100)
    assert h.target() == 100
    h.cycle(sw=SW_ENABLED, pos=798396)         # forged TxPDO3
    j.inputs.on_heartbeat(b"\x04", 100.0, j.ready)  # then a STOPPED heartbeat
    j.watch(100.0, h.n, 0.01, 1.5, 50)
    assert j.error and "STOPPED" in j.error
    for _ in range(3):
        h.cycle(sw=SW_ENABLED)
        assert h.target() == 100               # the last target the driver sent


@pytest.mark.parametrize("frame, counter", [
    (b"\x78", "undefined_nmt_state"), (b"", "bad_heartbeat"), (b"\x05\x00", "bad_heartbeat")])
def test_odd_heartbeats_are_counted_not_taken(h, frame, counter):
    j = enabled(h)
    j.inputs.on_heartbeat(frame, 50.0, j.ready)
    assert j.counters[counter] == 1 and j.snapshot().nmt_state == "OPERATIONAL"


def test_undefined_statusword_and_short_emcy_are_counted(h):
    j = enabled(h)
    h.cycle(sw=0x0003)                 # no CiA 402 state has these bits
    assert j.counters["undefined_statusword"] == 1 and j.state == State.OPERATION_ENABLED and not j.error
    j.inputs.on_emcy(b"\x10")
    assert j.counters["bad_emcy"] == 1


def test_readings_are_nan_until_the_tpdo_a_conversion_reads_has_come():
    h = Harness()
    del h.payload[0x381]                 # the statusword came, the position not yet
    h.cycle(sw=SW_SWITCH_ON_DISABLED)
    assert h.axis.state == State.SWITCH_ON_DISABLED
    assert math.isnan(h.axis.position)
    h.payload[0x381] = struct.pack("<ii", 1234, 0)
    h.cycle()
    assert h.axis.position == 1234


@pytest.mark.parametrize("sw, cw", [(SW_SWITCH_ON_DISABLED, 0x0000), (SW_READY, 0x0006), (SW_SWITCHED_ON, 0x0007),
                                    (SW_ENABLED, 0x000F), (SW_QUICK_STOP, 0x0002), (SW_FAULT, 0x0000),
                                    (0x0018, 0x0000)])
def test_the_first_controlword_holds_the_state_the_drive_is_in(sw, cw):
    # a drive its consumer quick-stopped still has 0x000F in 0x6040: sending
    # that again would re-enable it, so the state decides, never 0x6040
    assert holding_controlword(sw) == cw


def walk_to_enabled(h):
    h.axis.request_state(State.OPERATION_ENABLED)
    for sw in (SW_SWITCH_ON_DISABLED, SW_READY, SW_SWITCHED_ON, SW_ENABLED):
        h.cycle(sw=sw)
    assert h.axis.held_state == State.OPERATION_ENABLED


@pytest.mark.parametrize("sw", [SW_QUICK_STOP, SW_SWITCHED_ON, SW_READY, SW_SWITCH_ON_DISABLED])
def test_a_drive_that_stopped_on_its_own_is_never_enabled_again_by_the_driver(h, sw):
    """A drive its own consumer (0x6007) or input quick-stopped must stay
    stopped: enable operation (0x000F, halted or not) would take Quick Stop
    Active back to Operation Enabled (transition 16, option codes 5-8) and
    Switched On to Operation Enabled. Quick stop is no transition in any of
    these states, and on a drive that is still enabled (a lying frame) it
    is a ramp to rest, never a coast."""
    walk_to_enabled(h)
    for _ in range(5):
        h.cycle(sw=sw)
        assert h.controlword() & 0x0F != 0x0F, hex(h.controlword())
    assert h.controlword() & 0x8F == 0x0002
    assert h.axis.error


def test_after_clearing_an_error_the_first_controlword_holds_what_the_drive_said_by_sdo(h):
    """recover clears an error while PDOs may be stale (a drive that left
    OPERATIONAL sent none): until a fresh statusword comes, the controlword
    holds the state read over SDO, not the one held before the error."""
    walk_to_enabled(h)
    h.axis.set_error("bus error")
    h.cycle(sw=SW_ENABLED)
    h.axis.clear_error(SW_QUICK_STOP)
    h.axis.request_state(State.OPERATION_ENABLED, fault_reset=True)
    h.axis.write(lambda cob, data: h.last.update({cob: data}))   # before any fresh statusword
    assert h.controlword() & 0x8F == 0x0002
    h.cycle(sw=SW_QUICK_STOP)
    assert h.controlword() == 0x000F  # from quick stop active by transition 16 (0x605A = 6)


def test_an_rxpdo_value_goes_out_once_when_it_changes_and_again_with_each_refresh(h):
    # The cycle packs a PDO again only when a value in it changed: what goes
    # out must still be the current values, on change and on refresh.
    from maxon_epos4_ros_canopen.objects import ObjectKey
    ppm_enabled(h)
    h.axis.set_output(ObjectKey(0x6083), 1234)
    out = h.cycle(sw=SW_ENABLED)
    assert struct.unpack_from("<I", out[0x401])[0] == 1234
    h.axis.set_output(ObjectKey(0x6083), 1234)       # the same value: nothing new to send
    sent = [h.cycle(sw=SW_ENABLED) for _ in range(REFRESH_CYCLES)]
    refreshes = [o[0x401] for o in sent if 0x401 in o]
    assert len(refreshes) == 1 and struct.unpack_from("<I", refreshes[0])[0] == 1234
    h.axis.set_output(ObjectKey(0x6084), 99)
    out = h.cycle(sw=SW_ENABLED)
    assert struct.unpack("<II", out[0x401]) == (1234, 99)
    # the controlword PDO, sent every cycle from its last frame when nothing
    # in it changed, follows a change at once
    h.axis.halted = True
    out = h.cycle(sw=SW_ENABLED)
    assert struct.unpack_from("<H", out[0x201])[0] & 0x0100


def test_a_snapshot_keeps_its_values_after_the_axis_moves_on():
    h = Harness(pos_from_device="obj6064")
    h.cycle(sw=SW_SWITCH_ON_DISABLED, pos=100)
    before = h.axis.snapshot()
    h.cycle(pos=200)
    h.axis.counters.add("bad_tpdo")
    after = h.axis.snapshot()
    assert (before.position, before.raw_position, before.counters["bad_tpdo"]) == (100, 100, 0)
    assert (after.position, after.raw_position, after.counters["bad_tpdo"]) == (200, 200, 1)
    assert type(after).__name__ == "AxisSnapshot" and after.name == "j" and after.key == "n1"
    with pytest.raises(AttributeError):
        after.position = 5


def test_a_drive_out_of_sight_is_held_with_quick_stop(h):
    """No statusword for longer than the watchdog (a drive its consumer sent
    to pre-operational sends none): its state is unknown, and it must not be
    re-enabled by the held enable operation the moment it takes PDOs again
    (an NMT start by anyone). Quick stop holds every state it may be in."""
    walk_to_enabled(h)
    h.axis.ready = True
    h.axis.watch(now=time.monotonic() + 100.0, cycle=h.n + 200, period=0.01, pdo_timeout=1.0, pdo_cycles=50)
    assert "no statusword" in h.axis.error
    h.axis.write(lambda cob, data: h.last.update({cob: data}))
    assert h.controlword() & 0x8F == 0x0002


def test_an_emcy_storm_is_a_few_log_lines_a_second_and_a_count(h, caplog):
    # forged EMCYs with every code: the cycle thread writes the log lines,
    # and a storm of them would starve it
    with caplog.at_level("INFO", logger="maxon_epos4_ros_canopen.driver"):
        for code in range(1, 201):
            h.axis.inputs.on_emcy(struct.pack("<HB5s", code, 0x01, bytes(5)), now=5.0)
            h.axis.inputs.on_emcy(bytes(8), now=5.0)   # and error resets
    lines = [r for r in caplog.records if "EMCY" in r.getMessage()]
    assert 1 <= len(lines) <= 5
    assert h.axis.counters["emcy_not_logged"] == 400 - len(lines)
    caplog.clear()
    with caplog.at_level("INFO", logger="maxon_epos4_ros_canopen.driver"):
        h.axis.inputs.on_emcy(struct.pack("<HB5s", 0x8611, 0x81, bytes(5)), now=6.5)  # a second later: logged
    assert any("0x8611" in r.getMessage() for r in caplog.records)
