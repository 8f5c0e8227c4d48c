"""The heartbeat consumer of the virtual EPOS4 (CiA 301, 0x1016): which
nodes it watches, when each entry is armed, and which ones timed out."""
from __future__ import annotations

import logging
from typing import Dict, List, Tuple

from .objects import ABORT_PARAMETER_INCOMPATIBLE, ObjectStore, SdoAbort

log = logging.getLogger(__name__)


def consumer_entry(value: int) -> Tuple[int, float]:
    """0x1016 sub-index value -> (watched node id, timeout in s); (0, 0) = unused."""
    node_id, ms = (value >> 16) & 0xFF, value & 0xFFFF
    if not 1 <= node_id <= 127 or ms == 0:
        return 0, 0.0
    return node_id, ms / 1000.0


def _entries(store: ObjectStore):
    for sub in range(1, 128):
        if (0x1016, sub) not in store:
            break
        yield sub, consumer_entry(store.get(0x1016, sub, 0))


def report_lost(own_node_id: int, watched: int, silent: float, timeout: float, behind: float) -> None:
    """Log a consumer timeout with what tells a lost master from a host
    that held the simulator: the silence and the consumer time (bus time),
    and how far the supervision clock is behind the clock (s)."""
    log.warning("node %d: heartbeat of node %d lost: none for %.0f ms of bus time (consumer time %.0f ms); "
                "supervision %.0f ms behind the clock", own_node_id, watched, silent * 1000, timeout * 1000,
                behind * 1000)


class HeartbeatConsumer:
    """The entries of 0x1016 and the last heartbeat of each armed one."""

    def __init__(self) -> None:
        self.timeouts: Dict[int, float] = {}  # watched node id -> timeout (s)
        self.seen: Dict[int, float] = {}  # armed entries: node id -> last heartbeat (bus time)

    def load(self, store: ObjectStore, own_node_id: int) -> None:
        """(Re)read 0x1016: every entry starts unarmed (CiA 301: supervision
        begins with the first heartbeat received from the watched node)."""
        self.timeouts = {node_id: timeout for _, (node_id, timeout) in _entries(store)
                         if node_id and node_id != own_node_id}
        self.seen = {}

    @staticmethod
    def check_entry(store: ObjectStore, sub: int, value: int) -> None:
        """Refuse a write of ``value`` to 0x1016 ``sub`` that watches a node twice."""
        node_id, _ = consumer_entry(value)
        if not node_id:
            return
        for other, (watched, _) in _entries(store):
            if other != sub and watched == node_id:
                # CiA 301: one node may be watched by one entry only
                raise SdoAbort(ABORT_PARAMETER_INCOMPATIBLE, "node %d already watched" % node_id)

    def watches(self, node_id: int) -> bool:
        return node_id in self.timeouts

    def heard(self, node_id: int, bus_time: float) -> None:
        """A heartbeat (or boot-up) of a watched node arms/feeds its entry."""
        self.seen[node_id] = bus_time

    def expired(self, bus_time: float) -> List[Tuple[int, float]]:
        """(node-ID, seconds silent) of the armed nodes silent past their
        timeout; each is unarmed until its next heartbeat."""
        lost = [(node_id, bus_time - last) for node_id, last in self.seen.items()
                if bus_time - last > self.timeouts[node_id]]
        for node_id, _ in lost:
            del self.seen[node_id]
        return lost
