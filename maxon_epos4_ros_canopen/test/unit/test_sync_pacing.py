"""With SYNC from a kernel timer, each period's RxPDOs go out between two
SYNCs, a quarter period after the SYNC the driver heard, every period.

Linux's CAN broadcast manager arms its next expiry from the moment the last
one fired, so its SYNCs fall behind any fixed schedule by every expiry's
latency (about 1 % of a 10 ms period in user-mode Linux under load, less on
a quiet native host, never zero). A cycle paced by the schedule alone
drifts through the SYNCs: periods then carry two targets or none. Here a
stepped kernel timer drifts by DRIFT a period; the frames are the bus's."""
import itertools
from typing import List

import can
import pytest

from maxon_epos4_ros_canopen.driver import bus as bus_module
from maxon_epos4_ros_canopen.driver import link as link_module
from driver_support import J1, SYNC_MS

PERIOD = SYNC_MS / 1000.0
DRIFT = 0.01 * PERIOD
SYNC, CONTROLWORD_RPDO = 0x080, 0x201


@pytest.fixture
def kernel_sync_rig(monkeypatch, driver_rig):
    """A driver rig whose bus passes for SocketCAN and whose periodic frames
    come from a stepped stand-in for the broadcast manager: a socket of its
    own (the driver hears its SYNCs), each expiry armed from the last one
    plus the period, late by DRIFT."""
    rig = driver_rig

    def start_periodic(bus, msgs, period_s, what, kernel=True, store_task=False, clock=None):
        sender = can.Bus(interface="virtual", channel=rig.channel)
        rig.buses.append(sender)
        frames = itertools.cycle(list(msgs))

        def expire() -> float:
            sender.send(next(frames))
            return rig.clock.now() + period_s + DRIFT
        return rig.clock.periodic("kernel timer " + what, period_s, expire, delay=period_s), None

    monkeypatch.setattr(link_module, "is_socketcan", lambda _bus: True)
    monkeypatch.setattr(bus_module, "start_periodic", start_periodic)
    return rig


def periods_and_offsets(log: List[tuple], cob_id: int):
    """For each interval between consecutive SYNCs in ``log``: how many
    frames on ``cob_id`` it holds, and their times after its SYNC."""
    syncs = [t for t, m in log if m.arbitration_id == SYNC]
    stamps = [t for t, m in log if m.arbitration_id == cob_id]
    counts, offsets = [], []
    for a, b in zip(syncs, syncs[1:]):
        inside = [t - a for t in stamps if a <= t < b]
        counts.append(len(inside))
        offsets.extend(inside)
    return syncs, counts, offsets


def test_each_period_between_drifting_kernel_syncs_carries_one_target(kernel_sync_rig):
    rig, seconds = kernel_sync_rig, 3.0
    d = rig.start(sync={"interval_ms": SYNC_MS, "overflow": 0, "kernel_timer": True})
    assert d.init().success
    assert d.switch_mode([J1], 8).success
    rig.clock.advance(0.5)
    start = len(rig.recorder.log)
    rig.clock.advance(seconds)  # the kernel's SYNCs fall 3 periods behind the schedule
    syncs, counts, offsets = periods_and_offsets(rig.recorder.log[start:], CONTROLWORD_RPDO)
    assert len(syncs) >= 0.9 * seconds / PERIOD
    assert counts == [1] * len(counts), "periods holding 0 or 2 RxPDOs: %s" % [
        (i, c) for i, c in enumerate(counts) if c != 1][:10]
    assert min(offsets) >= 0.1 * PERIOD and max(offsets) <= 0.5 * PERIOD, (min(offsets), max(offsets))


def test_a_cycle_that_misses_its_sync_is_counted_late(kernel_sync_rig):
    """A cycle the host leaves unscheduled past its SYNC counts in
    ``cycles_late`` once for each period its RxPDOs missed; the periods
    after it carry one target each again."""
    rig = kernel_sync_rig
    d = rig.start(sync={"interval_ms": SYNC_MS, "overflow": 0, "kernel_timer": True})
    assert d.init().success
    assert d.switch_mode([J1], 8).success
    rig.clock.advance(0.5)
    assert d.status()[0]["cycles_late"] == 0
    start = len(rig.recorder.log)
    rig.clock.advance(0.2)
    # the cycle's task and its receiver of TxPDOs and SYNC, which only it reads
    assert rig.clock.stall("epos4_driver_cycle", 3.5 * PERIOD) == 2
    rig.clock.advance(0.5)
    syncs, counts, _ = periods_and_offsets(rig.recorder.log[start:], CONTROLWORD_RPDO)
    empty = [i for i, c in enumerate(counts) if c == 0]
    late = d.status()[0]["cycles_late"]
    assert len(empty) == 3 and late == 3, (empty, late)
    assert all(c == 1 for c in counts[empty[-1] + 1:])
