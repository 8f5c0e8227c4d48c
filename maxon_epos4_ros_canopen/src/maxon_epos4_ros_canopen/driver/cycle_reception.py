"""The cycle's own reception of TxPDOs and SYNC.

The drives' TxPDOs and the SYNC frames are most of what the driver
receives: several frames per axis every cycle. Handed over by canopen's
notifier thread, each frame wakes that thread and passes the interpreter
lock to it and back; on a host where a thread handoff costs hundreds of
microseconds (a virtual machine, user-mode Linux) that handoff was the
largest part of the driver's CPU. Here a receiver of their own carries
only those frames (the kernel filters them out of the notifier's socket),
and the cycle thread reads everything waiting at the top of each cycle,
as a hand-written control loop does: no thread wakes per frame.

What the notifier path did stays: each frame counts from when it reached
this host (the kernel's receive stamp, see can_device.ArrivalClock), a
frame of the wrong length is rejected and counted, a second frame of a
COB-ID in one SYNC period is a conflict, a SYNC heard on the bus paces the
cycle (pdo.TpdoReceiver does all that). A receive error (an interface
going down) is counted and logged at most once a second, and the cycle
goes on: the TxPDO watchdog then sees the silence. At most ``budget``
frames are read per cycle, so that a flood of forged frames on a TxPDO's
COB-ID cannot keep the cycle from sending; the rest wait for the next one.

Receivers:

* ``RawCanReceiver``: a SocketCAN raw socket of its own, kernel-filtered
  (or a socket a caller gives that carries SocketCAN frames).
* ``BusReceiver``: any python-can bus that carries those frames (a second
  python-can virtual bus on the driver's channel in stepped runs, or a bus
  a caller gives), read through the clock (clock.Clock.frame_reader): a
  stepped clock delivers to it as to everything else.

Adapters that cannot open a second receiver on one channel (vendor
libraries) keep the notifier path (link.py), and so does python-can's
virtual bus on the wall clock, where the fast suite's real-time tests run
that path.
"""
from __future__ import annotations

import logging
import socket
import struct
from typing import Callable, Iterable, List, Optional, Tuple, Union

import can

from ..can_device import ArrivalClock, enlarge_receive_buffer
from ..clock import Clock, FrameReader
from ..rawcan import CAN_EFF_FLAG, CAN_ERR_FLAG, CAN_MTU, CAN_RTR_FLAG, CAN_SFF_MASK, SO_TIMESTAMPNS, kernel_stamp
from .bus import SYNC_COB_ID
from .pdo import TpdoReceiver

log = logging.getLogger("maxon_epos4_ros_canopen.driver")

# The cycle's task, by name: a stepped clock holds its receiver's frames
# when it stalls the task (clock.SteppedClock.stall)
CYCLE_TASK = "epos4_driver_cycle"
# A received frame: COB-ID, payload, and when it reached this host (wall
# clock, the kernel's stamp); the stamp is None where none came.
Received = Tuple[int, bytes, Optional[float]]

_FILTER = struct.Struct("=II")  # struct can_filter: can_id, can_mask
_CAN_FRAME = struct.Struct("=IB3x8s")  # struct can_frame: can_id, len, padding, data
_NOT_DATA = CAN_EFF_FLAG | CAN_RTR_FLAG | CAN_ERR_FLAG
_MSG_TRUNC = int(socket.MSG_TRUNC)  # a plain int: an enum flag in the & costs more than the read
# per frame read, per expected frame of a cycle: room for a late cycle's backlog
BUDGET_PER_FRAME = 8
MIN_BUDGET = 64
ERROR_LOG_INTERVAL = 1.0  # s


def parse_frame(frame: bytes, ancillary: Iterable[Tuple[int, int, bytes]]) -> Optional[Received]:
    """A SocketCAN ``struct can_frame`` and its receive stamp as a
    Received; None for what is no classic standard data frame (extended,
    remote, error, CAN FD, a length over 8, truncated). The cycle parses
    every TxPDO here, with one struct call per frame."""
    if len(frame) != CAN_MTU:
        return None
    can_id, length, data = _CAN_FRAME.unpack(frame)
    if can_id & _NOT_DATA or length > 8:
        return None
    return can_id, data[:length], kernel_stamp(ancillary) or None


class RawCanReceiver:
    """SocketCAN frames read straight from a socket, without blocking:
    ``open`` makes a raw CAN socket on a channel that receives only standard
    data frames on given COB-IDs; a socket given (a socketpair that carries
    ``struct can_frame`` as a CAN_RAW socket reads them: the cycle
    benchmark's) is read the same way.

    Written by hand, not a second python-can SocketcanBus: python-can's
    receive makes a select() before every read, and here the cycle reads
    until the socket is empty: one system call per frame instead of two,
    where a system call costs tens of microseconds (user-mode Linux)."""

    def __init__(self, sock: socket.socket, owned: bool = True) -> None:
        """Reads ``sock`` (made non-blocking, with kernel receive stamps);
        ``owned``: close() closes it."""
        sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        sock.setblocking(False)
        self._sock = sock
        self._owned = owned
        self._ancillary = socket.CMSG_SPACE(16)  # one struct timespec

    @classmethod
    def open(cls, channel: str, cob_ids: Iterable[int]) -> "RawCanReceiver":
        """A raw CAN socket of its own on ``channel``, kernel-filtered to
        standard data frames on ``cob_ids``."""
        sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
        try:
            mask = CAN_EFF_FLAG | CAN_RTR_FLAG | CAN_SFF_MASK  # this id, standard, data frames only
            filters = b"".join(_FILTER.pack(c, mask) for c in sorted(set(cob_ids)))
            sock.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FILTER, filters)
            enlarge_receive_buffer(sock)
            sock.bind((channel,))
            return cls(sock)
        except BaseException:
            sock.close()
            raise

    def take(self, limit: int) -> Tuple[List[Received], Optional[BaseException]]:
        """Up to ``limit`` frames waiting, oldest first, and the receive
        error that ended the read (None: the socket was empty or the limit
        reached)."""
        out: List[Received] = []
        append, parse = out.append, parse_frame
        recvmsg, size, ancillary = self._sock.recvmsg, CAN_MTU, self._ancillary
        while len(out) < limit:
            try:
                frame, anc, flags, _addr = recvmsg(size, ancillary)
            except BlockingIOError:
                return out, None
            except OSError as e:  # ENETDOWN once when the interface goes down, EBADF once closed
                return out, e
            if flags & _MSG_TRUNC:  # longer than a can_frame (CAN FD): cut to its size, it would pass for one
                continue
            received = parse(frame, anc)
            if received is not None:
                append(received)
        return out, None

    def close(self) -> None:
        if self._owned:
            self._sock.close()


class BusReceiver:
    """Frames of a python-can bus that carries the TxPDOs and SYNC, read
    through ``reader`` (clock.FrameReader); frames on other COB-IDs are
    dropped here (a virtual bus has no kernel filter)."""

    def __init__(self, reader: FrameReader, cob_ids: Iterable[int], shutdown: Callable[[], None] = lambda: None
                 ) -> None:
        self._reader = reader
        self._wanted = frozenset(cob_ids)
        self._shutdown = shutdown

    def take(self, limit: int) -> Tuple[List[Received], Optional[BaseException]]:
        out: List[Received] = []
        recv, wanted = self._reader.recv, self._wanted
        while len(out) < limit:
            try:
                msg = recv()
            except (can.CanError, OSError, ValueError) as e:
                return out, e
            if msg is None:
                return out, None
            if (msg.arbitration_id in wanted and not msg.is_extended_id and not msg.is_remote_frame
                    and not msg.is_error_frame):
                out.append((msg.arbitration_id, bytes(msg.data), msg.timestamp))
        return out, None

    def close(self) -> None:
        self._reader.close()
        self._shutdown()


class CycleReception:
    """Reads the cycle's receiver into ``receiver`` (see the module's
    docstring). Owned by the cycle thread while a cycle runs, by the
    service holding the service lock otherwise."""

    def __init__(self, source: Union[RawCanReceiver, BusReceiver], receiver: TpdoReceiver, clock: Clock,
                 max_lag: float) -> None:
        self._source = source
        self._receiver = receiver
        self._clock = clock
        self._arrival = ArrivalClock(clock.now, max_lag=max_lag, wall=clock.wall)
        self.budget = max(MIN_BUDGET, BUDGET_PER_FRAME * (len(receiver.cob_ids) + 1))
        # (monotonic time the latest frame was read, when it arrived): a
        # new tuple each time, read by diagnostics in other threads
        now = clock.now()
        self.progress: Tuple[float, float] = (now, now)
        self.frames = 0          # frames read
        self.full_reads = 0      # reads that stopped at the budget with frames left
        self.errors = 0          # receive errors
        self.last_error: Optional[BaseException] = None
        self._logged = -float("inf")

    def poll(self, now: float, limit: Optional[int] = None) -> int:
        """Every frame waiting (up to ``limit``, the budget unless given)
        into the receiver, read at ``now``; how many. Never raises."""
        limit = self.budget if limit is None else limit
        try:
            frames, error = self._source.take(limit)
        except Exception as e:  # a receiver broken in a way not foreseen: the cycle goes on
            frames, error = [], e
        if frames:
            receiver = self._receiver
            put, sync_heard, lengths = receiver.put, receiver.sync_heard, receiver.lengths
            arrival = self._arrival.arrival
            arrived = now
            for can_id, data, stamp in frames:
                arrived = now if stamp is None else arrival(stamp, now)
                if can_id == SYNC_COB_ID:
                    sync_heard(arrived)
                elif can_id in lengths:
                    put(can_id, data, now, arrived)
            self.progress = (now, arrived)
            self.frames += len(frames)
            if len(frames) >= limit:
                self.full_reads += 1
        elif error is None:  # nothing waited: behind by nothing, whatever the last frame's wait
            self.progress = (now, now)
        if error is not None:
            self.errors += 1
            self.last_error = error
            if now - self._logged >= ERROR_LOG_INTERVAL:
                self._logged = now
                log.error("CAN receive error (TxPDOs and SYNC): %s", error)
        return len(frames)

    def lag(self) -> float:
        """How long the latest frame read had waited (s); 0 once a read
        found nothing waiting."""
        read_at, arrived = self.progress
        return read_at - arrived

    def close(self) -> None:
        try:
            self._source.close()
        except Exception as e:  # closing goes on whatever the receiver says
            log.warning("closing the TxPDO receiver: %s", e)
