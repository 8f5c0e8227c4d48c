"""What a test needs to watch a CAN bus from outside the nodes it tests:
a polling wait, a recorder of every frame, and an SDO observer that reads a
drive's object dictionary independently of the driver.

ROS-free (python-can and canopen only): the end-to-end rostests of both
packages (maxon_epos4_ros_canopen/test/rostest, mani_ros/test/rostest) and
the in-process rigs over python-can's ``virtual`` bus use it.
"""
from __future__ import annotations

import os
import struct
import threading
import time
from typing import Callable, Dict, List, Optional, Tuple, Type

import can
import canopen
from canopen.sdo.exceptions import SdoError


def poll(condition: Callable[[], object], timeout: float, step: float = 0.05,
         stop: Callable[[], bool] = lambda: False,
         ignore: Tuple[Type[BaseException], ...] = ()) -> bool:
    """Call ``condition`` every ``step`` s until it holds (True), ``timeout`` s
    have passed or ``stop()`` says to give up; then the condition's value,
    asked once more, so a condition that came true at the deadline counts.
    An exception of a type in ``ignore`` (a drive not answering yet) counts
    as False."""
    def holds() -> bool:
        try:
            return bool(condition())
        except ignore:
            return False

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not stop():
        if holds():
            return True
        time.sleep(step)
    return holds()


class FrameRecorder:
    """Every frame on a python-can bus from a reader thread, in bus order,
    with its arrival time (time.monotonic()) in ``arrivals``.

    ``marker_id``: an identifier no node under test uses; ``marker_bus``
    opens a second bus on the same channel. ``flush()`` sends a marker
    frame from there and waits until the reader has it: every frame sent
    before is then in ``frames`` (a socket hands a reader the bus's frames in order, python-can
    ``virtual`` likewise). Markers never show in ``frames``.
    """

    def __init__(self, bus: can.BusABC, marker_id: Optional[int] = None,
                 marker_bus: Optional[Callable[[], can.BusABC]] = None, period: float = 0.05) -> None:
        self.bus = bus
        self._period = period  # how long the reader blocks at most: how soon stop() ends it
        self.frames: List[can.Message] = []
        self.arrivals: List[float] = []
        self._marker_id = marker_id
        self._marker_bus = marker_bus
        self._markers_sent: List[bytes] = []
        self._markers_seen: List[bytes] = []
        self._lock = threading.Lock()
        self._running = False
        self._thread: Optional[threading.Thread] = None

    def start(self, drain: bool = True) -> "FrameRecorder":
        """Start the reader; with ``drain``, what the socket kept from before
        is not part of the recording."""
        if drain:
            for _ in range(1000000):
                if self.bus.recv(timeout=0.0) is None:
                    break
        self.clear()
        self._running = True
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()
        return self

    def _loop(self) -> None:
        while self._running:
            try:
                msg = self.bus.recv(timeout=self._period)
            except (can.CanError, OSError, ValueError):  # the bus was shut down under us
                return
            if msg is not None:
                self._keep(msg)

    def _keep(self, msg: can.Message) -> None:
        if (self._marker_id is not None and msg.arbitration_id == self._marker_id
                and bytes(msg.data) in self._markers_sent):
            self._markers_seen.append(bytes(msg.data))
            return
        with self._lock:
            self.arrivals.append(time.monotonic())
            self.frames.append(msg)

    def snapshot(self) -> List[can.Message]:
        with self._lock:
            return list(self.frames)

    def clear(self) -> None:
        with self._lock:
            self.frames = []
            self.arrivals = []

    def take(self) -> List[can.Message]:
        """The frames so far, and an empty recording from here on."""
        with self._lock:
            frames, self.frames, self.arrivals = self.frames, [], []
        return frames

    def with_id(self, can_id: int) -> List[can.Message]:
        return [f for f in self.snapshot() if f.arbitration_id == can_id]

    def matching(self, match: Callable[[can.Message], bool], count: int, timeout: float,
                 step: float = 0.05) -> Optional[List[can.Message]]:
        """The first ``count`` recorded frames that ``match``, once the
        recorder has them; None after ``timeout`` s."""
        found: List[can.Message] = []

        def enough() -> bool:
            found[:] = [f for f in self.snapshot() if match(f)]
            return len(found) >= count

        return found[:count] if poll(enough, timeout, step) else None

    def flush(self, timeout: float, step: float = 0.005) -> bool:
        """Wait until every frame sent before this call is in ``frames``
        (needs ``marker_id``); False after ``timeout`` s."""
        if self._marker_id is None or self._marker_bus is None:
            raise ValueError("flush needs a marker_id and a marker_bus")
        token = os.urandom(8)
        self._markers_sent.append(token)
        sender = self._marker_bus()
        try:
            sender.send(can.Message(arbitration_id=self._marker_id, data=token, is_extended_id=False),
                        timeout=1.0)
        finally:
            sender.shutdown()
        return poll(lambda: token in self._markers_seen, timeout, step)

    def stop(self) -> List[can.Message]:
        """Stop the reader, keep what the socket still holds (on a loaded
        host the reader falls behind: those frames were on the bus before
        this call too) and return the recording."""
        self._running = False
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        for _ in range(1000000):
            msg = self.bus.recv(timeout=0.0)
            if msg is None:
                break
            self._keep(msg)
        return self.snapshot()

    def close(self) -> None:
        self._running = False
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        self.bus.shutdown()


class SdoObserver:
    """Reads drives' object dictionaries over SDO, independently of the
    driver, so a test sees each drive's own values.

    Give it a connected ``canopen.Network``, or a socketcan ``channel``: then
    it opens its own network on which only SDO answers (0x580-0x5FF) reach
    this process (the kernel drops the rest, so the observer does not wake
    for every SYNC and PDO of the drives it watches)."""

    def __init__(self, channel: Optional[str] = None, network: Optional[canopen.Network] = None,
                 response_timeout: float = 2.0) -> None:
        if network is None:
            network = canopen.Network()
            network.connect(interface="socketcan", channel=channel,
                            can_filters=[{"can_id": 0x580, "can_mask": 0x780, "extended": False}])
            self._own = True
        else:
            self._own = False
        self.network = network
        self.response_timeout = response_timeout
        self._nodes: Dict[int, canopen.RemoteNode] = {}

    def node(self, node_id: int) -> canopen.RemoteNode:
        if node_id not in self._nodes:
            node = canopen.RemoteNode(node_id, canopen.ObjectDictionary())
            node.sdo.RESPONSE_TIMEOUT = self.response_timeout
            self.network.add_node(node)
            self._nodes[node_id] = node
        return self._nodes[node_id]

    def try_read(self, node_id: int, index: int, subindex: int = 0, signed: bool = False) -> Optional[int]:
        """One upload; None when the drive does not answer (or answers short)."""
        try:
            return self.upload(node_id, index, subindex, signed)
        except (SdoError, can.CanError, struct.error):
            return None

    def upload(self, node_id: int, index: int, subindex: int = 0, signed: bool = False) -> int:
        data = self.node(node_id).sdo.upload(index, subindex)
        return int.from_bytes(data, "little", signed=signed)

    def read(self, node_id: int, index: int, subindex: int = 0, signed: bool = False,
             within: float = 0.0, attempts: int = 3, pause: float = 0.5) -> int:
        """At least ``attempts`` uploads (the driver may be using the same
        SDO channel a moment), and more until ``within`` s have passed (a
        drive working off a backlog of frames answers late); AssertionError
        naming the object when none answered."""
        last: Optional[Exception] = None
        deadline = time.monotonic() + within
        tries = 0
        while tries < attempts or time.monotonic() < deadline:
            tries += 1
            try:
                return self.upload(node_id, index, subindex, signed)
            except (SdoError, can.CanError, struct.error) as exc:  # struct.error: a forged short answer
                last = exc
                time.sleep(pause)
        raise AssertionError("SDO read of node %d 0x%04X/%d failed (%d attempts): %s"
                             % (node_id, index, subindex, tries, last))

    def close(self) -> None:
        if self._own:
            self.network.disconnect()
