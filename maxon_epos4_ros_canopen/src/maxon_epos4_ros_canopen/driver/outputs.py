"""The RxPDOs of one axis: the values the driver commands, and which frames
go out in a cycle.

Owned by its Axis, so by the cycle thread. It holds only values the axis
set (its controlword, its mode, its targets, what set_object wrote); no
value of a received frame is ever copied into it.
"""
from __future__ import annotations

from typing import Callable, Dict, List, Mapping, Optional, Set, Tuple

from ..objects import ObjectKey
from .modes import CONTROLWORD, TARGET_OF_KIND, TARGET_POSITION, TARGET_TORQUE, TARGET_VELOCITY
from .pdo import RxPdo

REFRESH_CYCLES = 50  # RxPDOs that did not change are sent again this often


class Outputs:
    """One axis's RxPDO values and the frames last sent of them.

    Where each object sits is worked out at ``bind`` so the cycle indexes
    lists instead of hashing keys. A PDO is packed again only when a value
    in it changed: after a pack, the last frame sent holds exactly these
    values.
    """

    def __init__(self) -> None:
        self.vals: List[List[int]] = []          # per RxPDO: its objects' values
        self._dirty: List[bool] = []             # values changed since the PDO was last packed
        self._last: List[bytes] = []             # per RxPDO: the frame last sent
        self._codec: Tuple[Tuple[int, Callable[..., bytes]], ...] = ()
        self._force: Set[int] = set()            # RxPDOs sent this cycle whether they changed or not
        self._tick = 0
        self._at: Dict[ObjectKey, Tuple[Tuple[int, int], ...]] = {}   # object -> (PDO, field) of each copy
        self._cw_at: Tuple[Tuple[int, int], ...] = ()
        self._cw_rx = -1
        self.target_at: Dict[str, Tuple[Tuple[int, int], ...]] = {}   # command kind -> where its target sits
        self.cyclic_rx_of: Dict[str, int] = {}                          # command kind -> its target's RxPDO

    def bind(self, rx: Tuple[RxPdo, ...], initial: Mapping[ObjectKey, int]) -> None:
        """A configured node's RxPDOs, with the values they start with; every
        PDO goes out in the next cycle."""
        self._last = [b""] * len(rx)
        self._dirty = [True] * len(rx)
        self._codec = tuple((r.cob_id, r.pack_args) for r in rx)
        self.vals = [[int(initial.get(k, 0)) for k in r.keys] for r in rx]
        at: Dict[ObjectKey, List[Tuple[int, int]]] = {}
        for i, r in enumerate(rx):
            for j, key in enumerate(r.keys):
                at.setdefault(key, []).append((i, j))
        self._at = {k: tuple(v) for k, v in at.items()}
        self._cw_at = self._at[CONTROLWORD]
        self._cw_rx = self._cw_at[0][0]
        self.target_at = {kind: self._at.get(key, ()) for kind, key in TARGET_OF_KIND.items()}
        cyclic_rx = {key: self._at[key][0][0] for key in (TARGET_POSITION, TARGET_VELOCITY, TARGET_TORQUE)
                     if key in self._at}
        self.cyclic_rx_of = {kind: cyclic_rx.get(key, -1) for kind, key in TARGET_OF_KIND.items()}
        self._force = set()

    def set(self, key: ObjectKey, value: int) -> None:
        """An object's value in every RxPDO that carries it (none: no-op)."""
        vals, dirty = self.vals, self._dirty
        for i, j in self._at.get(key, ()):
            if vals[i][j] != value:
                vals[i][j] = value
                dirty[i] = True

    def set_target(self, kind: str, value: int) -> None:
        """``set`` for a command kind's target object."""
        vals, dirty = self.vals, self._dirty
        for i, j in self.target_at[kind]:
            if vals[i][j] != value:
                vals[i][j] = value
                dirty[i] = True

    def send_target(self, kind: str, value: int) -> None:
        """A command kind's target, sent in this cycle's RxPDOs whether it
        changed or not."""
        self.set_target(kind, value)
        for i, _ in self.target_at.get(kind, ()):
            self._force.add(i)

    def send(self, send: Callable[[int, bytes], None], cw: int, cyclic_rx: int,
             kind: Optional[str] = None, target: int = 0) -> None:
        """Send this cycle's RxPDOs with controlword ``cw`` and, when
        ``kind`` is given, that command kind's target ``target``. The
        controlword PDO goes out every cycle, as with ros_canopen, so drive
        and master stay in step even if a frame was lost; the cyclic
        target's PDO (``cyclic_rx``, -1: none) too; the others when they
        change, every REFRESH_CYCLES cycles, and those with a target the
        driver must be sure the drive holds (send_target)."""
        vals, dirty = self.vals, self._dirty
        if kind is not None:
            for i, j in self.target_at[kind]:  # set_target, inline: every cycle in a cyclic mode
                if vals[i][j] != target:
                    vals[i][j] = target
                    dirty[i] = True
        for i, j in self._cw_at:
            if vals[i][j] != cw:
                vals[i][j] = cw
                dirty[i] = True
        self._tick += 1
        force = self._force
        refresh = self._tick % REFRESH_CYCLES == 0
        last = self._last
        cw_rx = self._cw_rx
        i = -1
        for cob_id, pack in self._codec:
            i += 1
            if dirty[i]:
                data = pack(*vals[i])
                dirty[i] = False
                if data != last[i] or i == cw_rx or i == cyclic_rx or refresh or (force and i in force):
                    last[i] = data
                    send(cob_id, data)
            elif i == cw_rx or i == cyclic_rx or refresh or (force and i in force):
                send(cob_id, last[i])
        if force:
            force.clear()
