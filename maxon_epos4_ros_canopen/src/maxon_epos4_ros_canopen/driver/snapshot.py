"""What the rest of the program sees of an axis: the immutable AxisSnapshot
the cycle makes of it once per cycle, the one shown before the first init,
and the counters it carries.
"""
from __future__ import annotations

import math
from types import MappingProxyType
from typing import Any, Dict, Mapping, NamedTuple, Optional, Tuple

from .. import cia402
from ..cia402 import State
from ..config_schema import NodeConfig
from ..limits import JointLimits
from ..objects import ObjectKey
from ..units import object_variable_name
from .modes import POSITION_ACTUAL, VELOCITY_ACTUAL
from .plan import NodePlan


class AxisSnapshot(NamedTuple):
    """One axis as it stood at the end of a cycle's reading phase. Immutable."""
    name: str
    node_id: int
    key: str
    position: float
    velocity: float
    effort: float
    raw_position: int
    statusword: int
    state: Optional[State]
    mode_display: int
    active_mode: Optional[int]
    nmt_state: str
    error: Optional[str]
    halted: bool
    homing: bool
    ready: bool
    attached: bool
    target_state: Optional[State]
    held_state: Optional[State]
    last_emcy: str
    error_register: int
    heartbeat_ms: int
    rebooted: bool
    command_kind: Optional[str]
    command_value: float
    last_refusal: str
    tpdo_keys: Tuple[Tuple[ObjectKey, ...], ...]          # per TPDO: its objects
    tpdo_values: Tuple[Optional[Tuple[Any, ...]], ...]    # per TPDO: the latest values (None: none yet)
    counters: Mapping[str, int]
    limits: JointLimits
    plan: NodePlan
    status_cycle: int              # the cycle that last took in a statusword TPDO
    stamp: float                   # wall clock (time.time()) when the newest TPDO taken in arrived; 0: none
    # The position target (ROS units) the driver sends in CSP: the last
    # position command applied (in CSP, as far toward it as the joint's
    # velocity limit allowed so far), or the 0x6064 read over SDO that it
    # holds (enable, recover, mode switch). Never a TxPDO reading; NaN when
    # unknown.
    target_position: float = math.nan
    tpdo_arrived: Tuple[float, ...] = ()   # per TPDO: when its latest frame arrived (monotonic; NaN: none yet)
    read_at: float = math.nan              # when the cycle took in these readings (same clock)
    controlword: int = 0                   # the controlword the cycle before this snapshot sent

    @property
    def mode(self) -> int:
        """The drive's mode of operation display (0x6061)."""
        return self.mode_display

    @property
    def readings(self) -> Dict[ObjectKey, Any]:
        """object -> latest value of every TPDO-mapped object received."""
        return {k: v for keys, values in zip(self.tpdo_keys, self.tpdo_values) if values is not None
                for k, v in zip(keys, values)}

    def mode_name(self) -> str:
        return cia402.mode_name(self.mode_display)

    def tpdo_ages(self) -> Tuple[float, ...]:
        """Per TPDO: the age of its latest values when the cycle took them
        in (seconds; NaN: none yet). A PDO of transmission type N is up to
        N SYNC periods old by design."""
        at = self.read_at
        return tuple(at - t for t in self.tpdo_arrived)

    def describe_ages(self) -> str:
        """For diagnostics: "6041,6064: 2; 606C: 41" (ms per TPDO's objects)."""
        return "; ".join("%s: %s" % (",".join(str(k) for k in keys), "-" if math.isnan(age) else "%.0f" % (age * 1000))
                         for keys, age in zip(self.tpdo_keys, self.tpdo_ages()))

    def motion_age(self) -> float:
        """The age (s) of the older of the position and velocity actual
        values (0x6064, 0x606C) when the cycle took them in: what a judge
        of the joint's motion must allow for. NaN while one of them has not
        arrived; 0.0 when no TPDO carries either."""
        ages = [age for keys, age in zip(self.tpdo_keys, self.tpdo_ages())
                if POSITION_ACTUAL in keys or VELOCITY_ACTUAL in keys]
        if any(math.isnan(age) for age in ages):
            return math.nan
        return max(ages, default=0.0)

    @property
    def reading_ages(self) -> Dict[ObjectKey, float]:
        """object -> age (s) of its value in ``readings``."""
        return {k: age for keys, values, age in zip(self.tpdo_keys, self.tpdo_values, self.tpdo_ages())
                if values is not None for k in keys}



class Counters(dict):
    """What an axis counted (bad frames, refused commands...), by name; a
    snapshot carries an immutable copy, made again only after a count
    changed."""

    NAMES = ("bad_tpdo", "undefined_statusword", "undefined_nmt_state", "bad_heartbeat", "bad_emcy",
             "refused_commands", "clipped_commands", "emcy_not_logged", "tpdo_conflicts")

    def __init__(self) -> None:
        super().__init__((name, 0) for name in self.NAMES)
        self.shown: Optional[Mapping[str, int]] = None  # the copy snapshots carry; None: stale

    def add(self, what: str, n: int = 1) -> None:
        self[what] += n
        self.shown = None

    def view(self) -> Mapping[str, int]:
        """The immutable copy for a snapshot."""
        shown = self.shown
        if shown is None:
            shown = self.shown = MappingProxyType(dict(self))
        return shown


def initial_snapshot(cfg: NodeConfig, plan: NodePlan, limits: JointLimits) -> AxisSnapshot:
    """What status shows for an axis before the first init."""
    return AxisSnapshot(cfg.name, cfg.node_id, cfg.key, math.nan, math.nan, math.nan, 0, 0, None, 0, None,
                        "UNKNOWN", None, False, False, False, False, None, None, "", 0, 0, False, None, math.nan,
                        "", (), (), MappingProxyType({}), limits, plan, 0, 0.0)


def env_for_check(snapshot: AxisSnapshot, initial_env: Mapping[str, float]) -> Dict[str, float]:
    """An environment for converting a command outside the cycle: the
    objects of the latest snapshot (plus those read by SDO at init)."""
    env: Dict[str, float] = dict(initial_env)
    for key, value in snapshot.readings.items():
        env[object_variable_name(key)] = value
    env["pos"], env["vel"], env["eff"] = snapshot.position, snapshot.velocity, snapshot.effort
    return env
