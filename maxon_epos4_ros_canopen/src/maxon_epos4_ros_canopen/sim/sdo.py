"""SDO server (CiA 301 expedited and segmented transfers) of one node.

Written by hand because the drive needs what canopen's SdoServer lacks:
transfer timeouts, toggle checks, size checks and delayed answers for fault
injection.  Block transfer is answered with "command specifier not valid".
"""
from __future__ import annotations

import struct
from typing import Callable, List, Optional

from .objects import (ABORT_COMMAND, ABORT_GENERAL, ABORT_LENGTH, ABORT_TIMEOUT,
                      ABORT_TOGGLE, ObjectStore, SdoAbort)

_HEADER = struct.Struct("<BHB")


class SdoServer:
    """Answers requests; ``send(data)`` transmits one 8-byte answer."""

    def __init__(self, store: ObjectStore, send: Callable[[bytes], None], timeout: float = 1.0):
        self.store = store
        self.send = send
        self.timeout = timeout
        self._mode: Optional[str] = None  # None, "download", "upload"
        self._index = 0
        self._sub = 0
        self._toggle = 0
        self._buffer = bytearray()
        self._size: Optional[int] = None
        self._last = 0.0

    def _abort(self, code: int, index: Optional[int] = None, sub: Optional[int] = None) -> None:
        self._mode = None
        index = self._index if index is None else index
        sub = self._sub if sub is None else sub
        self.send(_HEADER.pack(0x80, index, sub) + struct.pack("<I", code))

    def check_timeout(self, now: float) -> None:
        if self._mode is not None and now - self._last > self.timeout:
            self._abort(ABORT_TIMEOUT)

    def on_request(self, data: bytes, now: float) -> None:
        if len(data) != 8:
            return  # CiA 301: SDO frames have 8 bytes; others are ignored
        self._last = now
        command = data[0]
        ccs = command >> 5
        try:
            if ccs == 1:
                self._initiate_download(command, data)
            elif ccs == 0:
                self._download_segment(command, data)
            elif ccs == 2:
                self._initiate_upload(data)
            elif ccs == 3:
                self._upload_segment(command)
            elif ccs == 4:
                self._mode = None  # the client aborted
            else:
                index, sub = _HEADER.unpack_from(data)[1:]
                self._abort(ABORT_COMMAND, index, sub)
        except SdoAbort as exc:
            self._abort(exc.code)
        except Exception:  # a bug must not kill the simulator: report it on the bus
            self._abort(ABORT_GENERAL)

    def _initiate_download(self, command: int, data: bytes) -> None:
        _, self._index, self._sub = _HEADER.unpack_from(data)
        self._mode = None
        expedited, size_given = command & 0x02, command & 0x01
        if expedited:
            payload = data[4:8 - ((command >> 2) & 0x3)] if size_given else self._unsized(data[4:8])
            self.store.download(self._index, self._sub, bytes(payload))
            self.send(_HEADER.pack(0x60, self._index, self._sub) + bytes(4))
            return
        self.store.variable(self._index, self._sub)  # abort early if absent
        self._size = struct.unpack_from("<I", data, 4)[0] if size_given else None
        self._mode, self._toggle, self._buffer = "download", 0, bytearray()
        self.send(_HEADER.pack(0x60, self._index, self._sub) + bytes(4))

    def _unsized(self, payload: bytes) -> bytes:
        var = self.store.variable(self._index, self._sub)
        size = max(1, len(var) // 8) if var.data_type in var.STRUCT_TYPES or var.data_type == 1 else 4
        return payload[:size]

    def _download_segment(self, command: int, data: bytes) -> None:
        if self._mode != "download":
            raise SdoAbort(ABORT_COMMAND)
        toggle = (command >> 4) & 1
        if toggle != self._toggle:
            raise SdoAbort(ABORT_TOGGLE)
        self._buffer += data[1:8 - ((command >> 1) & 0x7)]
        if command & 0x01:  # last segment: store first, so a bad value aborts instead of confirming
            self._mode = None
            if self._size is not None and self._size != len(self._buffer):
                raise SdoAbort(ABORT_LENGTH)
            self.store.download(self._index, self._sub, bytes(self._buffer))
        self.send(bytes([0x20 | (toggle << 4)]) + bytes(7))
        self._toggle ^= 1

    def _initiate_upload(self, data: bytes) -> None:
        _, self._index, self._sub = _HEADER.unpack_from(data)
        self._mode = None
        payload = self.store.upload(self._index, self._sub)
        if 0 < len(payload) <= 4:
            command = 0x43 | ((4 - len(payload)) << 2)
            self.send(_HEADER.pack(command, self._index, self._sub) + payload.ljust(4, b"\0"))
            return
        self._buffer, self._toggle, self._mode = bytearray(payload), 0, "upload"
        self.send(_HEADER.pack(0x41, self._index, self._sub) + struct.pack("<I", len(payload)))

    def _upload_segment(self, command: int) -> None:
        if self._mode != "upload":
            raise SdoAbort(ABORT_COMMAND)
        toggle = (command >> 4) & 1
        if toggle != self._toggle:
            raise SdoAbort(ABORT_TOGGLE)
        chunk, self._buffer = self._buffer[:7], self._buffer[7:]
        last = not self._buffer
        header = (toggle << 4) | ((7 - len(chunk)) << 1) | int(last)
        self.send(bytes([header]) + bytes(chunk).ljust(7, b"\0"))
        self._toggle ^= 1
        if last:
            self._mode = None


__all__: List[str] = ["SdoServer"]
