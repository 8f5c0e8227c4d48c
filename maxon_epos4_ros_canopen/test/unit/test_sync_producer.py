"""SyncProducer's periodic path on python-can's virtual bus (no broadcast
manager there: the thread fallback), the frames' counter sequence, and the
schedule a cycle can be paced by; the master's periodic senders through a
bus that fails for a while."""
import os
import threading
import time

import can
import pytest

from maxon_epos4_ros_canopen.config_schema import HeartbeatConfig
from maxon_epos4_ros_canopen.driver.bus import SYNC_COB_ID, HeartbeatProducer, SyncProducer
from maxon_epos4_ros_canopen.clock import REAL

MASTER_HEARTBEAT = 0x77F


def collect(bus, n, timeout=10.0, cob_id=SYNC_COB_ID):
    frames = []
    end = time.monotonic() + timeout
    while len(frames) < n and time.monotonic() < end:
        msg = bus.recv(0.2)
        if msg is not None and msg.arbitration_id == cob_id:
            frames.append(msg)
    return frames


@pytest.fixture
def buses():
    channel = "sync_producer_%d_%d" % (os.getpid(), time.monotonic_ns())
    master = can.Bus(interface="virtual", channel=channel)
    sniffer = can.Bus(interface="virtual", channel=channel)
    yield master, sniffer
    master.shutdown()
    sniffer.shutdown()


def periodic(buses, overflow, n):
    """Start a 5 ms SYNC, take n of its frames, stop."""
    master, sniffer = buses
    sync = SyncProducer(master, overflow)
    sync.start(0.005)
    try:
        return sync, collect(sniffer, n)
    finally:
        sync.stop()


def test_periodic_sync_with_counter_falls_back_to_the_thread(buses):
    sync, frames = periodic(buses, 4, 10)
    assert not sync.kernel_timed  # the virtual bus has no kernel timer
    assert [bytes(f.data) for f in frames] == [bytes([c]) for c in (1, 2, 3, 4, 1, 2, 3, 4, 1, 2)]
    assert all(not f.is_extended_id and f.dlc == 1 for f in frames)


def test_periodic_sync_without_counter_is_empty(buses):
    sync, frames = periodic(buses, 0, 3)
    assert len(frames) == 3 and all(f.dlc == 0 for f in frames)
    assert sync.frames()[0].dlc == 0


def test_stop_ends_the_frames_and_restart_counts_from_1(buses):
    master, sniffer = buses
    sync = SyncProducer(master, overflow=3)
    sync.start(0.005)
    collect(sniffer, 2)
    sender = sync._task.thread  # python-can's sender thread (no kernel timer on this bus)
    sync.stop()
    # stop() does not wait for the thread: it ends at its next wake-up, a
    # frame it was sending then the last. Once it ended, nothing can follow.
    assert REAL.wait_until(lambda: not sender.is_alive(), 5.0)
    while sniffer.recv(0) is not None:
        pass
    sync.start(0.005)
    try:
        assert [bytes(f.data) for f in collect(sniffer, 2)] == [b"\x01", b"\x02"]
    finally:
        sync.stop()


def test_schedule_counts_periods_from_the_first_sync(buses):
    master, _ = buses
    sync = SyncProducer(master, overflow=3)
    with pytest.raises(RuntimeError):
        sync.next_after(0.0)
    sync.start(0.01)
    try:
        t0 = sync.first_at
        assert sync.index_at(t0 - 0.001) == 0 and sync.counter_at(t0 - 0.001) == 0
        assert sync.index_at(t0) == 1 and sync.counter_at(t0) == 1
        assert sync.counter_at(t0 + 0.0305) == 1       # the 4th SYNC wraps to 1
        assert sync.next_after(t0 + 0.015) == pytest.approx(t0 + 0.02)
    finally:
        sync.stop()
    with pytest.raises(ValueError):
        sync.start(0)


def test_send_advances_the_counter(buses):
    master, sniffer = buses
    sync = SyncProducer(master, overflow=2)
    for _ in range(3):
        sync.send()
    assert [bytes(f.data) for f in collect(sniffer, 3)] == [b"\x01", b"\x02", b"\x01"]
    assert sync.sent == 3


class _Task:
    def __init__(self):
        self.stopped = False

    def stop(self):
        self.stopped = True


def test_socketcan_hands_the_counter_sequence_to_the_kernel(buses, monkeypatch):
    """On SocketCAN the frames go to send_periodic as one list without a
    modifier callback (python-can makes that a BCM task); the virtual bus
    stands in for the SocketCAN bus here and records the call."""
    import maxon_epos4_ros_canopen.driver.bus as bus_module
    master, sniffer = buses
    calls = []
    task = _Task()

    def send_periodic(msgs, period, **kwargs):
        calls.append((msgs, period, kwargs))
        return task
    monkeypatch.setattr(bus_module, "is_socketcan", lambda bus: True)
    monkeypatch.setattr(master, "send_periodic", send_periodic)
    sync = SyncProducer(master, overflow=5)
    before = time.monotonic()
    sync.start(0.01)
    assert sync.kernel_timed
    (msgs, period, kwargs), = calls
    assert period == 0.01 and "modifier_callback" not in kwargs
    assert [(m.arbitration_id, bytes(m.data)) for m in msgs] == [(SYNC_COB_ID, bytes([c])) for c in range(1, 6)]
    assert sync.first_at >= before + 0.01  # BCM's first frame comes one period after setup
    sync.stop()
    assert task.stopped and sync.first_at is None


def test_socketcan_without_can_bcm_falls_back_to_the_thread(buses, monkeypatch):
    import maxon_epos4_ros_canopen.driver.bus as bus_module
    master, sniffer = buses

    def no_bcm(msgs, period, **kwargs):
        raise OSError(93, "Protocol not supported")
    monkeypatch.setattr(bus_module, "is_socketcan", lambda bus: True)
    monkeypatch.setattr(master, "send_periodic", no_bcm)
    sync = SyncProducer(master, overflow=2)
    sync.start(0.005)
    try:
        frames = collect(sniffer, 3)
    finally:
        sync.stop()
    assert not sync.kernel_timed
    assert [bytes(f.data) for f in frames] == [b"\x01", b"\x02", b"\x01"]


@pytest.mark.parametrize("producer", ["sync", "heartbeat"])
def test_a_bus_that_refuses_frames_for_a_while_does_not_end_the_sender(buses, monkeypatch, producer):
    """The bus refuses every frame for a while (down, or its transmit queue
    full): the sender thread counts the errors and goes on, and the frames
    are on the bus again as soon as it takes them. A heartbeat that ended
    at the first lost frame would let every drive's consumer stop its drive."""
    master, sniffer = buses
    thread_exceptions = []
    monkeypatch.setattr(threading, "excepthook", thread_exceptions.append)
    down = threading.Event()
    down.set()
    refused = []
    real_send = master.send

    def send(msg, timeout=None):
        if down.is_set():
            refused.append(msg)
            raise can.CanOperationError("Failed to transmit: Network is down", 100)
        return real_send(msg, timeout)
    monkeypatch.setattr(master, "send", send)
    if producer == "sync":
        sender, cob_id = SyncProducer(master, overflow=0), SYNC_COB_ID
        sender.start(0.005)
    else:
        sender, cob_id = HeartbeatProducer(master, HeartbeatConfig(200.0, MASTER_HEARTBEAT, b"\x05")), MASTER_HEARTBEAT
        sender.start()
    try:
        assert REAL.wait_until(lambda: len(refused) >= 3, 5.0)
        assert sniffer.recv(0) is None
        down.clear()
        frames = collect(sniffer, 3, cob_id=cob_id)
    finally:
        sender.stop()
    assert len(frames) == 3
    assert thread_exceptions == []
    assert sender.send_errors.count >= 3 and isinstance(sender.send_errors.last, can.CanOperationError)
