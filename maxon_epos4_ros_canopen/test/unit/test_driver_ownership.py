"""Each field of the driver has one owner thread (driver/cycle.py): what
happens when a service thread and the cycle meet at the worst moment. The
drive's values are read from the simulator, frames from the bus."""
import struct
import threading

import can
import pytest

from maxon_epos4_ros_canopen.cia402 import State
from driver_support import J1
from test_driver_adversary import csp_ready

CYCLE_THREAD = "epos4_driver_cycle"
QUICK_STOP_BY_SDO = b"\x2b\x40\x60\x00\x02\x00\x00\x00"  # 0x6040 = 0x0002, expedited download


@pytest.fixture
def rig(real_driver_rig):
    """The wall clock: these tests race the cycle thread against services."""
    return real_driver_rig


def cycle_threads():
    return [t for t in threading.enumerate() if t.name == CYCLE_THREAD and t.is_alive()]


@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")
def test_a_bus_that_keeps_failing_after_recover_is_reported_again(rig):
    """RxPDO sends refused before and after recover (SYNC, SDO and NMT still
    go out, so the drive stays enabled and answers): recover must not hide
    it. The bus error comes back, the joint is in error, and no command is
    taken while nothing reaches the drive."""
    d = csp_ready(rig)
    start = rig.read(0x6064)
    real_send = d.bus.send

    def rxpdos_refused(msg, timeout=None):
        if 0x200 <= msg.arbitration_id < 0x580:
            raise can.CanOperationError("No buffer space available")
        return real_send(msg, timeout)
    d.bus.send = rxpdos_refused
    assert rig.until(lambda: d.joints[J1].error is not None)
    assert "bus error" in d.joints[J1].error and d.snapshot().bus_error is not None
    r = d.recover()
    assert not r.success, r.message
    assert "bus error" in r.message, r.message
    assert rig.until(lambda: d.snapshot().bus_error is not None and d.joints[J1].error is not None)
    assert "bus error" in d.joints[J1].error
    answer = d.set_command(J1, "position", start + 2000)
    assert not answer.success, answer.message
    # and once the bus works again, recover brings the joint back
    d.bus.send = real_send
    r = d.recover()
    assert r.success, r.message
    assert d.snapshot().bus_error is None
    assert d.set_command(J1, "position", start + 2000).success
    assert rig.until(lambda: rig.read(0x607A) == start + 2000)


def test_recover_leaves_the_sync_producer_to_the_cycle_that_sends_with_it(rig):
    """recover restarts SYNC: the producer the cycle sends with (or paces
    itself by) is started and stopped by the cycle thread only, never torn
    down under it from the service thread."""
    d = csp_ready(rig)
    producer = d.sync
    calls = []

    def watched(name):
        method = getattr(producer, name)

        def call(*args, **kwargs):
            calls.append((name, threading.current_thread().name))
            return method(*args, **kwargs)
        setattr(producer, name, call)
    for name in ("start", "stop"):
        watched(name)
    rig.sim.inject_fault(1, "emcy", 0x8611)
    assert rig.until(lambda: d.joints[J1].error is not None)
    r = d.recover()
    assert r.success, r.message
    assert calls, "recover did not restart SYNC"
    assert {thread for _, thread in calls} == {CYCLE_THREAD}, calls


def test_a_stalled_cycle_never_runs_twice_nor_enables_the_drive_after_its_quick_stop(rig):
    """The cycle thread stalls (a cycle callback blocks) past shutdown's
    join timeout. Shutdown stops the drive over SDO; the stalled cycle,
    when it goes on, must not send the enable operation it held the drive
    with; init meanwhile must not start a second cycle; once the stalled
    thread has ended, init works again with one cycle."""
    d = csp_ready(rig)
    d.state_timeout = 1.0
    d.cycle_join_timeout = 0.3
    stalled, release = threading.Event(), threading.Event()

    def stall(driver):
        if not release.is_set():
            stalled.set()
            release.wait(30.0)
    d.add_cycle_callback(stall)
    assert stalled.wait(5.0)
    rig.drain()
    try:
        d.shutdown()
        assert rig.state() == State.SWITCH_ON_DISABLED
        again = d.init()
        assert len(cycle_threads()) <= 1
    finally:
        release.set()
    assert not again.success, again.message
    assert rig.until(lambda: not cycle_threads())  # the stalled thread ends, none other runs
    frames = [m for m in rig._collect() if m.arbitration_id in (0x601, 0x201)]
    quick_stop = [i for i, m in enumerate(frames) if m.arbitration_id == 0x601 and bytes(m.data) == QUICK_STOP_BY_SDO]
    assert quick_stop, "no quick stop over SDO"
    later = [struct.unpack_from("<H", bytes(m.data))[0] for m in frames[quick_stop[0]:] if m.arbitration_id == 0x201]
    assert not [cw for cw in later if cw & 0x8F == 0x0F], later
    assert rig.state() == State.SWITCH_ON_DISABLED
    d.remove_cycle_callback(stall)
    r = d.init()
    assert r.success, r.message
    assert len(cycle_threads()) == 1
