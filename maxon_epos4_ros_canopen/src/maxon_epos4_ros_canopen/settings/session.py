"""The bus side of epos4_settings: the listen window that keeps the tool off
a bus another master drives, and the session with one drive (canopen's SDO
client, the checks every command makes).

Time is the injected ``Clock``'s (clock.py), real time by default: the
listen window, the notifier that hands frames to canopen and the wait for
each SDO answer all go through it."""
from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Dict, List, Sequence, TextIO

import can
import canopen
from canopen.objectdictionary import ODVariable
from canopen.objectdictionary import datatypes as dt
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from ..clock import REAL, Clock
from ..driver.sdo import ClockedRemoteNode
from .dcf import (IDENTITY_PRODUCT, IDENTITY_REVISION, IDENTITY_VENDOR, PROG, Key, SettingsError, SettingsFile,
                  abort_text, decode, find)

SYNC_COB_ID = 0x080
HEARTBEAT_BASE = 0x700
MASTER_NODE_ID = 0x7F  # the master's heartbeat in ros_canopen's and this driver's configs: 77f#05
DRAIN_LIMIT = 10000  # frames read after the listen window at most (a second of a full 1 Mbit/s bus)
NOTIFIER_POLL_S = 0.05  # s the notifier waits on the bus at a time (how soon it sees a stop)


@dataclass
class Heard:
    """What a listen window heard: SYNC frames and heartbeats per node-ID."""

    seconds: float
    syncs: int
    heartbeats: Dict[int, int]  # node-ID -> count

    def masters(self, watched: Sequence[int] = ()) -> List[str]:
        """Descriptions of what another master sent; empty when nothing."""
        found = []
        if self.syncs:
            found.append("SYNC (COB-ID 0x080) %d times in %.1f s" % (self.syncs, self.seconds))
        for node_id in sorted(self.heartbeats):
            if node_id == MASTER_NODE_ID:
                found.append("the heartbeat of node %d (COB-ID 0x%03X), the master's in the ROS driver's "
                             "configuration (heartbeat msg 77f#05)" % (node_id, HEARTBEAT_BASE + node_id))
            elif node_id in watched:
                found.append("the heartbeat of node %d (COB-ID 0x%03X), which the drive's heartbeat consumer "
                             "0x1016 watches as its master" % (node_id, HEARTBEAT_BASE + node_id))
        return found


class _Counter(can.Listener):
    """Counts SYNCs and heartbeats per node-ID."""

    def __init__(self) -> None:
        self.syncs = 0
        self.heartbeats: Dict[int, int] = {}
        self._lock = threading.Lock()  # a notifier's thread counts, and the listener after it

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_extended_id or msg.is_remote_frame:
            return
        with self._lock:
            if msg.arbitration_id == SYNC_COB_ID and msg.dlc <= 1:
                self.syncs += 1
            elif HEARTBEAT_BASE < msg.arbitration_id <= HEARTBEAT_BASE + 0x7F and msg.dlc == 1:
                node_id = msg.arbitration_id - HEARTBEAT_BASE
                self.heartbeats[node_id] = self.heartbeats.get(node_id, 0) + 1


def listen(bus: can.BusABC, seconds: float, clock: Clock = REAL) -> Heard:
    """Receive for ``seconds`` of ``clock`` before anything is sent (the
    clock's notifier hands the frames over), then take what is already
    queued, and count SYNCs and heartbeats."""
    counter = _Counter()
    notifier = clock.notifier(bus, [counter], NOTIFIER_POLL_S)
    try:
        clock.sleep(seconds)
    finally:
        notifier.stop(NOTIFIER_POLL_S + 1.0)
    for _ in range(DRAIN_LIMIT):  # what came in the window and waits unread; a busy bus never runs dry
        msg = bus.recv(timeout=0.0)
        if msg is None:
            break
        counter.on_message_received(msg)
    return Heard(seconds, counter.syncs, dict(counter.heartbeats))


STOP_MASTER = ("Stop that master first, then run again: the ROS driver with Ctrl-C on its roslaunch "
               "(or `rosnode kill` of its canopen_motor node), EPOS Studio by closing its connection, "
               "a PLC by stopping its CANopen master. Two masters would configure the drive at once.")


class Session:
    """One drive on one bus: the listen window, canopen's SDO client, counts."""

    def __init__(self, bus: can.BusABC, device: str, node_id: int, file: SettingsFile,
                 sdo_timeout: float, listen_s: float, err: TextIO, clock: Clock = REAL) -> None:
        self.bus = bus
        self.device = device
        self.node_id = node_id
        self.file = file
        self.err = err
        self.transfers = 0
        self.clock = clock
        self.heard = listen(bus, listen_s, clock) if listen_s > 0 else Heard(0.0, 0, {})
        masters = self.heard.masters()
        if masters:
            raise SettingsError("another CANopen master is active on %s: heard %s. %s"
                                % (device, " and ".join(masters), STOP_MASTER))
        self.network = canopen.Network(bus)
        self.network.notifier = clock.notifier(bus, self.network.listeners, self.network.NOTIFIER_CYCLE)
        self.node = ClockedRemoteNode(node_id, file.od, clock)
        self.node.sdo.RESPONSE_TIMEOUT = sdo_timeout
        self.network.add_node(self.node)

    def close(self) -> None:
        if self.network.notifier is not None:
            self.network.notifier.stop(1.0)
        self.network.nodes.clear()

    # transfers
    def upload(self, var: ODVariable) -> bytes:
        """The object's bytes; SdoAbortedError when refused, SettingsError
        when the node does not answer."""
        self.transfers += 1
        try:
            return self.node.sdo.upload(var.index, var.subindex)
        except SdoCommunicationError as exc:
            raise self._silent(var, exc) from None

    def download(self, var: ODVariable, data: bytes) -> None:
        self.transfers += 1
        try:
            self.node.sdo.download(var.index, var.subindex, data)
        except SdoCommunicationError as exc:
            raise self._silent(var, exc) from None

    def read(self, var: ODVariable) -> object:
        return decode(var, self.upload(var))

    def _silent(self, var: ODVariable, exc: Exception) -> SettingsError:
        if self.transfers == 1:
            heard = sorted(self.heard.heartbeats)
            return SettingsError(
                "node %d does not answer on %s (no SDO answer to a read of 0x%04X sub %d within %.1f s: %s). "
                "Is the drive powered, its node-ID %d and the bus's bit rate right? A drive in NMT "
                "stopped does not answer SDO either. %s"
                % (self.node_id, self.device, var.index, var.subindex, self.node.sdo.RESPONSE_TIMEOUT, exc,
                   self.node_id, "Heartbeats heard in the listen window: nodes %s." % heard if heard
                   else "No heartbeat was heard in the listen window."))
        return SettingsError("node %d stopped answering at 0x%04X sub %d (%s) after %d transfers; a restore "
                             "cut short leaves part of the file's settings in the drive, unstored: run it "
                             "again once the drive answers"
                             % (self.node_id, var.index, var.subindex, exc, self.transfers - 1))

    # checks every command makes
    def check_identity(self, refuse: bool) -> Dict[Key, int]:
        """Read the drive's identity; refuse (SettingsError) a file for
        another vendor or product when ``refuse``. Returns the identity read."""
        identity: Dict[Key, int] = {}
        for key in (IDENTITY_VENDOR, IDENTITY_PRODUCT, IDENTITY_REVISION):
            var = find(self.file.od, key)
            if var is None:
                var = ODVariable("identity", key[0], key[1])
                var.data_type = dt.UNSIGNED32
                var.access_type = "ro"
            try:
                identity[key] = int(self.read(var))  # type: ignore[call-overload]
            except SdoAbortedError as exc:
                self.err.write("%s: the drive refused to read 0x%04X sub %d: %s\n"
                               % (PROG, key[0], key[1], abort_text(exc)))
        for key, what, expected in ((IDENTITY_VENDOR, "vendor-ID", self.file.vendor_id()),
                                    (IDENTITY_PRODUCT, "product code", self.file.product_code())):
            actual = identity.get(key)
            if expected is None or actual is None:
                self.err.write("%s: %s not checked (%s has none)\n"
                               % (PROG, what, "the file" if expected is None else "the drive"))
            elif actual != expected and refuse:
                raise SettingsError(
                    "%s is for %s 0x%08X (0x1018 sub %d), node %d on %s is 0x%08X: the file describes "
                    "another product, its objects and values do not fit this drive. Use a file made for "
                    "this drive (a backup of it, or its own DCF from EPOS Studio)."
                    % (self.file.path, what, expected, key[1], self.node_id, self.device, actual))
        return identity

    def check_consumers(self) -> None:
        """A heartbeat the drive's consumer (0x1016) watches, heard in the
        listen window, is its master's: refuse."""
        watched = []
        for sub in range(1, 128):
            var = find(self.file.od, (0x1016, sub))
            if var is None:
                break
            try:
                value = int(self.read(var))  # type: ignore[call-overload]
            except SdoAbortedError:
                continue
            node_id = (value >> 16) & 0xFF
            if node_id and value & 0xFFFF and node_id != self.node_id:
                watched.append(node_id)
        masters = self.heard.masters(watched)
        if masters:
            raise SettingsError("another CANopen master is active on %s: heard %s. %s"
                                % (self.device, " and ".join(masters), STOP_MASTER))


