"""The clocks: the stepped scheduler's order of events and frames, its
waits and timeouts on virtual time; the real clock's threads and waits
(these few tests run on the wall clock, waiting for conditions only)."""
import queue
import threading

import can
import pytest

from maxon_epos4_ros_canopen.clock import REAL, RealClock, SteppedClock, StepNotifier


def test_periodic_tasks_run_at_their_virtual_times_in_order():
    clock = SteppedClock()
    runs = []
    clock.periodic("a", 0.010, lambda: runs.append(("a", round(clock.now(), 6))))
    clock.periodic("b", 0.004, lambda: runs.append(("b", round(clock.now(), 6))), delay=0.001)
    clock.advance(0.012)
    assert runs == [("a", 0.0), ("b", 0.001), ("b", 0.005), ("b", 0.009), ("a", 0.01)]
    assert clock.now() == pytest.approx(0.012)


def test_a_periodic_task_may_name_its_next_time_and_stops_for_good():
    clock = SteppedClock()
    runs = []

    def fn():
        runs.append(round(clock.now(), 6))
        return clock.now() + 0.003
    task = clock.periodic("paced", 0.010, fn)
    clock.advance(0.007)
    assert runs == [0.0, 0.003, 0.006]
    task.stop()
    clock.advance(1.0)
    assert runs == [0.0, 0.003, 0.006]
    assert not task.alive and task.join(0.0)


def test_a_timer_fires_once():
    clock = SteppedClock()
    fired = []
    clock.after(0.5, lambda: fired.append(clock.now()))
    assert not clock.wait_until(lambda: bool(fired), 0.4)
    assert clock.now() == pytest.approx(0.4)
    assert clock.wait_until(lambda: bool(fired), 1.0)
    assert fired == [pytest.approx(0.5)] and clock.now() == pytest.approx(0.5)
    clock.advance(5.0)
    assert len(fired) == 1


def test_wait_until_stops_at_the_first_event_after_which_the_condition_holds():
    clock = SteppedClock()
    count = [0]
    clock.periodic("count", 0.01, lambda: count.__setitem__(0, count[0] + 1))
    assert clock.wait_until(lambda: count[0] >= 5, 1.0)
    assert count[0] == 5 and clock.now() == pytest.approx(0.04)
    # a condition that never holds: time ends at the deadline, exactly
    assert not clock.wait_until(lambda: False, 0.105)
    assert clock.now() == pytest.approx(0.145)


def _virtual_pair(name):
    return (can.Bus(interface="virtual", channel=name, receive_own_messages=False),
            can.Bus(interface="virtual", channel=name, receive_own_messages=False))


def test_frames_sent_in_a_step_and_their_answers_are_delivered_before_the_next_step():
    clock = SteppedClock()
    a, b = _virtual_pair("clock_ping_%d" % id(clock))
    seen = []

    def on_b(msg):  # b answers every frame once, a records
        seen.append(("b", msg.arbitration_id, round(clock.now(), 6), msg.timestamp))
        if msg.arbitration_id == 0x100:
            b.send(can.Message(arbitration_id=0x200, is_extended_id=False, data=msg.data))

    clock.add_pump(b, on_b)
    clock.add_pump(a, lambda msg: seen.append(("a", msg.arbitration_id, round(clock.now(), 6), msg.timestamp)))
    clock.periodic("ping", 0.01, lambda: a.send(can.Message(arbitration_id=0x100, is_extended_id=False)))
    clock.periodic("check", 0.01, lambda: seen.append(("check", round(clock.now(), 6))), delay=0.0)
    clock.advance(0.015)
    # ping at 0 is answered before "check" at 0 runs, and so on
    assert [s[:3] for s in seen] == [("b", 0x100, 0.0), ("a", 0x200, 0.0), ("check", 0.0),
                                     ("b", 0x100, 0.01), ("a", 0x200, 0.01), ("check", 0.01)]
    assert seen[0][3] == SteppedClock.EPOCH and seen[3][3] == pytest.approx(SteppedClock.EPOCH + 0.01)
    a.shutdown()
    b.shutdown()


def test_a_response_queue_waits_on_virtual_time():
    clock = SteppedClock()
    q = clock.response_queue()
    clock.after(0.2, lambda: q.put("answer"))
    assert q.get(timeout=1.0) == "answer"
    assert clock.now() == pytest.approx(0.2)
    with pytest.raises(queue.Empty):
        q.get(timeout=0.3)
    assert clock.now() == pytest.approx(0.5)


def test_the_step_notifier_calls_listeners_and_their_error_handlers():
    clock = SteppedClock()
    a, b = _virtual_pair("clock_notify_%d" % id(clock))
    got, errors = [], []

    class Boom(can.Listener):
        def on_message_received(self, msg):
            raise ValueError("boom")

        def on_error(self, exc):
            errors.append(str(exc))

    class Keep(can.Listener):
        def on_message_received(self, msg):
            got.append(msg.arbitration_id)

    notifier = clock.notifier(b, [Boom()])
    assert isinstance(notifier, StepNotifier)
    notifier.add_listener(Keep())
    a.send(can.Message(arbitration_id=0x123, is_extended_id=False))
    clock.advance(0.0)
    assert got == [0x123] and errors == ["boom"]
    notifier.stop()
    a.send(can.Message(arbitration_id=0x124, is_extended_id=False))
    clock.advance(0.1)
    assert got == [0x123]
    a.shutdown()
    b.shutdown()


def test_acquire_waits_for_a_lock_on_virtual_time_at_most_its_timeout():
    """A stepped clock runs its events while it tries the lock: a lock an
    event releases is taken then; one nobody releases is given up at the
    timeout, on virtual time."""
    clock = SteppedClock()
    lock = threading.Lock()
    lock.acquire()
    clock.after(0.5, lock.release)
    assert not clock.acquire(lock, 0.2)
    assert clock.now() == pytest.approx(0.2)
    assert clock.acquire(lock, 1.0)
    assert clock.now() == pytest.approx(0.5) and lock.locked()
    assert not clock.acquire(lock, 0.0) and clock.now() == pytest.approx(0.5)


def test_real_acquire_takes_a_free_lock_and_gives_up_on_a_held_one():
    lock = threading.Lock()
    assert REAL.acquire(lock, 0.0) and lock.locked()
    assert not REAL.acquire(lock, 0.0)
    assert not REAL.acquire(lock, -1.0)  # a deadline already past: no wait without a bound
    lock.release()


def test_send_periodic_sends_its_frames_in_turn_from_now():
    clock = SteppedClock()
    a, b = _virtual_pair("clock_send_%d" % id(clock))
    seen = []
    clock.add_pump(b, lambda msg: seen.append((round(clock.now(), 6), bytes(msg.data))))
    frames = [can.Message(arbitration_id=0x80, is_extended_id=False, data=bytes([c])) for c in (1, 2)]
    task = clock.send_periodic(a, frames, 0.01, "SYNC")
    clock.advance(0.025)
    task.stop()
    clock.advance(0.1)
    assert seen == [(0.0, b"\x01"), (0.01, b"\x02"), (0.02, b"\x01")]
    a.shutdown()
    b.shutdown()


def test_run_each_runs_every_item():
    done = []
    SteppedClock().run_each(done.append, [1, 2, 3], 8)
    assert done == [1, 2, 3]
    lock = threading.Lock()
    real = []

    def add(i):
        with lock:
            real.append(i)
    REAL.run_each(add, list(range(5)), 3)
    assert sorted(real) == list(range(5))


# ------------------------------------------------------------ real time
def test_real_periodic_task_runs_on_its_thread_until_stopped():
    count = [0]
    threads = set()

    def fn():
        count[0] += 1
        threads.add(threading.current_thread().name)
    task = REAL.periodic("clock_test_task", 0.005, fn)
    assert REAL.wait_until(lambda: count[0] >= 3, 10.0)
    task.stop()
    assert task.join(5.0) and not task.alive
    stopped_at = count[0]
    assert threads == {"clock_test_task"}
    assert REAL.wait_until(lambda: False, 0.02) is False
    assert count[0] == stopped_at


def test_real_wait_until_wakes_on_its_condition():
    cond = threading.Condition()
    flag = []

    def later():
        with cond:
            flag.append(1)
            cond.notify_all()
    threading.Timer(0.01, later).start()
    assert RealClock().wait_until(lambda: bool(flag), 10.0, wake=cond)


def test_a_second_thread_may_not_move_stepped_time():
    clock = SteppedClock()
    clock.advance(0.01)
    errors = []

    def other():
        try:
            clock.advance(0.01)
        except RuntimeError as e:
            errors.append(str(e))
    t = threading.Thread(target=other, name="intruder")
    t.start()
    t.join(10.0)
    assert errors and "intruder" in errors[0]
    assert clock.now() == pytest.approx(0.01)


def test_a_stalled_task_runs_late_once_and_counts_it():
    clock = SteppedClock()
    runs = []
    task = clock.periodic("cycle", 0.01, lambda: runs.append(round(clock.now(), 6)))
    clock.advance(0.015)
    assert clock.stall("cycle", 0.05) == 1
    clock.advance(0.1)
    # 0, 0.01, then nothing until the stall ends at 0.065; late, the task
    # runs again at once (as the thread's loop does) and then on time
    assert runs[:6] == [0.0, 0.01, 0.065, 0.065, 0.075, 0.085]
    assert task.overruns == 1


def test_a_stalled_reader_gets_its_frames_at_the_end_stamped_when_they_came():
    clock = SteppedClock()
    a, b = _virtual_pair("clock_stall_%d" % id(clock))
    seen = []
    clock.add_pump(b, lambda msg: seen.append((round(clock.now(), 6), round(msg.timestamp - clock.EPOCH, 6))),
                   "reader")
    clock.advance(0.01)
    clock.stall("reader", 0.1)
    clock.after(0.02, lambda: a.send(can.Message(arbitration_id=0x181, is_extended_id=False)))
    clock.advance(0.05)
    assert seen == []
    clock.advance(0.1)
    assert seen == [(0.11, 0.03)]
    a.shutdown()
    b.shutdown()


def test_a_frame_reader_keeps_frames_stamped_when_they_came_until_its_task_reads_them():
    """What a task that reads its bus itself (the driver's cycle) gets:
    each frame stamped when it came, held while the task is stalled, none
    after close."""
    clock = SteppedClock()
    a, b = _virtual_pair("clock_reader_%d" % id(clock))
    reader = clock.frame_reader(b, "cycle")
    read = []

    def cycle():
        msg = reader.recv()
        while msg is not None:
            read.append((round(clock.now(), 6), msg.arbitration_id, round(msg.timestamp - clock.EPOCH, 6)))
            msg = reader.recv()
    task = clock.periodic("cycle", 0.01, cycle)
    clock.after(0.003, lambda: a.send(can.Message(arbitration_id=0x181, is_extended_id=False)))
    clock.advance(0.015)
    assert read == [(0.01, 0x181, 0.003)]
    assert clock.stall("cycle", 0.03) == 2  # the task and its reader
    clock.after(0.001, lambda: a.send(can.Message(arbitration_id=0x182, is_extended_id=False)))
    clock.advance(0.02)
    assert read == [(0.01, 0x181, 0.003)]
    clock.advance(0.02)
    assert read[1] == (0.045, 0x182, 0.016)
    reader.close()
    a.send(can.Message(arbitration_id=0x183, is_extended_id=False))
    clock.advance(0.02)
    assert reader.recv() is None and len(read) == 2
    task.stop()
    a.shutdown()
    b.shutdown()


def test_the_real_clocks_frame_reader_reads_without_waiting():
    a, b = _virtual_pair("clock_real_reader")
    reader = REAL.frame_reader(b, "cycle")
    assert reader.recv() is None
    a.send(can.Message(arbitration_id=0x181, is_extended_id=False))
    msg = reader.recv()
    assert msg is not None and msg.arbitration_id == 0x181
    assert reader.recv() is None
    a.shutdown()
    b.shutdown()


def test_frame_order_interleaves_readers_but_keeps_each_readers_order():
    import random
    orders = set()
    for seed in range(20):
        clock = SteppedClock()
        clock.frame_order = random.Random(seed)
        a, b = _virtual_pair("clock_order_%d_%d" % (id(clock), seed))
        c = can.Bus(interface="virtual", channel="clock_order_%d_%d" % (id(clock), seed))
        seen = []
        clock.add_pump(b, lambda msg: seen.append(("b", msg.arbitration_id)))
        clock.add_pump(c, lambda msg: seen.append(("c", msg.arbitration_id)))
        for cob in (1, 2, 3):
            a.send(can.Message(arbitration_id=cob, is_extended_id=False))
        clock.advance(0.0)
        assert [i for r, i in seen if r == "b"] == [1, 2, 3] and [i for r, i in seen if r == "c"] == [1, 2, 3]
        orders.add(tuple(seen))
        for bus in (a, b, c):
            bus.shutdown()
    assert len(orders) > 3


class _ListBus(can.BusABC):
    """A bus that is not python-can's virtual one: frames put in ``waiting``
    are received in order."""

    def __init__(self):
        self.waiting = []
        super().__init__(channel="list")

    def _recv_internal(self, timeout):
        return (self.waiting.pop(0) if self.waiting else None), False

    def send(self, msg, timeout=None):
        raise NotImplementedError


def test_every_kind_of_bus_is_read_until_it_is_empty():
    clock = SteppedClock()
    a, b = _virtual_pair("clock_kinds_%d" % id(clock))
    other = _ListBus()
    seen = []
    clock.add_pump(b, lambda msg: seen.append(("virtual", msg.arbitration_id)))
    clock.add_pump(other, lambda msg: seen.append(("other", msg.arbitration_id)))

    def send_both():
        for cob_id in (0x181, 0x281):
            a.send(can.Message(arbitration_id=cob_id, is_extended_id=False))
            other.waiting.append(can.Message(arbitration_id=cob_id + 1, is_extended_id=False))
    clock.after(0.001, send_both)
    clock.advance(0.002)
    assert seen == [("virtual", 0x181), ("virtual", 0x281), ("other", 0x182), ("other", 0x282)]
    a.shutdown()
    b.shutdown()
    other.shutdown()
