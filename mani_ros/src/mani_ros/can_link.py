"""One CAN connection of a MANI node (ROS-free).

Opens a python-can bus, decodes every received frame with the MANI codec and
hands valid messages to a callback. Frames that are not MANI messages (wrong
id, wrong length, out-of-range values, error/remote/extended frames) are
counted and reported, never raised: a node must survive anything on the bus.

A plain receive thread is used instead of can.Notifier because the Notifier
stops its thread for good when a callback or the bus raises once.
"""
from __future__ import annotations

import threading
from typing import Callable, Optional

import can

from mani_ros import protocol

MessageHandler = Callable[[protocol.Message], None]
ProblemHandler = Callable[[str], None]


class CanLink:
    """Receive thread + send for one python-can bus."""

    def __init__(self, channel: str, interface: str = "socketcan",
                 on_message: Optional[MessageHandler] = None,
                 on_problem: Optional[ProblemHandler] = None,
                 bus: Optional[can.BusABC] = None,
                 command_data_length: int = 2) -> None:
        self.channel = channel
        self.command_data_length = protocol.check_command_data_length(command_data_length)
        self.interface = interface
        if bus is None:
            try:
                bus = can.Bus(channel=channel, interface=interface)
            except (can.CanError, OSError, ValueError, ImportError) as exc:
                raise can.CanError("cannot open CAN interface %s channel %s: %s"
                                   % (interface, channel, exc)) from exc
        self.bus = bus
        self._on_message = on_message
        self._on_problem = on_problem
        self._lock = threading.Lock()
        self.received = 0      # valid MANI messages
        self.rejected = 0      # frames that are not MANI messages
        self.handler_errors = 0
        self.bus_errors = 0
        self.last_problem = ""
        self._running = True
        self._thread = threading.Thread(target=self._run, name="mani-can-rx", daemon=True)
        self._thread.start()

    def _report(self, text: str) -> None:
        self.last_problem = text
        if self._on_problem is not None:
            try:
                self._on_problem(text)
            except Exception:  # a broken logger must not stop reception
                pass

    def _run(self) -> None:
        stop = threading.Event()
        while self._running:
            try:
                frame = self.bus.recv(timeout=0.1)
            except Exception as exc:  # interface down, driver error: retry, keep running
                self.bus_errors += 1
                self._report("CAN receive on %s failed: %s" % (self.channel, exc))
                stop.wait(0.5)
                continue
            if frame is None:
                continue
            self.handle_frame(frame)

    def handle_frame(self, frame: can.Message) -> None:
        """Decode one frame and pass it on; never raises."""
        try:
            message = protocol.decode_can_message(frame)
        except (protocol.ProtocolError, ValueError, TypeError) as exc:
            self.rejected += 1
            self._report("ignored frame 0x%X: %s" % (frame.arbitration_id, exc))
            return
        self.received += 1
        if self._on_message is None:
            return
        try:
            self._on_message(message)
        except Exception as exc:
            self.handler_errors += 1
            self._report("handling %s failed: %s" % (protocol.describe(message), exc))

    def send(self, message: protocol.Message, timeout: float = 0.1) -> None:
        """Send one message; raises can.CanError when the bus refuses it."""
        frame = protocol.to_can_message(message, self.command_data_length)
        with self._lock:  # one writer at a time: python-can buses are not thread-safe
            self.bus.send(frame, timeout=timeout)

    def shutdown(self) -> None:
        self._running = False
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)
        self.bus.shutdown()
