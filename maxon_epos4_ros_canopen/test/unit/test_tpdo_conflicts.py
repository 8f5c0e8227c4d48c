"""Two frames on one TxPDO COB-ID within one SYNC period are a conflict
(another node on that COB-ID, or a forger): the driver counts them per
axis and shows the count on diagnostics (status()).

The receiver's rule is tried with explicit arrival times for each
transmission type; on the virtual bus a forger repeats node 1's TPDO and
the count is checked against the frames on the bus."""
from __future__ import annotations

from typing import Dict, List, Tuple

import can
import pytest

from csp_rig import SYNC_COB_ID as SYNC, CspRig, Forger, position_mapping, wait
from maxon_epos4_ros_canopen.driver.pdo import TpdoReceiver, sync_driven
from maxon_epos4_ros_canopen.driver.plan import MapPlan

TIMEOUT = 15.0
COB_SYNCED, COB_EVERY_3RD, COB_TIMER = 0x181, 0x281, 0x381


class Arrivals:
    """The receive clock: (read, arrived) of the frame being handled."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> Tuple[float, float]:
        return self.t, self.t


def receiver(clock: Arrivals, synced=(COB_SYNCED, COB_EVERY_3RD)) -> TpdoReceiver:
    return TpdoReceiver({COB_SYNCED: 6, COB_EVERY_3RD: 4, COB_TIMER: 8}, clock, sync_driven=synced)


def frame(r: TpdoReceiver, clock: Arrivals, t: float, cob: int) -> None:
    clock.t = t
    r.on_frame(cob, bytes(r.lengths[cob]), t)


def test_one_frame_per_sync_period_is_no_conflict_a_second_one_is():
    clock = Arrivals()
    r = receiver(clock)
    for k in range(10):  # SYNC every 10 ms, the drive answers 1 ms later
        r.sync_sent(k * 0.010)
        frame(r, clock, k * 0.010 + 0.001, COB_SYNCED)
    assert r.conflicts[COB_SYNCED] == 0
    frame(r, clock, 0.0955, COB_SYNCED)  # a second frame before the next SYNC
    assert r.conflicts[COB_SYNCED] == 1
    r.sync_sent(0.100)
    frame(r, clock, 0.1005, COB_SYNCED)  # a forger first, then the drive
    frame(r, clock, 0.101, COB_SYNCED)
    assert r.conflicts[COB_SYNCED] == 2


def test_every_nth_sync_and_event_timer_tpdos_are_not_counted_wrongly():
    clock = Arrivals()
    r = receiver(clock)
    for k in range(30):
        r.sync_sent(k * 0.010)
        if k % 3 == 0:  # transmission type 3: every third SYNC
            frame(r, clock, k * 0.010 + 0.002, COB_EVERY_3RD)
        # an event-timer TPDO (type 255) at 4 ms: often twice between SYNCs
        frame(r, clock, k * 0.010 + 0.003, COB_TIMER)
        frame(r, clock, k * 0.010 + 0.007, COB_TIMER)
    assert r.conflicts == {COB_SYNCED: 0, COB_EVERY_3RD: 0, COB_TIMER: 0}
    frame(r, clock, 0.2905, COB_EVERY_3RD)  # two in the period of SYNC 29 (one at 0.272, SYNC 27)
    assert r.conflicts[COB_EVERY_3RD] == 0
    frame(r, clock, 0.2955, COB_EVERY_3RD)
    assert r.conflicts[COB_EVERY_3RD] == 1


def test_frames_count_by_arrival_not_by_when_the_notifier_handles_them():
    clock = Arrivals()
    r = receiver(clock)
    r.sync_sent(0.000)
    r.sync_sent(0.010)
    r.sync_sent(0.020)  # the notifier lags: both frames handled after the third SYNC
    frame(r, clock, 0.001, COB_SYNCED)
    frame(r, clock, 0.011, COB_SYNCED)
    frame(r, clock, 0.021, COB_SYNCED)
    assert r.conflicts[COB_SYNCED] == 0


def test_syncs_heard_on_the_bus_count_too_and_none_known_counts_nothing():
    clock = Arrivals()
    r = receiver(clock)
    frame(r, clock, 0.001, COB_SYNCED)
    frame(r, clock, 0.002, COB_SYNCED)  # no SYNC known yet: no period to judge by
    assert r.conflicts[COB_SYNCED] == 0
    for k in range(1, 5):  # the kernel's SYNC, heard by the receiver
        clock.t = k * 0.010
        r.on_sync(SYNC, b"", clock.t)
        frame(r, clock, k * 0.010 + 0.001, COB_SYNCED)
    assert r.conflicts[COB_SYNCED] == 0
    frame(r, clock, 0.045, COB_SYNCED)
    assert r.conflicts[COB_SYNCED] == 1


def test_only_tpdos_sent_on_sync_are_watched():
    def plan(cob: int, trans: int, timer=None) -> MapPlan:
        return MapPlan(1, cob, True, trans, timer, True, ((object(), 16),))
    plans = [plan(0x181, 1), plan(0x281, 240), plan(0x381, 254, 10), plan(0x481, 255, 10), plan(0x1A1, 0)]
    assert sync_driven(plans) == [0x181, 0x281, 0x1A1]


def conflicts_on_the_bus(frames: List[can.Message], cobs) -> Dict[int, int]:
    """Frames beyond the first on each COB-ID in each SYNC period, as the bus carried them."""
    out = {c: 0 for c in cobs}
    seen: Dict[int, int] = {}
    started = False
    for f in frames:
        if f.arbitration_id == SYNC:
            seen, started = {}, True
        elif started and f.arbitration_id in out:
            seen[f.arbitration_id] = seen.get(f.arbitration_id, 0) + 1
            if seen[f.arbitration_id] > 1:
                out[f.arbitration_id] += 1
    return out


@pytest.fixture
def rig():
    rig = CspRig()
    try:
        rig.start()
        yield rig
    finally:
        rig.close()


def tpdo_cobs(sim, node_id: int) -> List[int]:
    return [sim.read(node_id, 0x1800 + n, 1) & 0x7FF for n in range(4)
            if not sim.read(node_id, 0x1800 + n, 1) & 0x80000000]


def test_a_repeated_tpdo_is_counted_per_axis_on_diagnostics(rig):
    driver, sim = rig.driver, rig.sim
    cob, _ = position_mapping(sim, 1)
    forger = Forger(rig.channel, cob)  # an exact copy after each of node 1's frames
    try:
        forger.active = True
        assert wait(lambda: forger.sent >= 50, TIMEOUT)
        forger.active = False
        sent = forger.sent
    finally:
        forger.close()

    def counted():
        """Each node's tpdo_conflicts, and the conflicts the bus carried
        since init (the frames the driver has yet to read on a loaded
        host come into both as the listener is flushed)."""
        assert rig.listener.flush(TIMEOUT)
        frames = list(rig.listener.frames)
        status = {s["node_id"]: s["tpdo_conflicts"] for s in driver.status()}
        return {n: (status[n], sum(conflicts_on_the_bus(frames, tpdo_cobs(sim, n)).values())) for n in (1, 2)}
    # Every conflict the bus carried, and no other, once the driver has read
    # them all. Equal on a quiet host; the driver places a frame by when it
    # arrived against when it was about to send each SYNC, the bus listener
    # by the order of frames, so a frame sent in the instant between the two
    # can count in the next period instead: where the simulator lags (two
    # CPU hogs beside the suite) its late answers fill periods unevenly and
    # that can move a conflict (3 of 589 seen).
    def agree(counts) -> bool:
        return all(abs(mine - bus) <= 3 + bus // 50 for mine, bus in counts.values())
    assert wait(lambda: agree(counted()), TIMEOUT), counted()
    counts = counted()
    assert agree(counts), counts
    assert counts[1][0] >= sent - 3 - counts[1][1] // 50, (sent, counts)
