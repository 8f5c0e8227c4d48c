"""What one drive sends, as its axis takes it in: the TPDO frames of each
cycle, heartbeats and EMCYs, and the watchdogs on them.

Owned by its Axis, so by the cycle thread. It records and counts; it
decides nothing about the drive's CiA 402 state: Axis.read interprets the
values taken in, and Axis.watch reacts to what ``silence`` answers.
"""
from __future__ import annotations

import logging
import math
from typing import Any, Dict, List, Optional, Tuple

from ..epos4_errors import describe as describe_error
from ..objects import ObjectKey
from .pdo import TpdoReceiver, TxPdo
from .snapshot import Counters

log = logging.getLogger("maxon_epos4_ros_canopen.driver")

NMT_NAMES = {0: "INITIALISING", 4: "STOPPED", 5: "OPERATIONAL", 0x7F: "PRE-OPERATIONAL"}
EMCY_LOG_LINES = 5  # EMCY log lines per second and axis at most


class Inputs:
    """One drive's TPDO values, node status and watchdog times."""

    def __init__(self, name: str, node_id: int, counters: Counters) -> None:
        self.name = name
        self.node_id = node_id
        self.counters = counters
        self.nmt_state = "UNKNOWN"
        self.last_emcy = ""
        self.error_register = 0
        self.heartbeat_ms = 0
        self.last_heartbeat = 0.0
        # the longest silence between two heartbeats read since the watchdog
        # (re)started, by their arrival: a drive silent past its heartbeat
        # time is lost even when the driver read its next heartbeat before
        # any later frame (a notifier behind on a loaded host)
        self.heartbeat_gap = 0.0
        self.rebooted = False           # a boot-up came while the axis was ready
        self.status_seen = 0.0          # monotonic time of the last statusword TPDO
        self.status_seen_cycle = 0      # the cycle that took it in
        self.status_arrived = 0.0       # monotonic time the last statusword TPDO taken arrived
        self.stamp = 0.0                # wall-clock time the newest TPDO taken arrived (AxisSnapshot.stamp)
        self.read_at = math.nan         # when the cycle last took TPDOs in
        # per TxPDO: its objects, the latest values (None: none yet) and when they arrived (NaN: none yet)
        self.keys: Tuple[Tuple[ObjectKey, ...], ...] = ()
        self.vals: List[Optional[Tuple[Any, ...]]] = []
        self.arrived: List[float] = []
        self.at: Dict[ObjectKey, Tuple[int, int]] = {}  # object -> (PDO, field) of its first copy
        self._codec: Tuple[Tuple[int, int, Any], ...] = ()
        self._seen: List[Any] = []                   # the receiver's frame last looked at
        self._rejected_seen: List[Optional[int]] = []  # receiver.rejected at the last read
        self._conflicts_seen: List[Optional[int]] = []  # receiver.conflicts at the last read
        # receiver.anomalies when the counts above were last looked up, and
        # whose it was (None: look them up at the next read)
        self._anomalies_seen: Optional[int] = None
        self._anomalies_of: Optional[TpdoReceiver] = None
        self._status_pdo = -1
        self._fresh_after = 0.0  # monotonic; frames that arrived before are stale
        self._emcy_logged = -1e9
        self._emcy_window = -1e9   # start of the current second of EMCY log lines
        self._emcy_lines = 0

    def bind(self, tx: Tuple[TxPdo, ...], status_key: ObjectKey, configured_at: float,
             heartbeat_ms: int, now: float, cycle: int) -> None:
        """A configured node's TxPDOs (``status_key``: the statusword's
        object); its readings are unknown again until they arrive, and its
        watchdogs start at ``now``."""
        self._seen = [None] * len(tx)
        self._rejected_seen = [None] * len(tx)
        self._conflicts_seen = [None] * len(tx)
        self._anomalies_seen = self._anomalies_of = None
        self.vals = [None] * len(tx)
        self.arrived = [math.nan] * len(tx)
        self.keys = tuple(t.keys for t in tx)
        self._codec = tuple((t.cob_id, t.length, t.unpack) for t in tx)
        self._fresh_after = configured_at
        self.at = {}
        for i, t in enumerate(tx):
            for j, key in enumerate(t.keys):
                self.at.setdefault(key, (i, j))
        self._status_pdo = self.at[status_key][0]
        self.heartbeat_ms = heartbeat_ms
        self.restart(now)
        self.status_seen_cycle = cycle
        self.nmt_state = "OPERATIONAL"
        self.rebooted = False

    def restart(self, now: float) -> None:
        """The heartbeat and TxPDO watchdogs start again at ``now``."""
        self.last_heartbeat = self.status_seen = now
        self.heartbeat_gap = 0.0

    def set_heartbeat(self, ms: int, now: float) -> None:
        """The node's heartbeat time (0x1017) is ``ms`` now; the consumer
        counts from ``now``."""
        self.heartbeat_ms = ms
        self.last_heartbeat = now
        self.heartbeat_gap = 0.0

    def take(self, receiver: TpdoReceiver, now: float, cycle: int,
             wall_offset: float) -> List[Optional[Tuple[Any, ...]]]:
        """The TPDO frames that came since the last cycle into ``vals``, which
        it returns; ``wall_offset``: time.time() minus time.monotonic(), for
        the stamp."""
        vals = self.vals
        arrived = self.arrived
        self.read_at = now
        seen = self._seen
        slots = receiver.slots
        # Read before the counts (the notifier raises it after them): while
        # it stays what it was, no count of any COB-ID changed.
        anomalies = receiver.anomalies
        if anomalies != self._anomalies_seen or receiver is not self._anomalies_of:
            self._anomalies_seen, self._anomalies_of = anomalies, receiver
            self._take_counts(receiver)
        newest = 0.0
        fresh_after = self._fresh_after
        status_pdo = self._status_pdo
        i = -1
        for cob_id, length, unpack in self._codec:
            i += 1
            frame = slots.get(cob_id)
            if frame is None or frame is seen[i]:
                continue
            seen[i] = frame
            if frame[2] < fresh_after:  # arrived before the node was (re)configured
                continue
            data = frame[0]
            if len(data) != length:  # TxPdo.decode's check, inlined
                self.counters.add("bad_tpdo")
                continue
            vals[i] = unpack(data)
            if frame[2] > newest:
                newest = frame[2]
            arrived[i] = frame[2]
            if i == status_pdo:
                self.status_seen = frame[1]
                self.status_seen_cycle = cycle
                self.status_arrived = frame[2]
        if newest:
            self.stamp = newest + wall_offset
        return vals

    def _take_counts(self, receiver: TpdoReceiver) -> None:
        """The receiver's counts of this node's TPDO COB-IDs since the last
        look, into the counters (counted from the first read after bind on)."""
        rejected, rejected_seen = receiver.rejected, self._rejected_seen
        conflicts, conflicts_seen = receiver.conflicts, self._conflicts_seen
        i = -1
        for cob_id, _, _ in self._codec:
            i += 1
            n = rejected.get(cob_id, 0)
            if n != rejected_seen[i]:
                # frames of a wrong length, dropped by the receiver
                if rejected_seen[i] is not None:
                    self.counters.add("bad_tpdo", n - rejected_seen[i])
                rejected_seen[i] = n
            n = conflicts.get(cob_id, 0)
            if n != conflicts_seen[i]:
                # a second frame in one SYNC period (another node, a forger)
                if conflicts_seen[i] is not None:
                    self.counters.add("tpdo_conflicts", n - conflicts_seen[i])
                conflicts_seen[i] = n

    # --------------------------------------------------------- watchdogs
    def silence(self, now: float, cycle: int, period: float, pdo_timeout: float, pdo_cycles: int,
                reception: Optional[Tuple[float, float]]) -> Optional[str]:
        """Why the driver lost sight of the drive (None: it has not): no
        heartbeat, a node out of OPERATIONAL, no statusword TxPDO.
        ``reception``: the receive clock's progress (bus.ReceiveClock), when
        the latest frame read was read and when it arrived."""
        if self.heartbeat_ms > 0 and self._heartbeat_missing(now, period, reception):
            self.nmt_state = "LOST"
            return "heartbeat lost: nothing for %.0f ms (0x1017 = %d ms)" % (
                max(now - self.last_heartbeat, self.heartbeat_gap) * 1000, self.heartbeat_ms)
        if self.nmt_state in ("STOPPED", "PRE-OPERATIONAL"):
            return "node left OPERATIONAL (heartbeat says %s)" % self.nmt_state
        if cycle - self.status_seen_cycle >= pdo_cycles and now - self.status_seen > pdo_timeout:
            # Counted in cycles too, so that a stall of this process (no
            # SYNC sent) is not taken for a silent drive.
            self.nmt_state = "LOST"
            return "no statusword TxPDO in %d cycles (%.0f ms)" % (
                cycle - self.status_seen_cycle, (now - self.status_seen) * 1000)
        return None

    def _heartbeat_missing(self, now: float, period: float, reception: Optional[Tuple[float, float]]) -> bool:
        """Nothing from the drive for 1.5 x 0x1017 + 2 cycles: between two
        heartbeats read (by when they arrived), or since the last one. Missing only
        once the driver has read a frame that arrived after the heartbeat
        was due (frames are read in the order they came), or has read
        nothing at all for as long: a heartbeat still waiting unread behind
        a stalled notifier is not a silent drive."""
        limit = 1.5 * self.heartbeat_ms / 1000.0 + 2 * period
        if self.heartbeat_gap > limit:
            return True
        if now - self.last_heartbeat <= limit:
            return False
        return reception is None or reception[1] - self.last_heartbeat > limit or now - reception[0] > limit

    def on_heartbeat(self, data: bytes, now: float, ready: bool) -> None:
        """A heartbeat; a boot-up of a node that is ``ready`` marks it rebooted."""
        if now < self._fresh_after:
            return  # from before the node was (re)configured: the boot-up of its reset
        if len(data) != 1:
            self.counters.add("bad_heartbeat")
            return
        byte = data[0]
        # A boot-up is 0x00 alone. Otherwise bit 7 is the toggle bit of a
        # node guarding answer (another master may guard the node), which
        # never reports "initialising": 0x80 is no state.
        state = byte & 0x7F
        name = NMT_NAMES.get(state) if byte != 0x80 else None
        if name is None:
            self.counters.add("undefined_nmt_state")
            return
        if self.heartbeat_ms > 0:
            self.heartbeat_gap = max(self.heartbeat_gap, now - self.last_heartbeat)
        self.last_heartbeat = now
        self.nmt_state = name
        if byte == 0 and ready:
            self.rebooted = True

    def on_emcy(self, data: bytes, now: float = 0.0) -> None:
        if len(data) < 3:
            self.counters.add("bad_emcy")
            return
        code = data[0] | data[1] << 8
        self.error_register = data[2]
        if code == 0:
            if self._may_log_emcy(now):
                log.info("%s (node %d): EMCY error reset", self.name, self.node_id)
            return
        text = "%s (error register 0x%02X)" % (describe_error(code), data[2])
        if (text != self.last_emcy or now - self._emcy_logged > 1.0) and self._may_log_emcy(now):
            self._emcy_logged = now
            log.error("%s (node %d): EMCY %s", self.name, self.node_id, text)
        self.last_emcy = text

    def emcy_suffix(self) -> str:
        """": <the last EMCY>" for an error message; "" when none came."""
        return (": " + self.last_emcy) if self.last_emcy else ""

    def _may_log_emcy(self, now: float) -> bool:
        """A storm of EMCYs (a drive in trouble, or forged frames with every
        code) must not become a storm of log lines: they are written by the
        cycle thread, and a log line costs far more than a cycle. At most
        EMCY_LOG_LINES a second per axis; the others are counted."""
        if now - self._emcy_window >= 1.0:
            self._emcy_window = now
            self._emcy_lines = 0
        if self._emcy_lines >= EMCY_LOG_LINES:
            self.counters.add("emcy_not_logged")
            return False
        self._emcy_lines += 1
        return True
