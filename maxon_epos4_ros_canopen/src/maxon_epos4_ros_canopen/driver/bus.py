"""The CAN side the canopen library leaves to the master: opening the
python-can bus from ``bus/device`` and ``bus/bitrate`` (can_device.py), the SYNC producer with ros_canopen's
overflow counter (canopen's SyncProducer sends no counter), and the
master's heartbeat producer (``heartbeat/rate``, ``heartbeat/msg``)."""
from __future__ import annotations

from typing import Optional

import can

from ..can_device import open_device
from ..config import BusConfig, HeartbeatConfig

SYNC_COB_ID = 0x080
def open_bus(cfg: BusConfig) -> can.BusABC:
    """The bus of ``bus/device`` and ``bus/bitrate``."""
    return open_device(cfg.device, cfg.bitrate, cfg.loopback)


class SyncProducer:
    """SYNC frames, with the CiA 301 counter 1..overflow when overflow > 0.

    ``send()`` is called by the driver's cycle when SYNC and cycle share a
    period; ``start(period)`` runs them on python-can's periodic sender
    otherwise.
    """

    def __init__(self, bus: can.BusABC, overflow: int) -> None:
        self.bus = bus
        self.overflow = overflow
        self.counter = 0
        self.sent = 0
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

    def start(self, period_s: float) -> None:
        self.stop()
        self._advance(self._msg)
        self._task = self.bus.send_periodic(self._msg, period_s, modifier_callback=self._advance)

    def stop(self) -> None:
        if self._task is not None:
            self._task.stop()
            self._task = None


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
