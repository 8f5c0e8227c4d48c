"""Faults a test injects into a virtual EPOS4 (the ``inject_fault`` service
of the simulator node, Simulator.inject_fault)."""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

from .. import epos4_errors

if TYPE_CHECKING:  # pragma: no cover
    from .drive import VirtualEpos4


def inject(node: "VirtualEpos4", fault: str, now: float, error_code: int = 0, duration: float = 0.0) -> str:
    """Apply ``fault`` to ``node``; returns a description.  Raises ValueError."""
    if fault == "emcy":
        if not 0 < error_code <= 0xFFFF:
            raise ValueError("emcy needs an error_code between 0x0001 and 0xFFFF")
        node.raise_fault(error_code, now)
        return "raised %s" % epos4_errors.describe(error_code)
    if fault == "silent":
        if duration < 0:
            raise ValueError("silent needs duration >= 0 (0 = until clear)")
        node.silent_until = now + duration if duration > 0 else math.inf
        return "silent for %s" % ("ever (until clear)" if duration <= 0 else "%.3f s" % duration)
    if fault == "heartbeat_stop":
        node.heartbeat_stopped = True
        return "heartbeat stopped"
    if fault == "reboot":
        node.silent_until = None
        node.power_on(now)
        return "rebooted"
    if fault == "sdo_delay":
        if duration < 0:
            raise ValueError("sdo_delay needs duration >= 0")
        node.sdo_delay = duration
        return "SDO answers delayed by %.3f s" % duration
    if fault == "corrupt_frame":
        node.corrupt_next = True
        return "next frame corrupted"
    if fault == "clear":
        node.silent_until = None
        node.heartbeat_stopped = False
        node.sdo_delay = 0.0
        node.corrupt_next = False
        return "injected faults cleared"
    raise ValueError("unknown fault %r (emcy, silent, heartbeat_stop, reboot, sdo_delay, "
                     "corrupt_frame, clear)" % fault)
