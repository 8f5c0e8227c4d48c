"""Errors of the virtual EPOS4 as a master sees them: the EMCY frame,
the error register 0x1001, the error history 0x1003 and 0x603F."""
from __future__ import annotations

import struct
from typing import Callable

from .. import epos4_errors
from .objects import ObjectStore
from .pdo import COB_INVALID

_EMCY = struct.Struct("<HB5s")


class ErrorReport:
    """``code`` is the error in force (0: none); ``send(cob_id, data)``
    puts an EMCY on the bus; ``may_send()`` says whether NMT allows it."""

    def __init__(self, store: ObjectStore, node_id: int, send: Callable[[int, bytes], None],
                 may_send: Callable[[], bool]):
        self.store, self.node_id, self.send, self.may_send = store, node_id, send, may_send
        self.code = 0

    def record(self, code: int) -> None:
        """An error occurs: EMCY, 0x1001, 0x1003, 0x603F (no change of the power state)."""
        register = epos4_errors.error_register(code)
        self.code = code
        self.store.set(0x603F, 0, code)
        self.store.set(0x1001, 0, register)
        self._push_history(code)
        self._emcy(code, register)

    def clear(self) -> None:
        """The errors are gone (fault reset): EMCY 0x0000."""
        self.code = 0
        self.store.set(0x603F, 0, 0)
        self.store.set(0x1001, 0, 0)
        self._emcy(0x0000, 0)

    def clear_history(self) -> None:
        """0 written to 0x1003 sub 0 clears the history."""
        for sub in range(1, 256):
            if (0x1003, sub) not in self.store:
                break
            self.store.set(0x1003, sub, 0)

    def _push_history(self, code: int) -> None:
        store = self.store
        subs = [s for s in range(1, 256) if (0x1003, s) in store]
        if not subs:
            return
        for sub in reversed(subs[1:]):
            store.set(0x1003, sub, store.get(0x1003, sub - 1))
        store.set(0x1003, 1, code)
        store.set(0x1003, 0, min(len(subs), store.get(0x1003, 0) + 1))

    def _emcy(self, code: int, register: int) -> None:
        cob = self.store.get(0x1014, 0, 0x80 + self.node_id)
        if cob & COB_INVALID or not self.may_send():
            return
        self.send(cob & 0x7FF, _EMCY.pack(code, register, bytes(5)))
