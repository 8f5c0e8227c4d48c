"""PDO communication and mapping parameters of one node (CiA 301 7.2 / 7.5.2).

Drive side only: canopen's PDO classes configure a remote node's PDOs; they
do not validate mapping writes nor implement the slave's SYNC counting, so
this module does.  Each PDO packs/unpacks with one precompiled struct.
"""
from __future__ import annotations

import operator
import struct
from typing import Any, Dict, List, Optional, Tuple

from .objects import (ABORT_DEVICE_STATE, ABORT_NOT_MAPPABLE, ABORT_PDO_LENGTH,
                      ABORT_VALUE_HIGH, ABORT_VALUE_RANGE, Key, ObjectStore, SdoAbort)

_FORMATS = {0x1: "?", 0x2: "b", 0x3: "h", 0x4: "i", 0x5: "B", 0x6: "H", 0x7: "I",
            0x8: "f", 0x15: "q", 0x1B: "Q"}
COB_INVALID = 0x80000000
COB_NO_RTR = 0x40000000


class Pdo:
    """Runtime view of one RPDO or TPDO."""

    def __init__(self, rx: bool, number: int):
        self.rx = rx
        self.number = number  # 1..4
        self.comm = (0x1400 if rx else 0x1800) + number - 1
        self.mapping = (0x1600 if rx else 0x1A00) + number - 1
        self.cob_id = 0
        self.valid = False
        self.rtr_allowed = False
        self.transmission_type = 255
        self.inhibit = 0.0  # seconds
        self.keys: List[Key] = []
        self.codec = struct.Struct("<")
        self.sync_counter = 0
        self.last_data: Optional[bytes] = None
        self.last_time = -1e9
        self.sampled: Optional[bytes] = None  # TPDO type 252 / buffered sync RPDO

    @property
    def synchronous(self) -> bool:
        return self.transmission_type <= 240 or self.transmission_type == 252

    def load(self, store: ObjectStore) -> None:
        cob = store.get(self.comm, 1, COB_INVALID)
        self.cob_id = cob & 0x7FF
        self.valid = not cob & COB_INVALID
        self.rtr_allowed = not cob & COB_NO_RTR
        self.transmission_type = store.get(self.comm, 2, 255)
        self.inhibit = store.get(self.comm, 3, 0) * 100e-6
        count = store.get(self.mapping, 0, 0)
        keys, fmt = [], "<"
        for sub in range(1, count + 1):
            entry = store.get(self.mapping, sub, 0)
            key = (entry >> 16, (entry >> 8) & 0xFF)
            var = store.vars.get(key)
            if var is None or var.data_type not in _FORMATS:
                self.valid = False  # an inconsistent DCF: keep the PDO off
                break
            keys.append(key)
            fmt += _FORMATS[var.data_type]
        self.keys = keys
        self.codec = struct.Struct(fmt)
        getter = operator.itemgetter(*keys) if keys else None
        self._values = (lambda values: (getter(values),)) if len(keys) == 1 else getter
        if not keys:
            self.valid = False
        self.sync_counter = 0
        self.last_data = None
        self.sampled = None

    def pack(self, values: Dict[Key, Any]) -> bytes:
        return self.codec.pack(*self._values(values))

    def unpack(self, data: bytes) -> List[Tuple[Key, Any]]:
        return list(zip(self.keys, self.codec.unpack_from(data)))


class PdoSet:
    """The 4 RPDOs and 4 TPDOs of an EPOS4."""

    def __init__(self) -> None:
        self.rpdos = [Pdo(True, n) for n in range(1, 5)]
        self.tpdos = [Pdo(False, n) for n in range(1, 5)]
        self._by_index: Dict[int, Pdo] = {}
        for pdo in self.rpdos + self.tpdos:
            self._by_index[pdo.comm] = pdo
            self._by_index[pdo.mapping] = pdo

    def load(self, store: ObjectStore) -> None:
        for pdo in self.rpdos + self.tpdos:
            pdo.load(store)

    def load_one(self, store: ObjectStore, index: int) -> None:
        """Reload the PDO whose parameter ``index`` was written (the others
        did not change)."""
        self._by_index[index].load(store)

    def owns(self, index: int) -> bool:
        return index in self._by_index

    def check_write(self, store: ObjectStore, key: Key, value: int) -> None:
        """Refuse writes the CiA 301 PDO configuration rules forbid."""
        index, sub = key
        pdo = self._by_index[index]
        cob = store.get(pdo.comm, 1, COB_INVALID)
        valid = not cob & COB_INVALID
        if index == pdo.comm:
            if sub == 1 and valid and not value & COB_INVALID and (value & 0x1FFFFFFF) != (cob & 0x1FFFFFFF):
                raise SdoAbort(ABORT_VALUE_RANGE, "change COB-ID of a valid PDO")
            if sub == 2 and 241 <= value <= 251:
                raise SdoAbort(ABORT_VALUE_RANGE, "reserved transmission type")
            if sub == 2 and pdo.rx and value in (252, 253):
                raise SdoAbort(ABORT_VALUE_RANGE, "RTR types are for TPDOs")
            if sub == 3 and valid:
                raise SdoAbort(ABORT_DEVICE_STATE, "inhibit time of a valid PDO")
            return
        # mapping parameter
        if valid:
            raise SdoAbort(ABORT_DEVICE_STATE, "mapping of a valid PDO")
        count = store.get(pdo.mapping, 0, 0)
        if sub == 0:
            if value > 8:
                raise SdoAbort(ABORT_VALUE_HIGH)
            bits = 0
            for n in range(1, value + 1):
                bits += store.get(pdo.mapping, n, 0) & 0xFF
                self._check_entry(store, pdo, store.get(pdo.mapping, n, 0))
            if bits > 64:
                raise SdoAbort(ABORT_PDO_LENGTH)
            return
        if count != 0:
            raise SdoAbort(ABORT_DEVICE_STATE, "set sub-index 0 to 0 before remapping")
        if value:
            self._check_entry(store, pdo, value)

    @staticmethod
    def _check_entry(store: ObjectStore, pdo: Pdo, entry: int) -> None:
        key = (entry >> 16, (entry >> 8) & 0xFF)
        var = store.variable(*key)  # 0x06020000 / 0x06090011 when absent
        allowed = var.writable if pdo.rx else var.readable
        if (not var.pdo_mappable or not allowed or var.data_type not in _FORMATS
                or len(var) != (entry & 0xFF) and not (var.data_type == 1 and entry & 0xFF == 8)):
            raise SdoAbort(ABORT_NOT_MAPPABLE, "0x%08X" % entry)
