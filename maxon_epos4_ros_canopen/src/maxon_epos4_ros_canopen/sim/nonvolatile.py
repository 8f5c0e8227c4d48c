"""Non-volatile memory of one simulated EPOS4: CiA 301 "store parameters"
(0x1010) and "restore default parameters" (0x1011).

A node powers on (and resets on NMT "reset node" / "reset communication")
with the values its ObjectStore calls ``initial``. At first these are the
DCF's ParameterValues: the settings the drive left the factory with, as the
file describes them. Writing "save" to 0x1010 copies the live values of the
settings into that memory, so that they survive the next power cycle;
writing "load" to 0x1011 puts the file's values back into it, effective at
the next power cycle or reset (as CiA 301 specifies). Anything written by SDO
and not stored is lost at power-off, as on the drive.
"""
from __future__ import annotations

from typing import Any, Dict, Tuple

from .objects import Key, ObjectStore

# Sub-index of 0x1010/0x1011 -> the index range it covers (CiA 301):
# 1 all parameters, 2 communication, 3 application (profile), 4 manufacturer.
RANGES: Dict[int, Tuple[int, int]] = {1: (0x0000, 0xFFFF), 2: (0x1000, 0x1FFF),
                                      3: (0x6000, 0x9FFF), 4: (0x2000, 0x5FFF)}

# Writable objects that are commands or set-points, not settings: the drive
# does not keep them across a power cycle (a controlword or a target stored
# in flash would act again at power-on).
NOT_STORED = frozenset({
    0x1003,  # error history (writing 0 clears it)
    0x1010, 0x1011,  # the store and restore commands themselves
    0x6040,  # controlword
    0x6071, 0x607A, 0x60FF,  # target torque, position, velocity
    0x60B0, 0x60B1, 0x60B2,  # position, velocity, torque offsets (CSx set-points)
    0x60FE,  # physical outputs
})


def stored(index: int) -> bool:
    """Whether 0x1010 keeps the object at ``index`` (when it is writable)."""
    return index not in NOT_STORED


class NonVolatileMemory:
    """The power-on values of ``store``, changed by 0x1010 and 0x1011."""

    def __init__(self, store: ObjectStore) -> None:
        self.store = store
        self.defaults: Dict[Key, Any] = dict(store.initial)  # the file's values
        self.saves = 0  # how often "save" was written (tests read it)

    def _keys(self, sub: int):
        lo, hi = RANGES.get(sub, RANGES[1])
        for key, var in self.store.vars.items():
            if lo <= key[0] <= hi and var.writable and stored(key[0]):
                yield key

    def save(self, sub: int) -> None:
        """0x1010 sub ``sub`` = "save": the live values become the power-on ones."""
        memory = dict(self.store.initial)  # a copy: the node's own from here on
        for key in self._keys(sub):
            memory[key] = self.store.values[key]
        self.store.initial = memory
        self.saves += 1

    def restore_defaults(self, sub: int) -> None:
        """0x1011 sub ``sub`` = "load": the file's values at the next power-on."""
        memory = dict(self.store.initial)
        for key in self._keys(sub):
            memory[key] = self.defaults[key]
        self.store.initial = memory
