"""The CAN side the canopen library leaves to the master: opening the
python-can bus from ``bus/device`` and ``bus/bitrate`` (can_device.py), the
SYNC producer with ros_canopen's overflow counter (canopen's SyncProducer
sends no counter), kernel-timed on SocketCAN, and the master's heartbeat
producer (``heartbeat/rate``, ``heartbeat/msg``), and the clock that says
when a received frame reached this host."""
from __future__ import annotations

import logging
import select
from typing import Any, Callable, List, Optional, Sequence, Tuple

import can

from ..can_device import MAX_RECEIVE_LAG, ArrivalClock, open_device
from ..clock import REAL, Clock
from ..config_schema import BusConfig, HeartbeatConfig

SYNC_COB_ID = 0x080
# A receive timestamp further than this from the host's wall clock is taken
# for an adapter's own clock: how long the frame waited is then unknown.
log = logging.getLogger("maxon_epos4_ros_canopen.driver")


def open_bus(cfg: BusConfig) -> can.BusABC:
    """The bus of ``bus/device`` and ``bus/bitrate``."""
    return open_device(cfg.device, cfg.bitrate, cfg.loopback)


class SyncProducer:
    """SYNC frames, with the CiA 301 counter 1..overflow when overflow > 0.

    Two ways to run it:

    * ``start(period_s)``: periodic SYNC, timed by the kernel where it can
      be. On SocketCAN the broadcast manager (BCM) sends them from a kernel
      timer, so no scheduling delay of this process shifts a SYNC; with a
      counter, as one BCM task that cycles through the ``overflow`` frames
      with counters 1..overflow (BCM sends fixed frames, a sequence is how
      it changes data). Other interfaces (python-can's ``virtual``), or a
      kernel without can-bcm, get python-can's sender thread with the same
      frame sequence. ``kernel_timed`` says which.
    * ``send()``: one SYNC now, the counter advanced (a cycle that sends its
      own SYNC).

    While started, ``index_at(t)``/``counter_at(t)``/``next_after(t)`` give
    the schedule (SYNC number, its counter, the next SYNC's time, all on
    ``clock``), so a cycle can be paced between kernel SYNCs: its RxPDOs
    only have to land before the next SYNC. Without a kernel timer the
    clock runs the periodic task (a thread, or a stepped clock's event).
    """

    def __init__(self, bus: can.BusABC, overflow: int, clock: Clock = REAL) -> None:
        self.bus = bus
        self.clock = clock
        self.overflow = overflow
        self.counter = 0          # counter of the last send() (0: none yet or no counter)
        self.sent = 0             # SYNCs sent by send()
        self.kernel_timed = False
        self.period: Optional[float] = None
        self.first_at: Optional[float] = None   # monotonic time of the first periodic SYNC
        self._msg = can.Message(arbitration_id=SYNC_COB_ID, is_extended_id=False,
                                data=b"\x00" if overflow else b"")
        self._task: Any = None
        self.send_errors: Optional[SendErrors] = None  # the thread's, when the thread sends

    def _advance(self, msg: can.Message) -> None:
        self.sent += 1
        if self.overflow:
            self.counter = self.counter % self.overflow + 1
            msg.data[0] = self.counter

    def send(self) -> None:
        self._advance(self._msg)
        self.bus.send(self._msg)

    def frames(self) -> List[can.Message]:
        """The periodic sequence: one frame, or one per counter value."""
        if not self.overflow:
            return [can.Message(arbitration_id=SYNC_COB_ID, is_extended_id=False, data=b"")]
        return [can.Message(arbitration_id=SYNC_COB_ID, is_extended_id=False, data=bytes([c]))
                for c in range(1, self.overflow + 1)]

    def start(self, period_s: float, kernel: bool = True) -> None:
        """Periodic SYNC every period_s; kernel=False forces the thread
        (benchmarks compare both). Restarting begins again at counter 1."""
        if not period_s > 0:
            raise ValueError("SYNC period must be > 0, not %r" % (period_s,))
        self.stop()
        task, self.send_errors = start_periodic(self.bus, self.frames(), period_s, "SYNC", kernel,
                                                clock=self.clock)
        self.kernel_timed = self.send_errors is None
        self.first_at = self.clock.now() + (period_s if self.kernel_timed else 0.0)
        self.period = period_s
        self._task = task

    def index_at(self, t: float) -> int:
        """Number of periodic SYNCs sent up to monotonic time t (by the schedule)."""
        if self.period is None or self.first_at is None or t < self.first_at:
            return 0
        return int((t - self.first_at) // self.period) + 1

    def counter_at(self, t: float) -> int:
        """Counter of the last periodic SYNC at or before t (0: none, or no counter)."""
        k = self.index_at(t)
        return (k - 1) % self.overflow + 1 if self.overflow and k else 0

    def next_after(self, t: float) -> float:
        """Monotonic time of the first periodic SYNC after t."""
        if self.period is None or self.first_at is None:
            raise RuntimeError("SYNC producer not started")
        return self.first_at + self.index_at(t) * self.period

    def stop(self) -> None:
        if self._task is not None:
            self._task.stop()
            self._task = None
        self.period = None
        self.first_at = None


class SendErrors:
    """The bus a python-can sender thread sends through: a send error (bus
    down, transmit queue full) is counted here, not raised. python-can's
    thread ends at the first error that reaches it, so one lost frame
    would end the master's heartbeat for good, and every drive's consumer
    would then stop its drive; the thread goes on and the frames are back
    as soon as the bus is."""

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus
        self.count = 0
        self.last: Optional[BaseException] = None

    def send(self, msg: can.Message, timeout: Optional[float] = None) -> None:
        try:
            self.bus.send(msg, timeout)
        except (can.CanError, OSError) as e:
            self.count += 1
            self.last = e


def start_periodic(bus: can.BusABC, msgs: Sequence[can.Message], period_s: float, what: str,
                   kernel: bool = True, store_task: bool = False, clock: Clock = REAL
                   ) -> Tuple[Any, Optional[SendErrors]]:
    """msgs sent in turn every period_s, the task and its SendErrors: the
    broadcast manager sends them on SocketCAN (errors None: the kernel's
    timer goes on whatever a send meets; store_task: the bus's shutdown
    ends the task), python-can's sender thread everywhere else, through
    SendErrors (a kernel without can-bcm too, with a warning naming
    ``what``); kernel=False forces the thread. The thread is ``clock``'s:
    a stepped clock runs the sends as its events. Either task has stop()."""
    if kernel and is_socketcan(bus):
        try:
            # no modifier callback: python-can then uses BCM, which sends
            # the first frame one period after setup
            return bus.send_periodic(list(msgs), period_s, store_task=store_task), None
        except (OSError, can.CanError) as e:  # can-bcm not loaded
            log.warning("%s: no kernel timer on %s (%s): sending from a thread", what, bus.channel_info, e)
    errors = SendErrors(bus)
    # RealClock: python-can's sender thread (on_error: whatever SendErrors
    # does not catch, python-can logs, and the thread goes on); its first
    # frame goes out at once
    return clock.send_periodic(errors, list(msgs), period_s, what), errors


def is_socketcan(bus: can.BusABC) -> bool:
    """A python-can SocketCAN bus (kernel timers and filters available)."""
    try:
        from can.interfaces.socketcan import SocketcanBus
    except ImportError:  # pragma: no cover - python-can always ships it
        return False
    return isinstance(bus, SocketcanBus)


class HeartbeatProducer:
    """The master's own heartbeat, a fixed frame sent at ``rate`` Hz."""

    def __init__(self, bus: can.BusABC, cfg: HeartbeatConfig, clock: Clock = REAL) -> None:
        self.bus = bus
        self.clock = clock
        self.period_s = 1.0 / cfg.rate
        self._msg = can.Message(arbitration_id=cfg.can_id, data=cfg.data, is_extended_id=cfg.extended)
        self._task: Any = None
        self.send_errors: Optional[SendErrors] = None  # the thread's, when the thread sends

    def start(self) -> None:
        if self._task is None:
            self._task, self.send_errors = start_periodic(self.bus, [self._msg], self.period_s, "heartbeat",
                                                          store_task=True, clock=self.clock)

    def stop(self) -> None:
        if self._task is not None:
            self._task.stop()
            self._task = None


def unread_frames(bus: can.BusABC) -> Optional[Callable[[], bool]]:
    """Whether frames wait in ``bus``'s receive queue that its reader has not
    taken yet. python-can has no such question; SocketCAN answers it with a
    select() that takes nothing, python-can's virtual bus with its queue.
    Other adapters buffer in their vendor's library, out of sight: None,
    no answer."""
    sock = getattr(bus, "socket", None)
    if is_socketcan(bus) and sock is not None:
        def socket_readable() -> bool:
            try:
                return bool(select.select([sock], [], [], 0.0)[0])
            except (OSError, ValueError):  # closed, or the interface went away
                return False
        return socket_readable
    pending = getattr(bus, "queue", None)
    if pending is not None and callable(getattr(pending, "empty", None)):
        return lambda: not pending.empty()
    return None


class ReceiveClock(can.Listener):
    """When frames reached this host, on the monotonic clock, and how far
    the CAN notifier has read.

    A loaded host can leave the notifier thread unscheduled for a while
    with frames waiting in the socket. A watchdog that judged a drive by
    when its frames were read would then take the driver's own stall for
    the drive's silence: each frame counts from when it arrived
    (``can_device.ArrivalClock``). An SDO transfer waiting for its answer
    asks ``unread_before`` the same question.

    The notifier's listener (link._Reception) calls it first for every
    frame: the subscribers it calls after it take the frame's times from
    ``progress`` instead of reading a clock each. ``progress`` is replaced whole by the notifier thread, one
    immutable tuple: (monotonic time the latest frame was read, when it
    arrived)."""

    def __init__(self, unread: Optional[Callable[[], bool]] = None, max_lag: float = MAX_RECEIVE_LAG,
                 clock: Clock = REAL) -> None:
        """``unread``: whether frames wait unread (unread_frames; None: the
        adapter cannot tell, and none are taken to wait)."""
        self._now = clock.now
        now = self._now()
        self.progress: Tuple[float, float] = (now, now)
        self._unread = unread
        self._arrival = ArrivalClock(clock.now, max_lag=max_lag, wall=clock.wall)
        self.max_lag = max_lag  # the longest backlog it can tell (can_device.max_receive_lag)

    def on_message_received(self, msg: can.Message) -> None:
        now = self._now()
        self.progress = (now, self._arrival.arrival(msg.timestamp, now))

    def times(self) -> Tuple[float, float]:
        """When the frame being handled (the latest) was read, and when it arrived."""
        return self.progress

    def lag(self) -> float:
        """How far the notifier is behind (s): how long the latest frame read
        had waited in the receive queue while frames still wait unread, 0
        once it has read all that came (a bus gone quiet after a burst is
        no backlog). Where the adapter cannot tell, the latest frame's wait."""
        if self._unread is not None and not self._unread():
            return 0.0
        read_at, arrived = self.progress
        return read_at - arrived

    def unread_before(self, t: float) -> bool:
        """Whether frames that reached this host before monotonic ``t`` may
        still wait unread: the notifier has read nothing that arrived at
        ``t`` or later, and the receive queue is not empty. Frames are read
        in the order they came, so once one that arrived after ``t`` has
        been read, all those before it have been too."""
        return self.progress[1] < t and self._unread is not None and self._unread()
