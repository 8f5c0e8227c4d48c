"""The driver's PDO codec and TPDO receiver.

canopen's PDO maps are not used at run time, for two reasons: a map
subscribes to its own COB-ID, so a foreign frame on an RxPDO's COB-ID
becomes the value the master sends next; and its receive path takes a lock
and wakes every waiter for each frame. Here an RxPDO is encoded from the
values the axis commands, nothing else, and a TxPDO is decoded only when
its length matches its mapping.

The receiver holds the latest frame of each TPDO: a slot per COB-ID with
an immutable (bytes, read, arrived) tuple. Where the cycle reads its TPDOs
itself (cycle_reception.py) the cycle thread alone writes and reads it.
Elsewhere the CAN notifier thread fills it and the cycle reads it: the swap
of one reference to an immutable tuple is atomic, so that is a latest-value
message, not shared mutable state.
"""
from __future__ import annotations

import math
import struct
import time
from typing import Any, Callable, Dict, Iterable, List, Mapping, Optional, Sequence, Tuple

from canopen.objectdictionary import ObjectDictionary

from ..objects import ObjectKey, find_variable
from .plan import MapPlan

Frame = Tuple[bytes, float, float]  # payload, when it was read and when it arrived (time.monotonic())
# SYNC times a receiver keeps: enough for a notifier that lags a few periods
_SYNC_HISTORY = 16


class PdoLayoutError(ValueError):
    """A mapping the codec cannot encode (an entry not of whole bytes)."""


def _layout(od: ObjectDictionary, entries: Sequence[Tuple[ObjectKey, int]]) -> Tuple[struct.Struct, Tuple[ObjectKey, ...]]:
    fmt = "<"
    keys = []
    for key, bits in entries:
        var = find_variable(od, key)
        st = var.STRUCT_TYPES.get(var.data_type)
        if st is None or st.size * 8 != bits:
            raise PdoLayoutError("object %s (%d bits mapped) cannot be packed in a PDO by the driver" % (key, bits))
        fmt += st.format.lstrip("<>=!@")
        keys.append(key)
    return struct.Struct(fmt), tuple(keys)


class RxPdo:
    """One PDO the driver sends: its COB-ID and the objects it carries."""

    __slots__ = ("number", "cob_id", "keys", "_st", "pack_args")

    def __init__(self, od: ObjectDictionary, plan: MapPlan) -> None:
        self.number = plan.number
        self.cob_id = plan.cob_id
        self._st, self.keys = _layout(od, plan.entries)
        # the prepared struct's own pack, for the cycle: one C call per frame
        self.pack_args = self._st.pack

    def pack(self, values: Sequence[int]) -> bytes:
        """The frame for values given in the order of ``keys``."""
        return self._st.pack(*values)


class TxPdo:
    """One PDO the drive sends; decode() refuses a frame of the wrong length."""

    __slots__ = ("number", "cob_id", "keys", "length", "_st", "unpack")

    def __init__(self, od: ObjectDictionary, plan: MapPlan) -> None:
        self.number = plan.number
        self.cob_id = plan.cob_id
        self._st, self.keys = _layout(od, plan.entries)
        self.length = self._st.size
        # the prepared struct's own unpack (callers check ``length`` first)
        self.unpack = self._st.unpack

    def decode(self, data: bytes) -> Optional[Tuple[Any, ...]]:
        if len(data) != self.length:
            return None
        return self._st.unpack(data)


def _read_on_arrival() -> Tuple[float, float]:
    now = time.monotonic()
    return now, now


class TpdoReceiver:
    """Latest frame of each TPDO COB-ID, filled by one thread: the cycle's
    reception (``put``, ``sync_heard``) or the CAN notifier (``on_frame``,
    ``on_sync``, canopen subscriber callbacks).

    A frame whose length is not its mapping's is counted in ``rejected``
    (written by the filling thread alone) and never stored: stored, a short
    forged frame would take the place of the drive's last good one and, if
    the drive's next frame came before the cycle read it, go unnoticed.

    A SYNC-driven TPDO (transmission type 0..240) comes at most once
    between two consecutive SYNCs; a second frame on its COB-ID in one SYNC
    period is a conflict (another node on that COB-ID, or a forger) and is
    counted in ``conflicts`` (filling thread alone). Which period a frame
    belongs to is told by arrival times, not by the order the filling thread
    happens to handle things in: a SYNC's time comes from ``sync_sent`` (the
    cycle, for the SYNCs it sends itself, which the bus does not echo back
    to their sender) or ``sync_heard`` / ``on_sync`` (a SYNC heard on the bus: the kernel's
    broadcast manager or another producer). Until a SYNC is known, and for
    TPDOs sent on an event timer or an event (254, 255), nothing is counted.
    """

    def __init__(self, lengths: Mapping[int, int],
                 clock: Callable[[], Tuple[float, float]] = _read_on_arrival,
                 sync_driven: Iterable[int] = ()) -> None:
        self.cob_ids = tuple(lengths)
        self.lengths = dict(lengths)
        self.slots: Dict[int, Optional[Frame]] = {c: None for c in self.cob_ids}
        self.rejected: Dict[int, int] = {c: 0 for c in self.cob_ids}
        self.conflicts: Dict[int, int] = {c: 0 for c in self.cob_ids}
        # rejected plus conflicts, all COB-IDs (filling thread alone): a
        # reader that saw this number unchanged has no count to look up
        self.anomalies = 0
        self._clock = clock  # (when the frame being handled was read, when it arrived)
        # per SYNC-driven COB-ID, when its last well-formed frame arrived (filling thread)
        self._arrived: Dict[int, float] = {c: -math.inf for c in sync_driven if c in self.lengths}
        # Times of recent SYNCs, newest first, each tuple replaced whole by
        # its one writer: the cycle (sent) and the filling thread (heard).
        self._sent: Tuple[float, ...] = ()
        self._heard: Tuple[float, ...] = ()

    def sync_sent(self, t: float) -> None:
        """The cycle is about to send a SYNC (monotonic ``t``, taken before
        the send: every frame answering it arrives later)."""
        self._sent = (t,) + self._sent[:_SYNC_HISTORY - 1]

    def on_sync(self, _can_id: int, _data: Any, _timestamp: float) -> None:
        """canopen.Network subscriber callback for SYNC frames heard on the bus."""
        self.sync_heard(self._clock()[1])

    def sync_heard(self, arrived: float) -> None:
        """A SYNC heard on the bus arrived at monotonic ``arrived``."""
        self._heard = (arrived,) + self._heard[:_SYNC_HISTORY - 1]

    def last_sync_heard(self) -> float:
        """When the latest SYNC heard on the bus arrived (-inf: none yet)."""
        heard = self._heard
        return heard[0] if heard else -math.inf

    def _period_start(self, t: float) -> float:
        """Time of the latest known SYNC at or before ``t`` (-inf: none known)."""
        start = -math.inf
        for times in (self._sent, self._heard):
            for s in times:  # newest first
                if s <= t:
                    if s > start:
                        start = s
                    break
        return start

    def on_frame(self, can_id: int, data: Any, _timestamp: float) -> None:
        """canopen.Network subscriber callback: never raises."""
        read_at, arrived = self._clock()
        self.put(can_id, data, read_at, arrived)

    def put(self, can_id: int, data: Any, read_at: float, arrived: float) -> None:
        """A frame on one of ``cob_ids``, read at ``read_at`` after it
        arrived at ``arrived`` (monotonic). Never raises for a frame of any
        length."""
        if len(data) != self.lengths[can_id]:
            self.rejected[can_id] += 1
            self.anomalies += 1  # after the count: a reader that sees this sees the count
            return
        self.slots[can_id] = (bytes(data), read_at, arrived)
        last = self._arrived.get(can_id)
        if last is not None:
            if last >= self._period_start(arrived) > -math.inf:
                self.conflicts[can_id] += 1
                self.anomalies += 1
            self._arrived[can_id] = arrived

    def latest(self, cob_id: int) -> Optional[Frame]:
        return self.slots.get(cob_id)


def sync_driven(plans: Sequence[MapPlan]) -> List[int]:
    """COB-IDs of the enabled TPDOs sent on SYNC (transmission types 0..240)."""
    return [p.cob_id for p in enabled_maps(plans) if 0 <= p.trans_type <= 240]


def enabled_maps(plans: Sequence[MapPlan]) -> List[MapPlan]:
    return [p for p in plans if p.enabled and p.entries]
