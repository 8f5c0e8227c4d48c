"""The messages other threads send the cycle (see cycle.py for who owns
what). Each is immutable; the cycle handles them in the order they came,
except commands, where the last of a joint in one batch wins."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional, Tuple

from ..cia402 import State
from ..limits import JointLimits
from ..objects import ObjectKey
from .axis import Binding
from .check import Checked


@dataclass(frozen=True)
class Command:
    axis: str
    checked: Checked


@dataclass(frozen=True)
class StateRequest:
    axes: Tuple[str, ...]
    state: Optional[State]
    fault_reset: bool = False


@dataclass(frozen=True)
class StopInPlace:
    axes: Tuple[str, ...]


@dataclass(frozen=True)
class ShuttingDown:
    """Shutdown has begun: from here on the cycle takes state requests only
    towards a stop (a mode switch still under way must not enable a drive
    shutdown has stopped)."""


@dataclass(frozen=True)
class Hold:
    axis: str
    raw_position: int


@dataclass(frozen=True)
class SetMode:
    axis: str
    mode: int
    raw_position: int


@dataclass(frozen=True)
class ModeConfirmed:
    axis: str
    mode: int


@dataclass(frozen=True)
class Homing:
    axis: str
    on: bool


@dataclass(frozen=True)
class Ready:
    axes: Tuple[str, ...]
    ready: bool


@dataclass(frozen=True)
class ClearError:
    axis: str
    raw_position: int
    statusword: int
    quick_stop_option: Optional[int] = None   # 0x605A read over SDO (None: not read)


@dataclass(frozen=True)
class Together:
    """Requests one cycle must take together: a state request with the
    error clearing it depends on, so that no cycle sees one without the
    other (a cleared error and no target state yet would judge the drive's
    state against the one held before the error)."""
    messages: Tuple[Any, ...]


@dataclass(frozen=True)
class Detach:
    axis: str


@dataclass(frozen=True)
class Attach:
    axis: str
    binding: Binding


@dataclass(frozen=True)
class SetOutput:
    axis: str
    key: ObjectKey
    value: int


@dataclass(frozen=True)
class SetHeartbeat:
    axis: str
    ms: int


@dataclass(frozen=True)
class SetLimits:
    axis: str
    limits: JointLimits


@dataclass(frozen=True)
class Heartbeat:
    node_id: int
    data: bytes
    time: float


@dataclass(frozen=True)
class Emcy:
    node_id: int
    data: bytes
    time: float


@dataclass(frozen=True)
class ClearBusError:
    """recover: count send failures afresh; the bus error ends with the
    first cycle whose frames all go out."""


@dataclass(frozen=True)
class RestartSync:
    """recover: restart the SYNC producer, in the cycle that uses it."""
