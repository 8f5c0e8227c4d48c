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
tries again (``Driver._sdo_transfer``).
"""
from __future__ import annotations

import time
from typing import Any, Optional, Tuple

from canopen.sdo import SdoClient

from ..can_device import MAX_RECEIVE_LAG

_ABORT = 0x80
_INITIATE_DOWNLOAD, _INITIATE_UPLOAD = 1, 2  # client command specifiers (bits 7-5)


class GuardedSdoClient(SdoClient):
    """An SdoClient that ignores stale frames and aborts of other objects.

    ``send_request`` runs in the thread that makes the transfer (under the
    driver's lock of that node), ``on_response`` in the bus's receive
    thread: it only reads the two values the other sets before sending."""

    def __init__(self, rx_cobid: int, tx_cobid: int, od: Any) -> None:
        super().__init__(rx_cobid, tx_cobid, od)
        self._sent_at = 0.0                  # wall clock, as frame timestamps
        self._multiplexer: Optional[bytes] = None
        self.frames = 0                      # every frame on the answer COB-ID
        self.dropped = 0                     # those taken for no answer
        self.last_dropped = ""               # why the last of them was no answer

    def send_request(self, request: bytes) -> None:
        command = request[0] >> 5
        if command in (_INITIATE_DOWNLOAD, _INITIATE_UPLOAD):
            self._multiplexer = bytes(request[1:4])
        elif command not in (0, 3):  # a segment keeps its transfer's object; block transfers are not guarded
            self._multiplexer = None
        self._sent_at = time.time()
        super().send_request(request)

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
        lag = time.time() - timestamp
        # a timestamp far from the wall clock is another clock's (an
        # adapter's own): it says nothing of when the frame came
        if 0.0 <= lag <= MAX_RECEIVE_LAG and timestamp < self._sent_at:
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
