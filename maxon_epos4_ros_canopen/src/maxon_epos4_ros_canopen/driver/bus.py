"""The CAN side the canopen library leaves to the master: opening the
python-can bus from ``bus/device`` and ``bus/bitrate`` (can_device.py), the
SYNC producer with ros_canopen's overflow counter (canopen's SyncProducer
sends no counter), kernel-timed on SocketCAN, and the master's heartbeat
producer (``heartbeat/rate``, ``heartbeat/msg``), and the clock that says
when a received frame reached this host."""
from __future__ import annotations

import logging
import time
from typing import List, Optional, Tuple

import can

from ..can_device import arrival_time, open_device
from ..config import BusConfig, HeartbeatConfig

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
    ``time.monotonic()``), so a cycle can be paced between kernel SYNCs:
    its RxPDOs only have to land before the next SYNC.
    """

    def __init__(self, bus: can.BusABC, overflow: int) -> None:
        self.bus = bus
        self.overflow = overflow
        self.counter = 0          # counter of the last send() (0: none yet or no counter)
        self.sent = 0             # SYNCs sent by send()
        self.kernel_timed = False
        self.period: Optional[float] = None
        self.first_at: Optional[float] = None   # monotonic time of the first periodic SYNC
        self._msg = can.Message(arbitration_id=SYNC_COB_ID, is_extended_id=False,
                                data=b"\x00" if overflow else b"")
        self._task: Optional[can.broadcastmanager.CyclicSendTaskABC] = None

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
        msgs = self.frames()
        task = None
        if kernel and is_socketcan(self.bus):
            try:
                # no modifier callback: python-can then uses BCM, which sends
                # the first frame one period after setup
                task = self.bus.send_periodic(msgs, period_s, store_task=False)
                self.first_at = time.monotonic() + period_s
                self.kernel_timed = True
            except (OSError, can.CanError) as e:  # can-bcm not loaded
                log.warning("SYNC: no kernel timer on %s (%s): sending from a thread", self.bus.channel_info, e)
        if task is None:
            self.kernel_timed = False
            self.first_at = time.monotonic()
            # python-can's generic sender thread (what send_periodic falls
            # back to); the thread sends the first frame at once
            task = can.BusABC._send_periodic_internal(self.bus, msgs, period_s)
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


def is_socketcan(bus: can.BusABC) -> bool:
    """A python-can SocketCAN bus (kernel timers and filters available)."""
    try:
        from can.interfaces.socketcan import SocketcanBus
    except ImportError:  # pragma: no cover - python-can always ships it
        return False
    return isinstance(bus, SocketcanBus)


class HeartbeatProducer:
    """The master's own heartbeat, a fixed frame sent at ``rate`` Hz."""

    def __init__(self, bus: can.BusABC, cfg: HeartbeatConfig) -> None:
        self.bus = bus
        self.period_s = 1.0 / cfg.rate
        self._msg = can.Message(arbitration_id=cfg.can_id, data=cfg.data, is_extended_id=cfg.extended)
        self._task: Optional[can.broadcastmanager.CyclicSendTaskABC] = None

    def start(self) -> None:
        if self._task is None:
            self._task = self.bus.send_periodic(self._msg, self.period_s)

    def stop(self) -> None:
        if self._task is not None:
            self._task.stop()
            self._task = None


class ReceiveClock(can.Listener):
    """When frames reached this host, on the monotonic clock, and how far
    the CAN notifier has read.

    A loaded host can leave the notifier thread unscheduled for a while
    with frames waiting in the socket. A watchdog that judged a drive by
    when its frames were read would then take the driver's own stall for
    the drive's silence: each frame counts from when it arrived
    (``can_device.arrival_time``).

    ``progress`` is replaced whole by the notifier thread, one immutable
    tuple: (monotonic time the latest frame was read, when it arrived)."""

    def __init__(self) -> None:
        now = time.monotonic()
        self.progress: Tuple[float, float] = (now, now)

    arrival = staticmethod(arrival_time)

    def on_message_received(self, msg: can.Message) -> None:
        now = time.monotonic()
        self.progress = (now, self.arrival(msg.timestamp, now))
