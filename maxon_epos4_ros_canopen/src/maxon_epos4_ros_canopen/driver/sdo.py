"""canopen's SDO client, taking as an answer only a frame that can be one.

canopen hands every frame on the answer COB-ID to the transfer under way.
Two kinds cannot be its answer, yet would end it, an abort as finally as
the drive's own refusal:

* a frame that reached the host before the request went out: the backlog
  of a process the host left unscheduled (a storm of forged frames, a
  stalled bus) is read after the next request is sent;
* an abort naming another object: CiA 301's abort carries the index and
  sub-index of the transfer it ends.

Both are dropped here. Any other frame that is not the answer (another
client's on the same channel) still fails the attempt, which the driver
tries again (``ObjectAccess.sdo_transfer``, access.py).

The timeout is judged by when the answer reached the host, not by when the
notifier read it: a notifier behind on a loaded host may still hold an
answer that came in time, unread. The transfer then waits until the
notifier has read past the deadline (``bus.ReceiveClock.unread_before``).
"""
from __future__ import annotations

import queue
from typing import Any, Optional, Tuple

import canopen
from canopen.sdo import SdoClient
from canopen.sdo.exceptions import SdoCommunicationError

from ..can_device import MAX_RECEIVE_LAG
from ..clock import REAL, Clock
from .bus import ReceiveClock

_ABORT = 0x80
_INITIATE_DOWNLOAD, _INITIATE_UPLOAD = 1, 2  # client command specifiers (bits 7-5)
_BACKLOG_POLL = 0.02  # s between two looks at a notifier that is behind


def no_answer(e: BaseException) -> bool:
    """Whether canopen raised ``e`` for a missing answer: it does so from its
    response queue's timeout, and words other failures the same way."""
    return isinstance(e.__context__, queue.Empty)


class ClockedSdoClient(SdoClient):
    """canopen's SdoClient waiting for its answers on ``clock``: on a
    stepped clock the wait runs the clock's events (the drive's answer
    among them) on the waiting thread, and its timeout is virtual time."""

    def __init__(self, rx_cobid: int, tx_cobid: int, od: Any, clock: Clock = REAL) -> None:
        self.clock = clock  # before canopen's __init__ makes the response queue
        super().__init__(rx_cobid, tx_cobid, od)

    @property
    def responses(self) -> "queue.Queue[Any]":
        return self._responses

    @responses.setter
    def responses(self, _fresh: "queue.Queue[Any]") -> None:
        # canopen makes a new queue.Queue at start and whenever stale
        # answers wait in it: the clock's kind instead
        self._responses = self.clock.response_queue()


class ClockedRemoteNode(canopen.RemoteNode):
    """canopen's RemoteNode whose SDO clients wait on ``clock``."""

    def __init__(self, node_id: int, od: Any, clock: Clock = REAL) -> None:
        self.clock = clock  # before RemoteNode's __init__ adds its SDO channel
        super().__init__(node_id, od)

    def add_sdo(self, rx_cobid: int, tx_cobid: int) -> ClockedSdoClient:
        client = ClockedSdoClient(rx_cobid, tx_cobid, self.object_dictionary, self.clock)
        self.sdo_channels.append(client)
        if self.has_network():
            self.network.subscribe(client.tx_cobid, client.on_response)
        return client


class GuardedSdoClient(ClockedSdoClient):
    """An SdoClient that ignores stale frames and aborts of other objects.

    ``send_request`` runs in the thread that makes the transfer (under the
    driver's lock of that node), ``on_response`` in the bus's receive
    thread: it only reads the values the other sets before sending.
    ``receive_clock``: the notifier's, to judge a timeout by arrival."""

    def __init__(self, rx_cobid: int, tx_cobid: int, od: Any,
                 receive_clock: Optional[ReceiveClock] = None, clock: Clock = REAL) -> None:
        super().__init__(rx_cobid, tx_cobid, od, clock)
        self._receive_clock = receive_clock
        self._max_lag = MAX_RECEIVE_LAG if receive_clock is None else receive_clock.max_lag
        self._sent_at = 0.0                  # wall clock, as frame timestamps
        self._sent_monotonic = 0.0           # the same moment, as the receive clock's
        self._multiplexer: Optional[bytes] = None
        self.frames = 0                      # every frame on the answer COB-ID
        self.dropped = 0                     # those taken for no answer
        self.last_dropped = ""               # why the last of them was no answer
        # set by the transfer's owner: no backlog is waited on past it (clock time)
        self.give_up_by: Optional[float] = None

    def send_request(self, request: bytes) -> None:
        command = request[0] >> 5
        if command in (_INITIATE_DOWNLOAD, _INITIATE_UPLOAD):
            self._multiplexer = bytes(request[1:4])
        elif command not in (0, 3):  # a segment keeps its transfer's object; block transfers are not guarded
            self._multiplexer = None
        self._sent_at, self._sent_monotonic = self.clock.wall(), self.clock.now()
        super().send_request(request)

    def read_response(self) -> bytes:
        timeout = self.RESPONSE_TIMEOUT
        try:
            return super().read_response()
        except SdoCommunicationError as e:
            if self._receive_clock is None or not no_answer(e):
                raise
            missing = e
        answer_by = self._sent_monotonic + timeout
        # Past max_lag the receive clock takes a frame for read on arrival:
        # no backlog is waited on longer than that.
        give_up = self.clock.now() + self._receive_clock.max_lag
        if self.give_up_by is not None:  # a deadline (shutdown's) ends the wait for a backlog too
            give_up = min(give_up, self.give_up_by)
        self.RESPONSE_TIMEOUT = _BACKLOG_POLL
        try:
            while self._receive_clock.unread_before(answer_by) and self.clock.now() < give_up:
                try:
                    return super().read_response()
                except SdoCommunicationError as e:
                    if not no_answer(e):
                        raise
        finally:
            self.RESPONSE_TIMEOUT = timeout
        raise missing

    def tally(self) -> Tuple[int, int]:
        """Frames seen and dropped so far, for ``since``."""
        return self.frames, self.dropped

    def since(self, tally: Tuple[int, int]) -> str:
        """What came on the answer COB-ID since ``tally`` was taken: whether
        a missing answer is the drive's silence or frames this client could
        not take."""
        frames, dropped = self.frames - tally[0], self.dropped - tally[1]
        if not frames:
            return "no frame on 0x%03X since the transfer began" % self.tx_cobid
        text = "%d frame(s) on 0x%03X since the transfer began" % (frames, self.tx_cobid)
        if dropped:
            text += ", %d taken for no answer (the last: %s)" % (dropped, self.last_dropped)
        return text

    def on_response(self, can_id: int, data: Any, timestamp: float) -> None:
        self.frames += 1
        payload = bytes(data)
        lag = self.clock.wall() - timestamp
        # a timestamp far from the wall clock is another clock's (an
        # adapter's own): it says nothing of when the frame came
        if 0.0 <= lag <= self._max_lag and timestamp < self._sent_at:
            self._drop("%s stamped %.3f s before the request" % (payload.hex(), self._sent_at - timestamp))
            return
        if len(payload) == 8 and payload[0] == _ABORT and self._multiplexer is not None \
                and payload[1:4] != self._multiplexer:
            self._drop("%s, an abort of another object" % payload.hex())
            return
        super().on_response(can_id, data, timestamp)

    def _drop(self, why: str) -> None:
        self.dropped += 1
        self.last_dropped = why
