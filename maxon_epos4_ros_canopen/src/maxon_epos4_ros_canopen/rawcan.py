"""CAN frames straight on a SocketCAN socket, for the simulator's bus and
the driver cycle's own receiver (driver/cycle_reception.py).

python-can's SocketCAN bus makes several system calls per frame: a send
reads the wall clock and polls the socket before writing, a receive reads
the wall clock (twice when it finds nothing) and polls before reading, and
each frame becomes a Message object. Natively that is cheap; in user-mode
Linux every system call is a round trip through the host (a clock read
about 25 µs), and for the simulator, which sends and receives several
frames per drive and SYNC, they were most of its CPU. Here a frame is one
system call each way (a receive that may wait polls first, as python-can
does), in the same struct can_frame layout (<linux/can.h>).
"""
from __future__ import annotations

import select
import socket
import struct
from typing import Any, Iterable, Optional, Tuple

# struct can_frame / canfd_frame: can_id, len, flags (FD), reserved, len8_dlc, then the data
_HEADER = struct.Struct("=IBB1xB")
_STAMP = struct.Struct("@ll")  # struct timespec of SO_TIMESTAMPNS
SO_TIMESTAMPNS = 35
CAN_EFF_FLAG, CAN_RTR_FLAG, CAN_ERR_FLAG, CAN_SFF_MASK = 0x80000000, 0x40000000, 0x20000000, 0x7FF
CAN_MTU, CANFD_MTU = 16, 72
try:
    _ANCILLARY = socket.CMSG_SPACE(_STAMP.size)
except AttributeError:  # pragma: no cover - not Linux: no SocketCAN either
    _ANCILLARY = 0

# (can_id with its EFF/RTR/ERR flags, data (empty for a remote frame), kernel time stamp on the wall clock)
Frame = Tuple[int, bytes, float]


def socketcan_socket(bus: Any) -> Optional[socket.socket]:
    """The raw socket of a python-can SocketCAN bus that filters nothing
    (the simulator's own), else None: other buses keep python-can's path."""
    try:
        from can.interfaces.socketcan import SocketcanBus
    except ImportError:  # pragma: no cover - python-can without SocketCAN
        return None
    sock = getattr(bus, "socket", None)
    if not isinstance(bus, SocketcanBus) or not isinstance(sock, socket.socket) or bus.filters:
        return None
    if type(bus).send is not SocketcanBus.send or type(bus).recv is not SocketcanBus.recv:
        return None  # a subclass that does more than python-can's bus
    return sock


def encode(cob_id: int, data: bytes, remote: bool) -> bytes:
    """A classic frame with an 11-bit identifier, as python-can's
    build_can_frame writes it (a remote frame: DLC 0, as the simulator asks)."""
    if remote:
        return _HEADER.pack(cob_id | CAN_RTR_FLAG, 0, 0, 0) + bytes(8)
    return _HEADER.pack(cob_id, len(data), 0, len(data)) + bytes(data).ljust(8, b"\x00")


def kernel_stamp(ancillary: Iterable[Tuple[int, int, bytes]]) -> float:
    """The SO_TIMESTAMPNS receive stamp among recvmsg's ancillary data, on
    the wall clock (0.0: none)."""
    stamp = 0.0
    for level, kind, data in ancillary:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(data) >= _STAMP.size:
            seconds, nanoseconds = _STAMP.unpack_from(data)
            stamp = seconds + nanoseconds * 1e-9  # python-can's own sum: the same float
    return stamp


def decode(frame: bytes, ancillary: list) -> Frame:
    """One frame as recvmsg returned it, with its SO_TIMESTAMPNS time stamp."""
    can_id, length, _, _ = _HEADER.unpack_from(frame)
    stamp = kernel_stamp(ancillary)
    if can_id & CAN_RTR_FLAG:
        return can_id, b"", stamp  # python-can's Message keeps no data for a remote frame
    return can_id, bytes(frame[8:8 + length]), stamp


class RawSocketcan:
    """Receive and send on ``sock`` (a python-can SocketCAN bus's socket).
    Errors are OSError, as the socket raises them."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self._recvmsg = sock.recvmsg

    def recv(self, timeout: float) -> Optional[Frame]:
        """The next frame, or None once ``timeout`` s passed without one
        (0: only one already waiting, one system call)."""
        if timeout > 0.0:
            if not select.select([self.sock], [], [], timeout)[0]:
                return None
        try:
            frame, ancillary, _, _ = self._recvmsg(CANFD_MTU, _ANCILLARY, socket.MSG_DONTWAIT)
        except BlockingIOError:
            return None
        return decode(frame, ancillary)

    def send(self, cob_id: int, data: bytes, remote: bool) -> None:
        """One frame, or OSError (BlockingIOError where python-can would
        find no room, ENOBUFS where the interface's queue is full)."""
        self.sock.send(encode(cob_id, data, remote), socket.MSG_DONTWAIT)
