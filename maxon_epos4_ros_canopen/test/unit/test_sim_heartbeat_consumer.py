"""Heartbeat consumer (0x1016) of the virtual EPOS4: a master that goes
silent makes the drive send EMCY 0x8130 and apply the abort connection
option code (0x6007) and the NMT error behaviour (0x1029)."""
import struct

import can
import pytest
from canopen.sdo.exceptions import SdoAbortedError

from maxon_epos4_ros_canopen.clock import REAL
from sim_support import NODE1, NODE2, NodeConfig, RampRecorder, spin_up

MASTER = 0x7F
TIMEOUT_MS = 100
# test_a_simulator_that_falls_behind_judges_the_master_by_when_its_heartbeats_
# arrived: the consumer time there, the SYNCs queued behind each of the
# master's heartbeats and what each costs the starved loop (2 s between two
# heartbeats, more than the consumer time). The heartbeats go out a few ms
# apart; a host would have to hold the sending thread for the consumer time
# to make that a real loss (the test checks it did not): 1.5 s, which a
# load average of 20 on two cores held it short of (568 ms was seen).
BEHIND_CONSUMER_MS = 1500
BEHIND_SYNCS = 400
BEHIND_HANDLE_S = 0.005
BEHIND_HEARTBEATS = 2
# The stall tests (test_a_stall_...): the consumer time, generous because
# the master's heartbeat there comes from a thread of this process, which a
# loaded host may hold too; and the stall of the simulating host they model,
# three consumer times.
STALL_CONSUMER_MS = 500
HOST_STALL = 3 * STALL_CONSUMER_MS / 1000.0
HEARTBEAT_LOST = struct.pack("<HB5s", 0x8130, 0x11, bytes(5))  # generic + communication
QUICK_STOP_DECEL = 2000  # rpm/s
PROFILE_DECEL = 6000


@pytest.fixture
def rig(sim_rig):
    return sim_rig([NodeConfig(1, NODE1), NodeConfig(2, NODE2)])


@pytest.fixture
def real_rig(sim_rig):
    """The simulator's own loop thread on the wall clock: for the tests of
    how that loop meets a host that stalls it (docs/testing.md)."""
    return sim_rig([NodeConfig(1, NODE1), NodeConfig(2, NODE2)], clock=REAL)


class Master:
    """The master's heartbeat producer: 0x77F [05] every 20 ms until stop()."""

    def __init__(self, rig, node_id=MASTER):
        msg = can.Message(arbitration_id=0x700 + node_id, data=b"\x05", is_extended_id=False)
        self.task = rig.send_periodic(msg, 0.02)

    def stop(self):
        self.task.stop()


def _watch_master(node, sub=1, timeout_ms=TIMEOUT_MS):
    node.sdo[0x1016][sub].raw = (MASTER << 16) | timeout_ms


def _is_emcy(msg, node_id=1):
    return msg.arbitration_id == 0x80 + node_id and bytes(msg.data) == HEARTBEAT_LOST


def _lose_master_while_turning(rig, settings):
    """Node 1 turning at 1000 rpm and watching the master, ``settings``
    ({(index, sub): value}) written first; then the master's heartbeat stops
    and the EMCY must come. Returns the node."""
    node = rig.remote(1)
    for (index, sub), value in settings.items():
        (node.sdo[index][sub] if sub else node.sdo[index]).raw = value
    _watch_master(node)
    master = Master(rig)
    spin_up(node, rig)
    rig.drain()
    master.stop()
    assert rig.expect(_is_emcy)
    return node


def test_the_drive_has_two_consumer_entries_off_by_default(rig):
    node = rig.remote(1)
    assert node.sdo[0x1016][0].raw == 2
    assert node.sdo[0x1016][1].raw == 0 and node.sdo[0x1016][2].raw == 0
    assert node.sdo[0x6007].raw == 3  # quick stop, maxon's default
    assert node.sdo[0x1029][1].raw == 0  # communication error: to pre-operational


def test_master_loss_quick_stops_with_the_quick_stop_deceleration(rig):
    node = rig.remote(1)
    node.sdo[0x6084].raw = PROFILE_DECEL
    node.sdo[0x6085].raw = QUICK_STOP_DECEL
    node.sdo[0x1029][1].raw = 1  # stay operational, so TxPDO3 shows the ramp
    _watch_master(node)
    master = Master(rig)
    spin_up(node, rig)
    recorder = RampRecorder(rig)
    try:
        rig.drain()
        master.stop()
        samples = recorder.record_until_rest()
    finally:
        recorder.stop()
    emcy = [i for i, m in enumerate(recorder.frames) if _is_emcy(m)]
    assert len(emcy) == 1
    assert samples[-1][1] == 0
    assert recorder.deceleration() == pytest.approx(QUICK_STOP_DECEL, rel=0.15)
    assert node.sdo[0x6041].raw == 0x0617  # quick stop active, target reached (0x605A = 6)
    assert node.sdo[0x603F].raw == 0x8130
    assert node.sdo[0x1003][1].raw == 0x8130
    assert node.sdo[0x1001].raw == 0x11


def test_default_error_behaviour_leaves_operational_and_stops_the_motor(rig):
    node = rig.remote(1)
    node.sdo[0x1017].raw = 20
    _watch_master(node)
    master = Master(rig)
    spin_up(node, rig)
    rig.send(0x000, bytes([0x01, 1]))
    assert rig.expect(lambda m: m.arbitration_id == 0x701 and m.data[0] == 0x05)
    master.stop()
    assert rig.expect(_is_emcy)
    assert rig.expect(lambda m: m.arbitration_id == 0x701 and m.data[0] == 0x7F)
    assert rig.wait(lambda: node.sdo[0x606C].raw == 0)
    assert node.sdo[0x6041].raw & 0x6F == 0x07  # quick stop active


def test_supervision_starts_with_the_first_heartbeat(rig):
    node = rig.remote(1)
    _watch_master(node)
    spin_up(node, rig)
    rig.drain()
    frames = rig.collect(5 * TIMEOUT_MS / 1000.0)  # no master heartbeat yet: nothing to miss
    assert not [m for m in frames if _is_emcy(m)]
    assert node.sdo[0x6041].raw & 0x6F == 0x27
    master = Master(rig)
    assert rig.wait(lambda: node.sdo[0x6041].raw & 0x6F == 0x27)
    master.stop()
    assert rig.expect(_is_emcy)


def test_option_1_is_a_fault_with_the_fault_reaction(rig):
    # fault reaction 1: profile deceleration
    node = _lose_master_while_turning(rig, {(0x6007, 0): 1, (0x605E, 0): 1})
    assert rig.wait(lambda: node.sdo[0x6041].raw == 0x0218)  # fault
    assert abs(node.sdo[0x606C].raw) < 5
    node.sdo[0x6040].raw = 0x0000
    node.sdo[0x6040].raw = 0x0080
    assert node.sdo[0x6041].raw == 0x0250 and node.sdo[0x603F].raw == 0


def test_option_2_disables_voltage_at_once(rig):
    node = _lose_master_while_turning(rig, {(0x6007, 0): 2})
    assert rig.wait(lambda: node.sdo[0x6041].raw == 0x0250)
    assert node.sdo[0x606C].raw > 500  # power stage off: the motor coasts


def test_option_0_only_reports_and_supervision_rearms(rig):
    node = _lose_master_while_turning(rig, {(0x6007, 0): 0, (0x1029, 1): 1})
    assert node.sdo[0x6041].raw & 0x6F == 0x27
    assert node.sdo[0x606C].raw > 950  # still turning: no action
    # a fault reset edge clears the error that needed no FAULT state
    node.sdo[0x6040].raw = 0x008F
    node.sdo[0x6040].raw = 0x000F
    assert node.sdo[0x603F].raw == 0 and node.sdo[0x1001].raw == 0
    master = Master(rig)  # the master is back: the entry arms again
    rig.drain()
    # half a second of the drive's time with the master's heartbeats coming: no error reset EMCY
    assert not [m for m in rig.handled(0.5) if m.arbitration_id == 0x081 and bytes(m.data) == bytes(8)]
    master.stop()
    assert rig.expect(_is_emcy)


def test_each_node_watches_only_its_own_entries(rig):
    node1, node2 = rig.remote(1), rig.remote(2, NODE2)
    _watch_master(node1, sub=2)
    master = Master(rig)
    spin_up(node1, rig)
    spin_up(node2, rig)
    rig.drain()
    master.stop()
    assert rig.expect(_is_emcy)
    assert rig.wait(lambda: node1.sdo[0x606C].raw == 0)
    assert node2.sdo[0x6041].raw & 0x6F == 0x27 and node2.sdo[0x606C].raw > 950


def test_a_node_is_watched_by_one_entry_only(rig):
    node = rig.remote(1)
    _watch_master(node, sub=1)
    with pytest.raises(SdoAbortedError) as err:
        node.sdo[0x1016][2].raw = (MASTER << 16) | 500
    assert err.value.code == 0x06040043
    node.sdo[0x1016][2].raw = (0x05 << 16) | 500  # another node is fine
    node.sdo[0x1016][1].raw = 0  # 0 switches an entry off
    assert node.sdo[0x1016][1].raw == 0


def test_reset_communication_restores_the_dcf_entries(rig):
    node = rig.remote(1)
    _watch_master(node)
    master = Master(rig)
    spin_up(node, rig)
    rig.send(0x000, bytes([0x82, 1]))
    assert rig.wait(lambda: node.sdo[0x1016][1].raw == 0)
    rig.drain()
    master.stop()
    frames = rig.collect(5 * TIMEOUT_MS / 1000.0)
    assert not [m for m in frames if _is_emcy(m)]
    assert node.sdo[0x6041].raw & 0x6F == 0x27


def test_a_drive_cut_off_the_bus_stops_on_its_own(rig):
    """A silent drive hears no heartbeat either: its consumer trips while it
    is cut off, and it ramps to rest before anyone can talk to it again (the
    EMCY is lost, nobody hears it)."""
    node = rig.remote(1)
    _watch_master(node)
    master = Master(rig)
    spin_up(node, rig)
    rig.sim.inject_fault(1, "silent")
    assert rig.wait(lambda: rig.sim.read(1, 0x606C) == 0)
    assert rig.sim.read(1, 0x6041) & 0x6F == 0x07  # quick stop active (0x6007 = 3)
    rig.drain()
    rig.sim.inject_fault(1, "clear")
    assert rig.wait(lambda: node.sdo[0x6041].raw & 0x6F == 0x07)
    assert not [m for m in rig.handled(0.2) if _is_emcy(m)]
    master.stop()


def test_a_sync_that_finds_the_master_lost_applies_no_rxpdo_received_before(rig):
    """The drive advances at each SYNC before it applies the synchronous
    RxPDOs received since the last one. When that advance finds the master
    lost (quick stop, 0x1029: pre-operational), the buffered RxPDO, the
    master's routine enable operation sent before it knew, must not be
    applied: a pre-operational drive takes no PDOs, and enable operation
    would take Quick Stop Active back to Operation Enabled (transition 16,
    0x605A = 6) at the old target velocity."""
    node = rig.remote(1)
    _watch_master(node)  # 100 ms
    master = Master(rig)
    spin_up(node, rig, 1000)
    rig.send(0x000, bytes([0x01, 1]))  # operational: RxPDOs count
    assert rig.wait(lambda: rig.sim.nodes[1].nmt_state == 0x05)
    master.stop()

    def cycles_without_the_masters_heartbeat():
        # in the loop thread, so nothing else runs in between: 10 ms cycles
        # of the master (RxPDO 1 with enable operation and the same target,
        # then SYNC) while its heartbeats are missing; one of the SYNCs
        # finds the consumer time run out
        drive = rig.sim.nodes[1]
        rpdo = next(p for p in drive.pdos.rpdos if p.valid and (0x6040, 0) in p.keys)
        values = dict(drive.store.values)
        values[(0x6040, 0)] = 0x000F
        data = rpdo.pack(values)
        t = rig.sim.bus_time
        for _ in range(50):
            drive.on_frame(rpdo.cob_id, data, False, drive.t)
            t += 0.01
            rig.sim.bus_time = t  # the SYNC's arrival, as the loop would note it
            drive.on_sync(max(t, drive.t + 0.01))
    rig.sim.call(cycles_without_the_masters_heartbeat)
    assert rig.sim.nodes[1].nmt_state == 0x7F  # pre-operational (0x1029 sub 1 = 0)
    assert rig.wait(lambda: node.sdo[0x606C].raw == 0)
    assert node.sdo[0x6041].raw & 0x6F == 0x07  # still quick stop active


def test_a_simulator_that_falls_behind_judges_the_master_by_when_its_heartbeats_arrived(real_rig):
    """A real drive never falls behind the bus; the simulating process can,
    on a loaded host, with frames waiting in its socket. Its consumer must
    judge by when each heartbeat reached it, not by when its loop got to
    it: the master's heartbeats, a few ms apart on the bus, must not count
    as a master loss because the SYNCs queued between them took the loop
    longer than the consumer time to work through. A master that really
    stops is still noticed. (The master's heartbeats go on until the loop
    has caught up and the test has looked: the EMCY of the master that
    stops at the end cannot be taken for one during the backlog.)"""
    rig = real_rig
    import time

    node = rig.remote(1)
    _watch_master(node, timeout_ms=BEHIND_CONSUMER_MS)
    master = Master(rig)
    spin_up(node, rig)
    rig.send(0x000, bytes([0x01, 1]))  # operational: every SYNC advances the drive
    assert rig.wait(lambda: rig.sim.nodes[1].nmt_state == 0x05)
    handle = rig.sim._route  # where the loop hands each received frame to the nodes

    def slow_handle(cob, data, remote, now):  # a starved loop: BEHIND_HANDLE_S for every frame
        time.sleep(BEHIND_HANDLE_S)
        handle(cob, data, remote, now)
    rig.sim._route = slow_handle
    heartbeat = can.Message(arbitration_id=0x700 + MASTER, data=b"\x05", is_extended_id=False)
    sync = can.Message(arbitration_id=0x080, data=b"", is_extended_id=False)
    before, after = [], []   # time.time() around each heartbeat's send (the bus stamps it in between)
    start = rig.sim.frames_in
    for i in range(BEHIND_HEARTBEATS + 1):
        before.append(time.time())
        rig.raw.send(heartbeat)
        after.append(time.time())
        if i == 0:
            master.stop()  # from here on this thread sends the heartbeats, each behind the SYNCs
        if i == BEHIND_HEARTBEATS:
            break
        for _ in range(BEHIND_SYNCS):  # each SYNC advances the drive
            rig.raw.send(sync)
    master = Master(rig)  # the heartbeats go on (the first at once) while the loop works off its backlog
    sent = BEHIND_HEARTBEATS * (BEHIND_SYNCS + 1) + 1
    gaps = [b - a for a, b in zip(before, after[1:])]
    assert max(gaps) < BEHIND_CONSUMER_MS / 1000.0, (
        "the host held this thread %.0f ms between two heartbeats: a real loss of the master" % (max(gaps) * 1000))
    assert rig.wait(lambda: rig.sim.frames_in >= start + sent, timeout=60.0)  # the loop worked off its backlog
    rig.sim._route = handle
    assert rig.sim.read(1, 0x6041) & 0x6F == 0x27, "the drive left operation enabled"
    emcys = [m for m in rig.handled() if _is_emcy(m)]
    assert not emcys, "EMCY 0x8130 while the master's heartbeats were on the bus"
    master.stop()
    assert rig.expect(_is_emcy, timeout=5.0), "a master that stopped was not noticed"


def _operational_under_a_master(rig) -> Master:
    """Node 1 turning, operational, watching the master's heartbeat
    (STALL_CONSUMER_MS); no frame recorded yet."""
    node = rig.remote(1)
    _watch_master(node, timeout_ms=STALL_CONSUMER_MS)
    master = Master(rig)
    spin_up(node, rig)
    rig.send(0x000, bytes([0x01, 1]))
    assert rig.wait(lambda: rig.sim.nodes[1].nmt_state == 0x05)
    rig.drain()
    return master


def _lost_no_earlier_than_a_consumer_time_after(rig, resumed_at: float) -> None:
    """The master stays silent after the heartbeat sent at ``resumed_at``
    (time.time() just before its send): the EMCY of its loss must come, and
    not before that heartbeat's consumer time ran out. An EMCY before it is
    the drive taking its own stall for the master's silence. Judged by the
    frames' send times, which a loaded host can only make later."""
    emcy = rig.expect(_is_emcy, timeout=10.0)
    assert emcy, "a master that stopped was not noticed"
    assert resumed_at, "the heartbeat after the stall was never sent"
    early = resumed_at + STALL_CONSUMER_MS / 1000.0 - emcy.timestamp
    assert early <= 0.005, ("EMCY 0x8130 %.0f ms after the heartbeat that followed the stall (consumer time %d ms):"
                            " the drive took its own stall for a lost master"
                            % ((emcy.timestamp - resumed_at) * 1000, STALL_CONSUMER_MS))


def test_a_stall_of_the_simulating_process_is_no_silence_of_the_master(real_rig):
    """The whole host can stop for a while (user-mode Linux under load):
    neither the master's heartbeat nor the simulator runs meanwhile, and
    when both go on, the simulator may look at its consumers before the
    heartbeat due during the stall has reached its socket. A real drive
    never stalls; the simulator leaves the time it stood still out of its
    supervision. A master that stays silent is still noticed."""
    rig = real_rig
    import time

    master = _operational_under_a_master(rig)
    receive = rig.sim._receive
    passes = []
    resumed = [0.0]
    heartbeat = can.Message(arbitration_id=0x700 + MASTER, data=b"\x05", is_extended_id=False)

    def host_stalls_once(timeout):
        passes.append(len(passes))
        if len(passes) == 1:
            master.stop()
            # The stall itself, on purpose (not a wait for anything): the
            # simulator's loop stands still for three consumer times. A
            # loaded host only makes it longer, which is the case under test.
            time.sleep(HOST_STALL)
            return None
        if len(passes) == 2:
            resumed[0] = time.time()
            rig.raw.send(heartbeat)  # the heartbeat due during the stall, sent on resuming
        return receive(timeout)
    rig.sim._receive = host_stalls_once
    assert rig.wait(lambda: len(passes) > 20)
    rig.sim._receive = receive
    _lost_no_earlier_than_a_consumer_time_after(rig, resumed[0])


def test_a_stall_while_the_simulator_handles_a_frame_is_no_silence_of_the_master(real_rig):
    """As above, with the host stopping while the simulating loop handles a
    frame instead of while it waits for one (user-mode Linux stops every
    process of it at any instruction): the loop finds no frame waiting when
    it goes on, as the master's heartbeat stood still too, and must not take
    the time the host stood still for the master's silence."""
    rig = real_rig
    import time

    master = _operational_under_a_master(rig)
    handle, receive = rig.sim._route, rig.sim._receive
    heartbeat = can.Message(arbitration_id=0x700 + MASTER, data=b"\x05", is_extended_id=False)
    after_stall = []
    resumed = [0.0]

    def host_stalls_in_a_heartbeat(cob, data, remote, now):
        handle(cob, data, remote, now)
        if not after_stall and cob == 0x700 + MASTER:
            master.stop()
            after_stall.append("stalled")
            # The stall itself, on purpose (not a wait for anything), as in
            # the test above.
            time.sleep(HOST_STALL)

    def heartbeat_one_pass_later(timeout):
        if after_stall:
            after_stall.append("pass")
            if len(after_stall) == 4:  # two passes after the stall: the heartbeat due meanwhile is in
                resumed[0] = time.time()
                rig.raw.send(heartbeat)
        return receive(timeout)
    rig.sim._route = host_stalls_in_a_heartbeat
    rig.sim._receive = heartbeat_one_pass_later
    assert rig.wait(lambda: len(after_stall) > 20)
    rig.sim._route, rig.sim._receive = handle, receive
    _lost_no_earlier_than_a_consumer_time_after(rig, resumed[0])
