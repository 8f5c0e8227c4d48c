"""Time for the driver and the simulator: real, or stepped by a test.

Every timer and every wait of the driver and the simulator goes through a
``Clock``. Two exist:

* ``RealClock`` (the default): the monotonic clock, threads for periodic
  work, python-can's notifier thread for received frames, blocking waits.
* ``SteppedClock``: virtual time on one thread, a discrete-event
  scheduler. Periodic tasks (the driver's cycle, the SYNC and heartbeat
  producers, the simulator's tick) and timers are events on its time line;
  received frames are delivered by a pump that reads each registered
  python-can bus with ``recv(0)`` and hands every frame to its listeners
  (or, for a task that reads a bus itself, keeps it for the task's
  ``frame_reader``).
  After each event every frame sent meanwhile is delivered (and those sent
  in answer, until the buses are quiet) before the next event runs. A wait
  (``wait_until``) runs the events in time order until its condition holds
  or its virtual deadline passes, so a service call made by a test (init,
  an SDO transfer) runs to its end on the test's thread, and its timeouts
  mean what they mean on a real bus. No outcome depends on how threads are
  scheduled: the same scenario gives the same frames at the same times.

The code that uses a clock is the same for both: it asks the clock to
start a periodic task, to wait for a condition, to sleep, for a queue to
wait on. Only the clock decides whether that is a thread or an event.
"""
from __future__ import annotations

import collections
import logging
import heapq
import itertools
import math
import queue
import random
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable, Deque, List, Optional, Sequence, Tuple

import can

# What a periodic task's function returns: when it wants to run next (on
# the clock), or None for one period after its last due time.
PeriodicFn = Callable[[], Optional[float]]


class Task:
    """A periodic task or a timer started by a clock."""

    name = ""
    overruns = 0  # periods a periodic task started late by a whole period or more

    def stop(self) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def join(self, timeout: float) -> bool:  # pragma: no cover - interface
        """Whether the task has ended (waiting up to ``timeout`` s for it)."""
        raise NotImplementedError

    @property
    def alive(self) -> bool:  # pragma: no cover - interface
        raise NotImplementedError


class Clock:
    """What the driver and the simulator ask of time."""

    stepped = False

    def now(self) -> float:
        """Monotonic time (s)."""
        raise NotImplementedError

    def wall(self) -> float:
        """Wall-clock time (s since the epoch): the time frames are stamped with."""
        raise NotImplementedError

    def sleep(self, seconds: float) -> None:
        raise NotImplementedError

    def wait_until(self, predicate: Callable[[], bool], timeout: float,
                   wake: Optional[threading.Condition] = None) -> bool:
        """Whether ``predicate`` came to hold within ``timeout`` s. ``wake``:
        a condition notified whenever the predicate may have changed (a
        real clock then waits on it instead of polling)."""
        raise NotImplementedError

    def wait_event(self, event: threading.Event, timeout: float) -> bool:
        return self.wait_until(event.is_set, timeout)

    def response_queue(self) -> "queue.Queue[Any]":
        """A queue whose blocking ``get(timeout=...)`` waits on this clock
        (canopen's SDO client waits for its answer on one)."""
        raise NotImplementedError

    def acquire(self, lock: Any, timeout: float) -> bool:
        """Whether ``lock`` (anything with ``acquire(blocking, timeout)``)
        was taken within ``timeout`` s of this clock."""
        raise NotImplementedError

    def periodic(self, name: str, period: float, fn: PeriodicFn, delay: float = 0.0,
                 on_thread_start: Optional[Callable[[], None]] = None) -> Task:
        """Run ``fn`` every ``period`` s, the first time ``delay`` s from now.
        ``fn`` may return when it wants to run next (see PeriodicFn).
        ``on_thread_start``: run first in the task's own thread, where it
        has one (the thread's scheduling); a stepped clock has none."""
        raise NotImplementedError

    def send_periodic(self, bus: Any, msgs: Sequence[can.Message], period: float, name: str) -> Task:
        """Send ``msgs`` in turn through ``bus`` (anything with ``send``)
        every ``period`` s, the first one now."""
        frames = list(msgs)
        index = itertools.cycle(range(len(frames)))

        def send() -> None:
            bus.send(frames[next(index)])
        return self.periodic(name, period, send)

    def notifier(self, bus: can.BusABC, listeners: List[can.Listener], timeout: float = 1.0) -> Any:
        """What hands ``bus``'s received frames to ``listeners`` (a
        ``can.Notifier`` or its stand-in: add_listener, stop, exception)."""
        raise NotImplementedError

    def frame_reader(self, bus: can.BusABC, name: str) -> "FrameReader":
        """What a periodic task named ``name`` reads ``bus``'s received
        frames with, itself, one at a time without waiting: no thread of
        its own (see FrameReader)."""
        raise NotImplementedError

    def run_each(self, fn: Callable[[Any], Any], items: Sequence[Any], workers: int) -> None:
        """``fn(item)`` for every item, up to ``workers`` at once; returns
        when all have. ``fn`` must not raise."""
        raise NotImplementedError


class _ThreadTask(Task):
    def __init__(self, name: str, period: float, fn: PeriodicFn, delay: float, clock: "RealClock",
                 on_thread_start: Optional[Callable[[], None]] = None) -> None:
        self.name, self.period, self._fn, self._clock = name, period, fn, clock
        self.overruns = 0
        self._on_thread_start = on_thread_start
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(delay,), name=name, daemon=True)
        self._thread.start()

    def _run(self, delay: float) -> None:
        if self._on_thread_start is not None:
            try:
                self._on_thread_start()
            except Exception:  # the task runs all the same, on the scheduling it has
                logging.getLogger(__name__).exception("%s: thread start failed", self.name)
        now = self._clock.now
        next_t = now() + delay
        if delay > 0 and self._stop.wait(delay):
            return
        while not self._stop.is_set():
            wanted = self._fn()
            t = now()
            if wanted is not None:
                next_t = wanted
            else:
                next_t += self.period
                if next_t < t:
                    self.overruns += 1
                    next_t = t
            self._stop.wait(max(0.0, next_t - now()))

    def stop(self) -> None:
        self._stop.set()

    def join(self, timeout: float) -> bool:
        if self._thread is not threading.current_thread():
            self._thread.join(timeout)
        return not self._thread.is_alive()

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()


class _CyclicTask(Task):
    """python-can's sender thread as a Task."""

    def __init__(self, task: can.broadcastmanager.ThreadBasedCyclicSendTask, name: str) -> None:
        self._task, self.name = task, name

    @property
    def thread(self) -> Optional[threading.Thread]:
        """python-can's sender thread."""
        return getattr(self._task, "thread", None)

    def stop(self) -> None:
        self._task.stop()

    def join(self, timeout: float) -> bool:
        thread = getattr(self._task, "thread", None)
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout)
        return thread is None or not thread.is_alive()

    @property
    def alive(self) -> bool:
        thread = getattr(self._task, "thread", None)
        return thread is not None and thread.is_alive()


class FrameReader:
    """``recv()``: the next frame received and not read yet, or None; a
    frame's ``timestamp`` is when it reached this host (wall clock).
    ``close()``: read no more (the bus itself stays open)."""

    def __init__(self, recv: Callable[[], Optional[can.Message]], close: Callable[[], None] = lambda: None) -> None:
        self.recv = recv
        self.close = close


class RealClock(Clock):
    """Real time: threads and blocking waits."""

    POLL = 0.01  # s between two looks at a predicate nothing notifies of

    # the C functions themselves: the cycle reads the clock every period
    now = staticmethod(time.monotonic)
    wall = staticmethod(time.time)

    def sleep(self, seconds: float) -> None:
        time.sleep(max(0.0, seconds))

    def wait_until(self, predicate: Callable[[], bool], timeout: float,
                   wake: Optional[threading.Condition] = None) -> bool:
        deadline = time.monotonic() + timeout
        while True:
            if predicate():
                return True
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return predicate()
            if wake is None:
                time.sleep(min(remaining, self.POLL))
            else:
                with wake:
                    if not predicate():
                        wake.wait(min(remaining, 0.5))

    def wait_event(self, event: threading.Event, timeout: float) -> bool:
        return event.wait(timeout)

    def response_queue(self) -> "queue.Queue[Any]":
        return queue.Queue()

    def acquire(self, lock: Any, timeout: float) -> bool:
        return bool(lock.acquire(True, max(0.0, timeout)))

    def periodic(self, name: str, period: float, fn: PeriodicFn, delay: float = 0.0,
                 on_thread_start: Optional[Callable[[], None]] = None) -> Task:
        return _ThreadTask(name, period, fn, delay, self, on_thread_start)

    def send_periodic(self, bus: Any, msgs: Sequence[can.Message], period: float, name: str) -> Task:
        # python-can's own sender thread (its timing is what users run on)
        task = can.broadcastmanager.ThreadBasedCyclicSendTask(bus, threading.Lock(), list(msgs), period,
                                                              on_error=lambda e: True)
        return _CyclicTask(task, name)

    def notifier(self, bus: can.BusABC, listeners: List[can.Listener], timeout: float = 1.0) -> Any:
        return can.Notifier(bus, listeners, timeout)

    def frame_reader(self, bus: can.BusABC, name: str) -> FrameReader:
        return FrameReader(lambda: bus.recv(0))

    def run_each(self, fn: Callable[[Any], Any], items: Sequence[Any], workers: int) -> None:
        if len(items) <= 1:
            for item in items:
                fn(item)
            return
        with ThreadPoolExecutor(max_workers=min(len(items), workers), thread_name_prefix="clock_each") as pool:
            list(pool.map(fn, items))


REAL = RealClock()


# --------------------------------------------------------------- stepped
class _Event(Task):
    def __init__(self, clock: "SteppedClock", name: str, period: Optional[float], fn: Callable[[], Any]) -> None:
        self._clock, self.name, self.period, self._fn = clock, name, period, fn
        self.overruns = 0
        self.due = 0.0
        self.cancelled = False
        self.running = False
        self.held_until = -math.inf  # a stalled task runs no earlier (SteppedClock.stall)
        self.planned = math.inf  # when a stalled run was due

    def stop(self) -> None:
        self.cancelled = True

    def join(self, timeout: float) -> bool:
        return not self.running  # one thread: a stopped event never runs again

    @property
    def alive(self) -> bool:
        return not self.cancelled and (self.period is not None or self._clock.pending(self))


class StepNotifier:
    """A ``can.Notifier`` stand-in on a stepped clock: the clock's pump
    reads the bus and calls the listeners; no thread."""

    def __init__(self, clock: "SteppedClock", bus: can.BusABC, listeners: List[can.Listener]) -> None:
        self.bus = bus
        self.listeners = listeners  # the caller's list: listeners added to it later are called too
        self.exception: Optional[BaseException] = None
        self._clock = clock
        self._running = True
        clock.add_pump(bus, self._deliver, "can_notifier")

    def _deliver(self, msg: can.Message) -> None:
        if not self._running:
            return
        for listener in list(self.listeners):
            try:
                listener.on_message_received(msg)
            except Exception as e:  # as can.Notifier: a listener's error goes to its on_error
                handler = getattr(listener, "on_error", None)
                if handler is None:
                    raise
                handler(e)

    def add_listener(self, listener: can.Listener) -> None:
        self.listeners.append(listener)

    def remove_listener(self, listener: can.Listener) -> None:
        self.listeners.remove(listener)

    def stop(self, timeout: float = 5.0) -> None:
        self._running = False
        self._clock.remove_pump(self.bus)
        for listener in self.listeners:
            stop = getattr(listener, "stop", None)
            if callable(stop):
                stop()


class StepQueue(queue.Queue):  # type: ignore[type-arg]
    """A queue whose blocking get waits on a stepped clock (virtual time)."""

    def __init__(self, clock: "SteppedClock") -> None:
        super().__init__()
        self._clock = clock

    def get(self, block: bool = True, timeout: Optional[float] = None) -> Any:
        if block and self.empty():
            self._clock.wait_until(lambda: not self.empty(), self._clock.FOREVER if timeout is None else timeout)
        return super().get(block=False)


class _Pump:
    """One bus the stepped clock reads, and where its frames go."""

    def __init__(self, bus: can.BusABC, handler: Callable[[can.Message], None], name: str) -> None:
        self.bus, self.handler, self.name = bus, handler, name
        self.inbox: Deque[can.Message] = collections.deque()  # read, stamped, not yet handed over
        self.held_until = -math.inf  # a stalled reader hands nothing over before
        # python-can's virtual bus keeps its received frames in a
        # queue.Queue: asking it whether it is empty costs a fraction of a
        # recv(0) that finds nothing, which is what most reads of a step
        # find. Other buses are read.
        pending = getattr(bus, "queue", None)
        self._empty: Callable[[], bool] = pending.empty if isinstance(pending, queue.Queue) else (lambda: False)

    def read(self) -> Optional[can.Message]:
        """The next frame the bus received, or None."""
        if self._empty():
            return None
        try:
            return self.bus.recv(0)
        except (can.CanError, OSError, ValueError):  # a bus shut down under its pump
            return None


class SteppedClock(Clock):
    """Virtual time, advanced only by waits: a single-threaded
    discrete-event scheduler (see the module's text).

    Use it from one thread. ``add_pump`` registers a python-can bus whose
    frames the clock delivers; ``advance`` and ``wait_until`` move time."""

    stepped = True
    EPOCH = 1_700_000_000.0  # wall time at virtual time 0
    FOREVER = 3600.0  # the deadline of a wait that gave none
    MAX_FRAMES_PER_STEP = 1_000_000  # frames answering frames without end: a defect, raised

    def __init__(self, start: float = 0.0) -> None:
        self._now = start
        self._heap: List[Tuple[float, int, _Event]] = []
        self._seq = itertools.count()
        self._pumps: List[_Pump] = []
        # None: each bus's frames go to its reader in turn, in bus order.
        # A Random: one frame at a time to a reader it picks (each reader
        # still gets its own frames in bus order): other orders of the
        # same traffic, as threads reading on a real host see it.
        self.frame_order: Optional[random.Random] = None
        self.frames_delivered = 0
        self.events_run = 0
        self._owner: Optional[int] = None  # the one thread that moves time

    # -------------------------------------------------------------- time
    def now(self) -> float:
        return self._now

    def wall(self) -> float:
        return self.EPOCH + self._now

    def sleep(self, seconds: float) -> None:
        self.wait_until(lambda: False, max(0.0, seconds))

    def advance(self, seconds: float) -> None:
        """Run everything due within ``seconds`` s; time is then now + seconds."""
        self.sleep(seconds)

    def wait_until(self, predicate: Callable[[], bool], timeout: float,
                   wake: Optional[threading.Condition] = None) -> bool:
        self._check_thread()
        deadline = self._now + max(0.0, timeout)
        while True:
            self._catch_up()
            if predicate():
                return True
            due = self._next_due()
            if due is None or due > deadline:
                self._now = max(self._now, deadline)
                self.deliver()
                return predicate()
            self._run_next()

    def wait_event(self, event: threading.Event, timeout: float) -> bool:
        return self.wait_until(event.is_set, timeout)

    def response_queue(self) -> "queue.Queue[Any]":
        return StepQueue(self)

    def acquire(self, lock: Any, timeout: float) -> bool:
        # one thread moves time: the events run while the lock is tried
        return self.wait_until(lambda: bool(lock.acquire(False)), timeout)

    # ------------------------------------------------------------ events
    def periodic(self, name: str, period: float, fn: PeriodicFn, delay: float = 0.0,
                 on_thread_start: Optional[Callable[[], None]] = None) -> Task:
        if not period > 0:
            raise ValueError("period must be > 0, not %r" % (period,))
        event = _Event(self, name, period, fn)
        self._push(event, self._now + max(0.0, delay))
        return event

    def after(self, delay: float, fn: Callable[[], Any], name: str = "timer") -> Task:
        """Run ``fn`` once, ``delay`` s from now."""
        event = _Event(self, name, None, fn)
        self._push(event, self._now + max(0.0, delay))
        return event

    def pending(self, event: _Event) -> bool:
        return any(e is event for _, _, e in self._heap)

    def _push(self, event: _Event, due: float) -> None:
        event.due = due
        heapq.heappush(self._heap, (due, next(self._seq), event))

    def _next_due(self) -> Optional[float]:
        while self._heap and self._heap[0][2].cancelled:
            heapq.heappop(self._heap)
        return self._heap[0][0] if self._heap else None

    def _check_thread(self) -> None:
        """Time moves on one thread only: a second one would run events
        beside the first, and outcomes would depend on threads again."""
        me = threading.get_ident()
        if self._owner is None:
            self._owner = me
        elif self._owner != me:
            raise RuntimeError("a stepped clock is moved by one thread; %s is another"
                               % threading.current_thread().name)

    def _catch_up(self) -> None:
        """Run what is due now (a task started since the last step runs
        before anyone looks), then deliver the frames."""
        while True:
            due = self._next_due()
            if due is None or due > self._now:
                break
            self._run_next()
        self.deliver()

    def _run_next(self) -> None:
        due, _, event = heapq.heappop(self._heap)
        if event.held_until > due:  # stalled: it runs when the stall ends,
            event.planned = min(event.planned, due)  # late for the time it was due
            self._push(event, event.held_until)
            return
        due, event.planned = min(due, event.planned), math.inf
        self._now = max(self._now, due)
        self.events_run += 1
        event.running = True
        try:
            wanted = event._fn()
        finally:
            event.running = False
        if event.period is not None and not event.cancelled:
            if wanted is not None:
                nxt = max(float(wanted), self._now)
            else:
                nxt = due + event.period
                if nxt < self._now:
                    event.overruns += 1
                    nxt = self._now
            self._push(event, nxt)
        self.deliver()

    # ------------------------------------------------------------ stalls
    def stall(self, name: str, seconds: float) -> int:
        """Stand the tasks and bus readers named ``name`` still for
        ``seconds`` from now, as a thread the host does not schedule: a
        task's runs are postponed to the stall's end (the task sees it is
        late), a reader's frames are received (stamped now, as a socket
        does) but handed over only at the end. How many were stalled."""
        until = self._now + seconds
        count = 0
        for _, _, event in self._heap:
            if event.name == name and not event.cancelled:
                event.held_until = max(event.held_until, until)
                count += 1
        for pump in self._pumps:
            if pump.name == name:
                pump.held_until = max(pump.held_until, until)
                count += 1
        if count:
            self.after(seconds, lambda: None, "stall of %s ends" % name)
        return count

    # ------------------------------------------------------------ frames
    def add_pump(self, bus: can.BusABC, deliver: Callable[[can.Message], None], name: str = "") -> None:
        """Deliver every frame ``bus`` receives to ``deliver``, stamped with
        this clock's wall time when read, before the next event runs."""
        self._pumps.append(_Pump(bus, deliver, name))

    def remove_pump(self, bus: can.BusABC) -> None:
        self._pumps = [p for p in self._pumps if p.bus is not bus]

    def _receive(self) -> None:
        """Every frame waiting on a bus into its pump's inbox, stamped now."""
        wall = self.wall()
        for pump in self._pumps:
            msg = pump.read()
            while msg is not None:
                msg.timestamp = wall
                pump.inbox.append(msg)
                msg = pump.read()

    def deliver(self) -> int:
        """Deliver frames until every registered bus is empty (but for the
        readers stalled now); how many."""
        self._check_thread()
        count = 0
        now = self._now
        while True:
            self._receive()
            ready = [p for p in self._pumps if p.inbox and p.held_until <= now]
            if not ready:
                break
            if self.frame_order is None:
                for pump in ready:
                    while pump.inbox:
                        pump.handler(pump.inbox.popleft())
                        count += 1
            else:
                pump = self.frame_order.choice(ready)
                pump.handler(pump.inbox.popleft())
                count += 1
            if count > self.MAX_FRAMES_PER_STEP:
                raise RuntimeError("more than %d frames at virtual time %.6f: frames answer "
                                   "frames without end" % (self.MAX_FRAMES_PER_STEP, self._now))
        self.frames_delivered += count
        return count

    def notifier(self, bus: can.BusABC, listeners: List[can.Listener], timeout: float = 1.0) -> Any:
        return StepNotifier(self, bus, listeners)

    def frame_reader(self, bus: can.BusABC, name: str) -> FrameReader:
        """The pump receives ``bus``'s frames as they are sent (stamped
        then, as a socket does) and keeps them until the task reads them;
        stalling ``name`` holds them back as it holds the task."""
        waiting: Deque[can.Message] = collections.deque()
        self.add_pump(bus, waiting.append, name)

        def recv() -> Optional[can.Message]:
            return waiting.popleft() if waiting else None
        return FrameReader(recv, lambda: self.remove_pump(bus))

    def run_each(self, fn: Callable[[Any], Any], items: Sequence[Any], workers: int) -> None:
        # one after the other: on virtual time their transfers cost nothing
        for item in items:
            fn(item)


def as_clock(clock: Any) -> Clock:
    """``clock`` if it is a Clock, the real clock for None."""
    if clock is None:
        return REAL
    if isinstance(clock, Clock):
        return clock
    raise TypeError("expected a Clock, not %r" % (clock,))

