"""Naming a CAN adapter in one string, as ``bus/device`` and the tools take
it; and when a received frame reached the host.

``can0`` is a SocketCAN interface (ros_canopen's only kind); ``INTERFACE:CHANNEL``
is any adapter python-can supports: ``pcan:PCAN_USBBUS1``, ``ixxat:0``,
``kvaser:0``, ``slcan:/dev/ttyACM0``, ``virtual:NAME`` (in-process, for tests).
"""
from __future__ import annotations

import errno
import math
import socket
import time
from typing import Callable, Optional, Tuple

import can

SOCKETCAN = "socketcan"
# Adapters opened without a bit rate (SocketCAN's is set
# with `ip link`, python-can's virtual bus has none).
NO_BITRATE = frozenset({SOCKETCAN, "virtual", "socketcand"})
DEFAULT_BITRATE = 1000000  # maxon's recommendation for EPOS4 networks


# A receive stamp further from the wall clock than this is an adapter's own
# clock (or the wall clock stepped): the frame counts as read on arrival.
MAX_RECEIVE_LAG = 5.0
# SocketCAN and python-can's virtual bus stamp each frame with this host's
# wall clock: a lag seconds long is a real backlog (a host too loaded to
# keep up: 5 to 15 s were seen in user-mode Linux under a storm of frames),
# up to what a receive buffer holds, well under a minute of traffic.
HOST_STAMPED_MAX_LAG = 60.0


def max_receive_lag(bus: can.BusABC) -> float:
    """How far behind a frame's receive stamp may be and still be a stamp of
    this host's wall clock, for ``bus``."""
    from can.interfaces.socketcan import SocketcanBus
    from can.interfaces.virtual import VirtualBus
    return HOST_STAMPED_MAX_LAG if isinstance(bus, (SocketcanBus, VirtualBus)) else MAX_RECEIVE_LAG


class ArrivalClock:
    """When a received frame reached this host, on ``clock`` (monotonic).

    The kernel stamps each frame as it arrives (python-can's ``timestamp``,
    wall clock on SocketCAN and the virtual bus); its distance from the wall
    clock when the frame is read is how long it waited in the socket.

    The offset between the wall clock and the monotonic one is read once a
    second, not for each frame: where reading a clock is a system call
    (user-mode Linux, about 80 us: more than the rest of a frame's handling)
    a busy bus would spend the reader's time on the clock and fall behind.
    Reading it again each second, and before a frame that seems to have
    waited long, follows a wall clock that was stepped.
    One reader thread owns an instance."""

    REFRESH_S = 1.0
    CHECK_LAG_S = 0.2  # a frame that waited longer has the offset read again first,
    CHECK_S = 0.1      # unless it was read that recently

    def __init__(self, clock: Callable[[], float] = time.monotonic, max_lag: float = MAX_RECEIVE_LAG,
                 wall: Optional[Callable[[], float]] = None) -> None:
        self._clock = clock
        # what frames are stamped with (time.time looked up at each read)
        self._wall = wall if wall is not None else lambda: time.time()
        self.max_lag = max_lag  # see max_receive_lag
        self._taken = -math.inf  # when the offset was read, on clock
        self._offset = 0.0       # wall clock minus clock

    def arrival(self, timestamp: float, read_at: float) -> float:
        """When a frame stamped ``timestamp`` and read at ``read_at`` (on
        clock) reached the host."""
        if not 0.0 <= read_at - self._taken <= self.REFRESH_S:
            self._refresh(read_at)
        lag = read_at + self._offset - timestamp
        if lag > self.CHECK_LAG_S and read_at - self._taken > self.CHECK_S:
            # a long wait, or a wall clock stepped back since the offset was
            # read: which of the two, a fresh offset tells (a backlog asks at
            # most every CHECK_S)
            self._refresh(read_at)
            lag = read_at + self._offset - timestamp
        return read_at - lag if 0.0 <= lag <= self.max_lag else read_at

    def _refresh(self, read_at: float) -> None:
        self._offset = self._wall() - self._clock()
        self._taken = read_at


class DeliveryDelay:
    """How late this host's kernel makes a frame readable after stamping it.

    A frame is stamped as it is sent; on a loaded host it may wait in the
    kernel (a stalled network softirq, a guest kernel left unscheduled)
    before its reader's socket has it. A socket found empty therefore
    means only that every frame sent up to ``delay()`` before was read.
    The evidence: a frame stamped before the moment its socket was last
    found empty was on its way then, at least for the difference. The
    estimate is the largest such difference, decaying with ``TAU_S`` so
    that a host that has become quiet is judged quiet again; it is 0 on a
    host that never delivered late. One reader thread owns an instance."""

    TAU_S = 10.0
    MAX_S = 1.0  # a longer wait than this is a stall of the reader, which it accounts itself

    def __init__(self) -> None:
        self._delay = 0.0
        self._at = 0.0

    def delay(self, now: float) -> float:
        """The estimate at ``now``."""
        if self._delay <= 0.0:
            return 0.0
        return self._delay * math.exp(-max(0.0, now - self._at) / self.TAU_S)

    def frame(self, arrival: float, empty_at: float, now: float) -> None:
        """A frame that reached the host at ``arrival`` was read at ``now``;
        its socket was last found empty at ``empty_at``."""
        late = min(empty_at - arrival, self.MAX_S)
        if late > 0.0 and late > self.delay(now):
            self._delay, self._at = late, now


# Receive buffer asked for on a SocketCAN socket: about a second of a full
# 1 Mbit/s bus (some 8,000 frames, each about 1 KB of kernel bookkeeping).
# The kernel's default holds a few hundred frames: a process the host left
# unscheduled for a third of a second would lose the rest, heartbeats too.
RECEIVE_BUFFER_BYTES = 8 * 1024 * 1024
_SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)  # Linux; beyond net.core.rmem_max


def enlarge_receive_buffer(sock: socket.socket, size: int = RECEIVE_BUFFER_BYTES) -> int:
    """Ask for a receive buffer of ``size`` bytes: beyond net.core.rmem_max
    where the process may (CAP_NET_ADMIN), else up to that limit. Returns
    what the kernel granted (it doubles a request for its bookkeeping)."""
    for option in (_SO_RCVBUFFORCE, socket.SO_RCVBUF):
        try:
            sock.setsockopt(socket.SOL_SOCKET, option, size)
            break
        except OSError:  # not permitted: the plain option, capped by rmem_max
            continue
    return sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)


class CanDeviceError(Exception):
    """A ``bus/device`` that names no usable CAN adapter; the message names it."""


def parse_device(device: str) -> Tuple[str, str]:
    """``bus/device`` as (python-can interface, channel).

    ``can0`` -> SocketCAN ``can0``; ``INTERFACE:CHANNEL`` -> any interface
    python-can knows (``pcan:PCAN_USBBUS1``, ``ixxat:0``, ``kvaser:0``,
    ``slcan:/dev/ttyACM0``, ``virtual:NAME``); only the first colon splits.
    """
    if not isinstance(device, str) or not device.strip():
        raise CanDeviceError("CAN device %r: empty name" % (device,))
    if ":" not in device:
        return SOCKETCAN, device
    interface, channel = device.split(":", 1)
    if interface not in can.interfaces.VALID_INTERFACES:
        raise CanDeviceError("CAN device %r: unknown interface %r (python-can knows %s; a name without "
                             "':' is a SocketCAN interface)"
                             % (device, interface, ", ".join(sorted(can.interfaces.VALID_INTERFACES))))
    if not channel:
        raise CanDeviceError("CAN device %r: no channel after %r" % (device, interface + ":"))
    return interface, channel


def open_device(device: str, bitrate: Optional[int] = None, receive_own_messages: bool = False) -> can.BusABC:
    """Opens ``device`` (see parse_device); ``bitrate`` (bit/s) goes to the
    adapters that take one, 1 Mbit/s when not given. Any failure is a
    CanDeviceError naming the device."""
    interface, channel = parse_device(device)
    kwargs = {"interface": interface, "channel": channel, "receive_own_messages": receive_own_messages}
    if interface not in NO_BITRATE:
        kwargs["bitrate"] = int(bitrate) if bitrate else DEFAULT_BITRATE
    try:
        bus = can.Bus(**kwargs)
    except Exception as exc:  # python-can raises OSError, CanError, NameError, ImportError ... per adapter
        raise CanDeviceError("CAN device %r (python-can interface %s, channel %s): %s%s"
                             % (device, interface, channel, exc, _hint(interface, channel, exc))) from None
    sock = getattr(bus, "socket", None)
    if interface == SOCKETCAN and isinstance(sock, socket.socket):
        enlarge_receive_buffer(sock)
    return bus


def _hint(interface: str, channel: str, exc: Exception) -> str:
    if interface == SOCKETCAN and isinstance(exc, OSError) and exc.errno == errno.ENODEV:
        return " (no network interface %s: `ip link show` lists them; a virtual one: " \
               "`ip link add dev %s type vcan && ip link set %s up`)" % (channel, channel, channel)
    if interface == SOCKETCAN and isinstance(exc, OSError) and exc.errno == errno.EAFNOSUPPORT:
        return " (this kernel has no SocketCAN)"
    if interface != SOCKETCAN:
        return " (is the adapter plugged in and its vendor library installed?)"
    return ""
