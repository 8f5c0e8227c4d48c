"""One drive as the driver's cycle sees it: readings in, CiA 402 and mode
work, the values it commands out.

An Axis belongs to the thread that runs the cycle; nothing else reads or
writes it (see the rule in driver/__init__.py). It learns what happens
through messages (commands, state requests, heartbeats, EMCYs) and through
the TPDO receiver's latest frames, and it shows itself to the rest of the
program only as an immutable AxisSnapshot, made once per cycle.

What it sends is built from its own fields only: the controlword it works
out, the mode it was asked for and the targets it was commanded (or the
position the service thread read over SDO when it asked to hold). No value
of a received frame is ever copied into an outgoing one.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, Callable, Dict, List, Mapping, NamedTuple, Optional, Tuple

from .. import cia402
from ..cia402 import State
from ..config import SWITCHING_STATES, NodeConfig
from ..limits import JointLimits, saturate
from ..epos4_errors import describe as describe_error
from ..objects import ObjectKey, find_variable
from ..result import OK, Result, fail, ok
from ..units import EVALUATION_ERRORS, Expression, object_variable_name
from .modes import (COMMAND_KINDS, CONTROLWORD, HOMING, MODES, MODES_DISPLAY, MODES_OF_OPERATION,
                    POSITION_ACTUAL, PROFILE_POSITION, STATUSWORD, TARGET_OF_KIND, TARGET_POSITION, TARGET_TORQUE,
                    TARGET_VELOCITY, mode_of)
from .pdo import RxPdo, TpdoReceiver, TxPdo
from .plan import NodePlan

log = logging.getLogger("maxon_epos4_ros_canopen.driver")

REFRESH_CYCLES = 50  # RxPDOs that did not change are sent again this often
NMT_NAMES = {0: "INITIALISING", 4: "STOPPED", 5: "OPERATIONAL", 0x7F: "PRE-OPERATIONAL"}
SWITCHING_STATE = {n: State(v) for n, v in SWITCHING_STATES.items()}

# Controlword that keeps the drive in each state once it is there.
_HOLD = {
    State.SWITCH_ON_DISABLED: cia402.CW_DISABLE_VOLTAGE,
    State.READY_TO_SWITCH_ON: cia402.CW_SHUTDOWN,
    State.SWITCHED_ON: cia402.CW_SWITCH_ON,
    State.OPERATION_ENABLED: cia402.CW_ENABLE_OPERATION,
    State.QUICK_STOP_ACTIVE: cia402.CW_QUICK_STOP,
}


def holding_controlword(statusword: int) -> int:
    """The controlword that keeps a drive in the state its statusword shows:
    what the driver sends before it has decided anything. Never the drive's
    last controlword (0x6040): a drive its own fault reaction or consumer
    brought to Quick Stop Active still holds "enable operation" there, and
    sending that again would re-enable it (transition 16)."""
    return _HOLD.get(cia402.state_or_none(statusword), cia402.CW_DISABLE_VOLTAGE)


_REBOOTED = "node rebooted"
EMCY_LOG_LINES = 5  # EMCY log lines per second and axis at most
# Transitions the drive makes by itself that are no error: the end of a
# quick stop ramp (option codes 1-4 end in Switch On Disabled).
_AUTOMATIC = {(State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED)}

# Bound once for the cycle's hot paths (a module global is one lookup, an
# enum member through its class several; MODES.get(None) is None, as mode_of).
_ENABLED = State.OPERATION_ENABLED
_mode_get = MODES.get
_isfinite = math.isfinite
_tuple_new = tuple.__new__
_CW_NO_FAULT_RESET = ~cia402.CW_FAULT_RESET_BIT


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


class Converter:
    """Commands in ROS units to device values: immutable, one per axis.

    The expressions were compiled once when the configuration was loaded;
    the target objects' integer ranges come from the object dictionary.
    """

    _VARIABLE = {"position": "pos", "velocity": "vel", "effort": "eff"}

    def __init__(self, cfg: NodeConfig, od: Any) -> None:
        self.expressions: Dict[str, Expression] = {
            "position": cfg.pos_to_device, "velocity": cfg.vel_to_device, "effort": cfg.eff_to_device}
        self.ranges: Dict[str, Tuple[int, int, int]] = {}
        for kind, key in TARGET_OF_KIND.items():
            bits = len(find_variable(od, key))
            self.ranges[kind] = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1, key.index)
        self.dynamic = {k: bool(e.objects) for k, e in self.expressions.items()}

    def convert(self, kind: str, value: float, env: Dict[str, float]) -> Tuple[Optional[int], Optional[str]]:
        """Device value of a command, or why there is none. ``env`` holds the
        objects the expression reads; its ``pos``/``vel``/``eff`` entry is
        overwritten with ``value``."""
        expr = self.expressions[kind]
        env[self._VARIABLE[kind]] = value
        try:  # Expression.evaluate, inline: every command goes through here
            raw = float(expr.raw(env))
        except EVALUATION_ERRORS:
            raw = math.nan
        if not math.isfinite(raw):
            return None, "%s %g converts to %r by %r: refused" % (kind, value, raw, expr.text)
        raw_int = int(round(raw))
        lo, hi, index = self.ranges[kind]
        if not lo <= raw_int <= hi:
            return None, "%s %g converts to %d, outside 0x%04X's range %d..%d" % (kind, value, raw_int, index, lo, hi)
        return raw_int, None


def command_problem(axis: Any, kind: str, value: Any) -> Optional[str]:
    """Why a command cannot be taken now (None: it can). ``axis`` is an Axis
    or an AxisSnapshot: the same checks run in the caller's thread on the
    latest snapshot and again in the cycle when the command is applied."""
    if kind not in COMMAND_KINDS:
        return "unknown command kind %r (position, velocity, effort)" % (kind,)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return "command must be a number"
    try:
        value = float(value)
    except OverflowError:
        return "%s command refused: not a finite number" % kind
    if not math.isfinite(value):
        return "%s command %r refused: not a finite number" % (kind, value)
    if axis.error:
        return "%s is in error (%s): call recover" % (axis.name, axis.error)
    if not axis.ready:
        return "%s is not initialized: call init" % axis.name
    if axis.halted:
        return "%s is halted: call recover before sending commands" % axis.name
    if axis.state != State.OPERATION_ENABLED:
        return "%s is not operation enabled (state %s)" % (axis.name, axis.state.value if axis.state else "unknown")
    if axis.homing:
        return "%s is homing" % axis.name
    mode = mode_of(axis.active_mode)
    if mode is None or mode.command_kind is None:
        return "%s has no mode for commands yet (start a controller)" % axis.name
    if mode.command_kind != kind:
        return "%s is in mode %s, which takes %s commands, not %s" % (
            axis.name, mode.name, mode.command_kind, kind)
    return None


@dataclass(frozen=True)
class Binding:
    """What configuring a node produced, handed to the axis in one piece:
    its PDO codecs and the values its RxPDOs start with (read by SDO)."""
    rx: Tuple[RxPdo, ...]
    tx: Tuple[TxPdo, ...]
    initial_out: Mapping[ObjectKey, int]
    initial_env: Mapping[str, float]       # objects conversions read that no TPDO carries
    raw_position: int                      # 0x6064 read by SDO
    heartbeat_ms: int
    configured_at: float                   # monotonic; older TPDO frames are stale


class Axis:
    """One drive's state; owned by the cycle thread."""

    def __init__(self, cfg: NodeConfig, od: Any, plan: NodePlan, limits: JointLimits) -> None:
        self.cfg = cfg
        self.name = cfg.name
        self.node_id = cfg.node_id
        self.key = cfg.key
        self.od = od
        self.plan = plan
        self.limits = limits
        self.converter = Converter(cfg, od)
        self.switching_state = SWITCHING_STATE[cfg.switching_state]
        self._from_device = (cfg.pos_from_device, cfg.vel_from_device, cfg.eff_from_device)
        # a constant conversion (eff_from_device: "0") has one value: not evaluated per cycle
        self._from_const = tuple(e.evaluate({}) if e.constant else None for e in self._from_device)
        self._from_raw = tuple(e.raw for e in self._from_device)
        # readings (ROS units) and what the drive reports
        self.position = math.nan
        self.velocity = math.nan
        self.effort = math.nan
        self.raw_position = 0
        self.statusword = 0
        self.state: Optional[State] = None
        self.mode_display = 0
        self.env: Dict[str, float] = {"pos": math.nan, "vel": math.nan, "eff": math.nan}
        # node status
        self.nmt_state = "UNKNOWN"
        self.last_emcy = ""
        self.error_register = 0
        self.error: Optional[str] = None
        self.heartbeat_ms = 0
        self.last_heartbeat = 0.0
        self.status_seen = 0.0          # monotonic time of the last statusword TPDO
        self.status_seen_cycle = 0
        self.rebooted = False
        # what the driver works towards
        self.target_state: Optional[State] = None
        self._confirm_after = 0  # status_seen_cycle when target_state was requested
        self._requested_at = 0.0  # monotonic time target_state was requested
        self.status_arrived = 0.0  # monotonic time the last statusword TPDO taken arrived
        # The drive left the held state on its own for a state that is no
        # fault, or the driver lost sight of it (no heartbeat, no TPDO, not
        # OPERATIONAL, bus error): its state is not the held one or
        # not known, and the driver holds it with quick stop until a state
        # is requested (see _hold_cw).
        self.quick_stop_hold = False
        self.held_state: Optional[State] = None  # the state last reached on request
        self.fault_reset = False
        self.active_mode: Optional[int] = None
        self.halted = False
        self.homing = False
        self.ready = False
        self.attached = False
        self.command_kind: Optional[str] = None
        self.command_value = math.nan
        self.command_raw = 0
        self.last_refusal = ""
        self._ppm_pending: Optional[int] = None
        self._ppm_stage = 0
        self._last_cw = 0
        self._tick = 0
        self.counters: Dict[str, int] = {"bad_tpdo": 0, "undefined_statusword": 0, "undefined_nmt_state": 0,
                                         "bad_heartbeat": 0, "bad_emcy": 0, "refused_commands": 0,
                                         "clipped_commands": 0, "emcy_not_logged": 0}
        self._counters_view: Optional[Mapping[str, int]] = None
        self._rx: Tuple[RxPdo, ...] = ()
        self._tx: Tuple[TxPdo, ...] = ()
        self._tx_last: List[Any] = []
        self._tx_vals: List[Optional[Tuple[Any, ...]]] = []
        self._tx_keys: Tuple[Tuple[ObjectKey, ...], ...] = ()
        self._rx_last: List[bytes] = []
        self._rx_dirty: List[bool] = []     # values changed since the PDO was last packed
        self._rx_codec: Tuple[Tuple[int, Callable[..., bytes]], ...] = ()
        self._tx_codec: Tuple[Tuple[int, int, Callable[[bytes], Tuple[Any, ...]]], ...] = ()
        self._status_pdo = -1
        # Where each object sits, worked out at attach so the cycle indexes
        # lists instead of hashing keys: RxPDO values per PDO, and
        # (PDO, field) of each object in the RxPDOs and TxPDOs.
        self._out_vals: List[List[int]] = []
        self._out_at: Dict[ObjectKey, Tuple[Tuple[int, int], ...]] = {}
        self._in_at: Dict[ObjectKey, Tuple[int, int]] = {}
        self._sw_at: Tuple[int, int] = (0, 0)
        self._mode_at: Optional[Tuple[int, int]] = None
        self._pos_at: Optional[Tuple[int, int]] = None
        self._env_at: Tuple[Tuple[str, int, int], ...] = ()
        self._cyclic_rx: Dict[ObjectKey, int] = {}
        self._cw_rx = -1
        self._cw_out: Tuple[Tuple[int, int], ...] = ()
        self._target_out: Dict[str, Tuple[Tuple[int, int], ...]] = {}  # command kind -> where its target sits
        self._cyclic_rx_of: Dict[str, int] = {}                          # command kind -> its target's RxPDO
        self._fresh_after = 0.0
        self._emcy_logged = -1e9
        self._emcy_window = -1e9   # start of the current second of EMCY log lines
        self._emcy_lines = 0
        self._display_mapped = True

    # ---------------------------------------------------------- binding
    def attach(self, binding: Binding, cycle: int, now: float) -> None:
        """Take a configured node's codecs and initial values; the drive's
        readings are unknown again until its TPDOs arrive."""
        self._rx, self._tx = binding.rx, binding.tx
        self._tx_last = [None] * len(self._tx)
        self._rejected_seen = [None] * len(self._tx)  # receiver.rejected at the last read
        self._tx_vals = [None] * len(self._tx)
        self._tx_keys = tuple(t.keys for t in self._tx)
        self._fresh_after = binding.configured_at
        self._rx_last = [b""] * len(self._rx)
        self._rx_dirty = [True] * len(self._rx)
        self._rx_codec = tuple((r.cob_id, r.pack_args) for r in self._rx)
        self._tx_codec = tuple((t.cob_id, t.length, t.unpack) for t in self._tx)
        self._out_vals = [[int(binding.initial_out.get(k, 0)) for k in r.keys] for r in self._rx]
        out_at: Dict[ObjectKey, List[Tuple[int, int]]] = {}
        for i, r in enumerate(self._rx):
            for j, key in enumerate(r.keys):
                out_at.setdefault(key, []).append((i, j))
        self._out_at = {k: tuple(v) for k, v in out_at.items()}
        self._cw_out = self._out_at[CONTROLWORD]
        self._target_out = {kind: self._out_at.get(key, ()) for kind, key in TARGET_OF_KIND.items()}
        self._in_at = {}
        for i, t in enumerate(self._tx):
            for j, key in enumerate(t.keys):
                self._in_at.setdefault(key, (i, j))
        # The controlword that holds the state the drive was in when it was
        # configured (holding_controlword): a node recover configured
        # without a reset may be enabled, and must stay so, and no more,
        # until the driver asks for another state. One the driver holds
        # with quick stop (it lost sight of it) gets that from the first
        # RxPDO on, not only once a TxPDO shows its state: recover reads
        # the state after this controlword reached the drive, and one that
        # changed it later would take the drive out of the state recover
        # confirmed.
        if self.quick_stop_hold:
            first_cw = cia402.CW_QUICK_STOP
        else:
            first_cw = int(binding.initial_out.get(CONTROLWORD, 0)) & ~cia402.CW_FAULT_RESET_BIT
        self._set_out(CONTROLWORD, first_cw)
        if self.active_mode is not None:
            self._set_out(MODES_OF_OPERATION, self.active_mode)
        self._sw_at = self._in_at[STATUSWORD]
        self._status_pdo = self._sw_at[0]
        self._mode_at = self._in_at.get(MODES_DISPLAY)
        self._pos_at = self._in_at.get(POSITION_ACTUAL)
        # A compact layout leaves modes of operation to SDO: the service that
        # switches modes confirms 0x6061 by SDO and tells the axis.
        self._display_mapped = self._mode_at is not None
        if not self._display_mapped:
            self.mode_display = 0  # unknown after a (re)configuration until confirmed
        self._cw_rx = self._out_at[CONTROLWORD][0][0]
        self._cyclic_rx = {}
        for key in (TARGET_POSITION, TARGET_VELOCITY, TARGET_TORQUE):
            if key in self._out_at:
                self._cyclic_rx[key] = self._out_at[key][0][0]
        self._cyclic_rx_of = {kind: self._cyclic_rx.get(key, -1) for kind, key in TARGET_OF_KIND.items()}
        names = []
        for expr in self._from_device + tuple(self.converter.expressions.values()):
            for key in expr.objects:
                names.append((object_variable_name(key), key))
        self._env_keys = tuple(dict(names).items())
        self._env_at = tuple((name, self._in_at[key][0], self._in_at[key][1])
                             for name, key in self._env_keys if key in self._in_at)
        for name, _ in self._env_keys:  # unknown (NaN) until a TPDO carries it
            self.env.setdefault(name, math.nan)
        self.env.update(binding.initial_env)
        self.raw_position = binding.raw_position
        self.state = None
        self.statusword = 0
        self.heartbeat_ms = binding.heartbeat_ms
        self.last_heartbeat = self.status_seen = now
        self.status_seen_cycle = cycle
        self.nmt_state = "OPERATIONAL"
        self.rebooted = False
        self.target_state = None
        self.held_state = None
        self._last_cw = first_cw
        self._ppm_pending = None
        self._ppm_stage = 0
        self.attached = True
        self.hold(binding.raw_position)

    def enabled_over_sdo(self, statusword: int) -> None:
        """The drive was brought to Operation Enabled over SDO before the
        cycle started (init), its statusword and, with a mode set, its 0x6061
        read back by SDO: the axis holds that state from its first RxPDO on,
        with the targets ``attach`` held."""
        self.statusword = statusword
        self.state = self.held_state = State.OPERATION_ENABLED
        self.target_state = None
        self.fault_reset = False
        self._last_cw = cia402.CW_ENABLE_OPERATION
        self._set_out(CONTROLWORD, cia402.CW_ENABLE_OPERATION)
        if self.active_mode is not None:
            self.mode_display = self.active_mode

    def detach(self) -> None:
        """Stop touching the node (it is being configured over SDO)."""
        self.attached = False

    # ------------------------------------------------------------- read
    def read(self, receiver: TpdoReceiver, now: float, cycle: int) -> None:
        """Take the TPDO frames that came since the last cycle."""
        vals = self._tx_vals
        seen = self._tx_last
        slots = receiver.slots
        rejected = receiver.rejected
        rejected_seen = self._rejected_seen
        i = -1
        for cob_id, length, unpack in self._tx_codec:
            i += 1
            n = rejected.get(cob_id, 0)
            if n != rejected_seen[i]:
                # frames of a wrong length, dropped by the receiver (counted
                # from the first read after attach on)
                if rejected_seen[i] is not None:
                    self._count("bad_tpdo", n - rejected_seen[i])
                rejected_seen[i] = n
            frame = slots.get(cob_id)
            if frame is None or frame is seen[i]:
                continue
            seen[i] = frame
            if frame[2] < self._fresh_after:  # arrived before the node was (re)configured
                continue
            data = frame[0]
            if len(data) != length:  # TxPdo.decode's check, inlined
                self._count("bad_tpdo")
                continue
            vals[i] = unpack(data)
            if i == self._status_pdo:
                self.status_seen = frame[1]
                self.status_seen_cycle = cycle
                self.status_arrived = frame[2]
        si, sj = self._sw_at
        if vals[si] is None:
            return
        sw = vals[si][sj]
        if sw != self.statusword or self.state is None:
            try:
                state = cia402.state_from_statusword(sw)
            except ValueError:
                self._count("undefined_statusword")
                state = self.state
            self.statusword = sw
            self.state = state
        at = self._mode_at
        if at is not None and vals[at[0]] is not None:
            self.mode_display = vals[at[0]][at[1]]
        at = self._pos_at
        if at is not None and vals[at[0]] is not None:
            self.raw_position = vals[at[0]][at[1]]
        env = self.env
        for name, i, j in self._env_at:
            if vals[i] is not None:
                env[name] = vals[i][j]
        env["pos"], env["vel"], env["eff"] = self.position, self.velocity, self.effort
        # Expression.evaluate, inline (three calls less per axis per cycle)
        pos, vel, eff = self._from_raw
        cpos, cvel, ceff = self._from_const
        if cpos is None:
            try:
                self.position = float(pos(env))
            except EVALUATION_ERRORS:
                self.position = math.nan
        else:
            self.position = cpos
        if cvel is None:
            try:
                self.velocity = float(vel(env))
            except EVALUATION_ERRORS:
                self.velocity = math.nan
        else:
            self.velocity = cvel
        if ceff is None:
            try:
                self.effort = float(eff(env))
            except EVALUATION_ERRORS:
                self.effort = math.nan
        else:
            self.effort = ceff
        # _supervise has nothing to do while the drive stays in the state it
        # was brought to and nothing else is asked
        state = self.state
        if state is not self.held_state or self.target_state is not None:
            self._supervise()

    def _supervise(self) -> None:
        state, target = self.state, self.target_state
        if state is None:
            return
        if target is not None:
            if (state == target and self.status_seen_cycle > self._confirm_after
                    and self.status_arrived > self._requested_at):
                self.target_state = None
                self.held_state = state
                if state != State.FAULT:
                    self.fault_reset = False
                return
            if state == State.FAULT and not self.fault_reset:
                self.set_error("drive is in fault%s" % self._emcy_suffix())
            return
        held = self.held_state
        if held is None or state == held:
            return
        if (held, state) in _AUTOMATIC:
            self.held_state = state
            return
        # The drive left the state on its own (fault, quick stop input, or a
        # frame that lies): report it and stop with the drive's own means;
        # never cut the power of a drive that may be moving.
        what = "fault" if state in (State.FAULT, State.FAULT_REACTION_ACTIVE) else state.value
        if what != "fault":
            self.quick_stop_hold = True
        self.set_error("drive left %s, now %s%s" % (held.value, what, self._emcy_suffix() if what == "fault" else ""))

    def _emcy_suffix(self) -> str:
        return (": " + self.last_emcy) if self.last_emcy else ""

    def set_error(self, text: str, sight_lost: bool = False) -> None:
        """The driver's reaction to anything wrong with this axis: report it
        and stop in place (see stop_in_place)."""
        if sight_lost:
            self.quick_stop_hold = True
        if self.error is None:
            log.error("%s (node %d): %s", self.name, self.node_id, text)
            self.error = text
        self.target_state = None
        self.stop_in_place()

    def stop_in_place(self) -> None:
        """Stop without a value the driver cannot vouch for: the halt bit in
        the profile modes and homing (the drive decelerates on its profile),
        and in the cyclic modes the last target the driver itself sent (CSP)
        or zero (CSV, CST). Power stays on."""
        self.halted = True
        self.command_kind = None
        self.command_value = math.nan
        self._ppm_pending = None
        mode = mode_of(self.active_mode)
        if mode is not None and mode.cyclic and mode.command_kind != "position":
            self._set_out(TARGET_OF_KIND[mode.command_kind], 0)

    def hold(self, raw_position: int) -> None:
        """Targets to 'stay where you are' at a position read by SDO: used
        before enabling and when switching modes, so nothing jumps."""
        self.command_kind = None
        self.command_value = math.nan
        for key, value in ((TARGET_POSITION, raw_position), (TARGET_VELOCITY, 0), (TARGET_TORQUE, 0)):
            self._set_out(key, value)
        self.command_raw = raw_position
        self._ppm_pending = raw_position if self.active_mode == PROFILE_POSITION.number else None

    # --------------------------------------------------------- watchdog
    def watch(self, now: float, cycle: int, period: float, pdo_timeout: float, pdo_cycles: int,
              reception: Optional[Tuple[float, float]] = None) -> None:
        """Heartbeat consumer, NMT state, boot-up and TxPDO watchdog for an
        enabled axis (monotonic time). ``reception``: the receive clock's
        progress (bus.ReceiveClock), when the latest frame read was read and
        when it arrived."""
        if not self.ready or not self.attached:
            return
        if self.rebooted:
            # A boot-up outweighs an error that came first (a rebooting
            # drive's heartbeat stops before it): the user must learn that
            # the position reference is gone.
            if not (self.error or "").startswith(_REBOOTED):
                self.error = None
                # no quick stop hold: a drive that really rebooted is in
                # Switch On Disabled, where enable operation does nothing,
                # and one a forged boot-up named is held where it is
                self.set_error(_REBOOTED + " (boot-up message received): its position reference and "
                               "configuration are lost")
            return
        if self.error:
            return
        if self.heartbeat_ms > 0 and self._heartbeat_missing(now, period, reception):
            self.nmt_state = "LOST"
            self.set_error("heartbeat lost: nothing for %.0f ms (0x1017 = %d ms)"
                           % ((now - self.last_heartbeat) * 1000, self.heartbeat_ms), sight_lost=True)
        elif self.nmt_state in ("STOPPED", "PRE-OPERATIONAL"):
            self.set_error("node left OPERATIONAL (heartbeat says %s)" % self.nmt_state, sight_lost=True)
        elif cycle - self.status_seen_cycle >= pdo_cycles and now - self.status_seen > pdo_timeout:
            # Counted in cycles too, so that a stall of this process (no
            # SYNC sent) is not taken for a silent drive.
            self.nmt_state = "LOST"
            self.set_error("no statusword TxPDO in %d cycles (%.0f ms)" % (
                cycle - self.status_seen_cycle, (now - self.status_seen) * 1000), sight_lost=True)

    def _heartbeat_missing(self, now: float, period: float, reception: Optional[Tuple[float, float]]) -> bool:
        """Nothing from the drive for 1.5 x 0x1017 + 2 cycles. Missing only
        once the driver has read a frame that arrived after the heartbeat
        was due (frames are read in the order they came), or has read
        nothing at all for as long: a heartbeat still waiting unread behind
        a stalled notifier is not a silent drive."""
        limit = 1.5 * self.heartbeat_ms / 1000.0 + 2 * period
        if now - self.last_heartbeat <= limit:
            return False
        return reception is None or reception[1] - self.last_heartbeat > limit or now - reception[0] > limit

    def _count(self, what: str, n: int = 1) -> None:
        self.counters[what] += n
        self._counters_view = None

    def on_heartbeat(self, data: bytes, now: float) -> None:
        if now < self._fresh_after:
            return  # from before the node was (re)configured: the boot-up of its reset
        if len(data) != 1:
            self._count("bad_heartbeat")
            return
        state = data[0] & 0x7F  # bit 7 is the toggle bit of node guarding
        name = NMT_NAMES.get(state)
        if name is None:
            self._count("undefined_nmt_state")
            return
        self.last_heartbeat = now
        self.nmt_state = name
        if state == 0 and self.ready:
            self.rebooted = True

    def on_emcy(self, data: bytes, now: float = 0.0) -> None:
        if len(data) < 3:
            self._count("bad_emcy")
            return
        code = data[0] | data[1] << 8
        self.error_register = data[2]
        if code == 0:
            if self._may_log_emcy(now):
                log.info("%s (node %d): EMCY error reset", self.name, self.node_id)
            return
        text = "%s (error register 0x%02X)" % (describe_error(code), data[2])
        if (text != self.last_emcy or now - self._emcy_logged > 1.0) and self._may_log_emcy(now):
            self._emcy_logged = now
            log.error("%s (node %d): EMCY %s", self.name, self.node_id, text)
        self.last_emcy = text

    def _may_log_emcy(self, now: float) -> bool:
        """A storm of EMCYs (a drive in trouble, or forged frames with every
        code) must not become a storm of log lines: they are written by the
        cycle thread, and a log line costs far more than a cycle. At most
        EMCY_LOG_LINES a second per axis; the others are counted."""
        if now - self._emcy_window >= 1.0:
            self._emcy_window = now
            self._emcy_lines = 0
        if self._emcy_lines >= EMCY_LOG_LINES:
            self._count("emcy_not_logged")
            return False
        self._emcy_lines += 1
        return True

    # --------------------------------------------------------- requests
    def request_state(self, state: Optional[State], fault_reset: bool = False) -> None:
        self.target_state = state
        self.fault_reset = fault_reset
        self.quick_stop_hold = False
        # Only a statusword that comes after the request confirms it: the
        # last one may be stale (a drive that left PDO exchange quick-stopped
        # meanwhile) and would end the request at once. "After" by when it
        # arrived, too: one read from a receive backlog may have arrived
        # seconds before the request.
        self._confirm_after = self.status_seen_cycle
        self._requested_at = time.monotonic()

    def mode_confirmed(self, number: int) -> None:
        """0x6061 read by SDO (modes display not mapped to a TPDO)."""
        if not self._display_mapped:
            self.mode_display = number

    def set_mode(self, number: int, raw_position: int) -> None:
        self.active_mode = number
        self._set_out(MODES_OF_OPERATION, number)
        self.hold(raw_position)

    def set_output(self, key: ObjectKey, value: int) -> None:
        """A value set_object wrote by SDO to an object an RxPDO carries: the
        PDO carries the new value from now on."""
        self._set_out(key, value)

    def _set_out(self, key: ObjectKey, value: int) -> None:
        """An object's value in every RxPDO that carries it (none: no-op)."""
        vals, dirty = self._out_vals, self._rx_dirty
        for i, j in self._out_at.get(key, ()):
            if vals[i][j] != value:
                vals[i][j] = value
                dirty[i] = True

    def _set_target(self, kind: str, value: int) -> None:
        """_set_out for a command kind's target object (positions worked out at attach)."""
        vals, dirty = self._out_vals, self._rx_dirty
        for i, j in self._target_out[kind]:
            if vals[i][j] != value:
                vals[i][j] = value
                dirty[i] = True

    def clear_error(self, statusword: int) -> None:
        """An error cleared (recover), ``statusword`` read over SDO just now.
        The statusword TPDO may be stale (a drive that left OPERATIONAL sent
        none): the state is unknown until a fresh one comes, and until then
        the controlword holds what the SDO answer shows."""
        self.error = None
        self.rebooted = False
        self.halted = False
        self.last_refusal = ""
        self.quick_stop_hold = False
        self.state = None
        self.held_state = None
        self._last_cw = holding_controlword(statusword)

    # --------------------------------------------------------- commands
    def apply_command(self, kind: str, value: float) -> Result:
        """A command from a controller, checked again now that it is applied."""
        mode = _mode_get(self.active_mode)
        # The common case decided in one expression: every condition of
        # command_problem holds. Anything else takes command_problem for
        # the reason (same checks, same order of messages).
        if not (type(value) is float and _isfinite(value) and mode is not None and mode.command_kind == kind
                and not self.error and self.ready and not self.halted and self.state is _ENABLED
                and not self.homing):
            problem = command_problem(self, kind, value)
        else:
            problem = None
        if problem:
            self._count("refused_commands")
            self.last_refusal = problem
            return fail(problem)
        value, clipped = saturate(self.limits, kind, float(value))
        if clipped:
            self._count("clipped_commands")
        raw, err = self.converter.convert(kind, value, self.env)
        if err:
            self._count("refused_commands")
            self.last_refusal = err
            return fail(err)
        self.command_kind = kind
        self.command_value = value
        self.command_raw = raw
        if mode is PROFILE_POSITION:
            self._ppm_pending = raw
        return ok("clipped to the joint limits (%s)" % self.limits.describe()) if clipped else OK

    # ------------------------------------------------------------ write
    def _controlword(self, mode: Any = None) -> int:
        """The next controlword; ``mode`` is mode_of(active_mode) (write has it)."""
        state = self.state
        target = self.target_state
        if state is None:
            return self._last_cw & ~cia402.CW_FAULT_RESET_BIT
        if target is not None and state != target:
            if state == State.FAULT:
                if not self.fault_reset:
                    return self._hold_cw()
                # Fault reset acts on the rising edge of bit 7.
                return 0 if self._last_cw & cia402.CW_FAULT_RESET_BIT else cia402.CW_FAULT_RESET
            cw = cia402.next_controlword(state, target)
            if cw is None:
                return self._last_cw & ~cia402.CW_FAULT_RESET_BIT
            if cw == cia402.CW_ENABLE_OPERATION and self.halted:
                cw |= cia402.CW_HALT
            return cw
        cw = self._hold_cw()
        if self.held_state is not _ENABLED or self.halted:
            return cw
        if mode is None:
            mode = _mode_get(self.active_mode)
        if mode is None or self.mode_display != mode.number:
            return cw
        if mode is HOMING:
            if self.homing:
                cw |= cia402.CW_HOMING_START
        elif mode is PROFILE_POSITION:
            cw |= self._ppm_bits()
        return cw

    def _hold_cw(self) -> int:
        if self.quick_stop_hold:
            # Enable operation would take Quick Stop Active back to
            # Operation Enabled (transition 16, quick stop options 5-8) and
            # Switched On to it, the moment the drive takes PDOs again; quick
            # stop is no transition in the states a drive stops in, and a
            # ramp to rest if it still runs unseen or a lying statusword hid
            # that it does. Never disable voltage: that coasts.
            return cia402.CW_QUICK_STOP
        held = self.held_state
        if held is _ENABLED:  # the running case, without hashing the enum
            return cia402.CW_ENABLE_OPERATION | cia402.CW_HALT if self.halted else cia402.CW_ENABLE_OPERATION
        cw = _HOLD.get(held, cia402.CW_DISABLE_VOLTAGE) if held is not None else self._last_cw & ~cia402.CW_FAULT_RESET_BIT
        if held == State.OPERATION_ENABLED and self.halted:
            cw |= cia402.CW_HALT
        return cw

    def _ppm_bits(self) -> int:
        """Profile position set-point handshake, change set immediately.

        The target goes out one cycle before the new set-point edge: a drive
        may apply the RPDO with the controlword before the one with 0x607A
        at the same SYNC, and would then take the old target.
        Stages: 0 idle, 3 target sent, 1 edge sent (wait for set-point
        acknowledge, statusword bit 12), 2 edge cleared (wait for ack to drop).
        """
        ack = self.statusword & cia402.SW_SET_POINT_ACKNOWLEDGE
        bits = cia402.CW_CHANGE_SET_IMMEDIATELY
        stage = self._ppm_stage
        if stage == 3:
            self._ppm_stage = 1
            return bits | cia402.CW_NEW_SET_POINT
        if stage == 1:
            if not ack:
                return bits | cia402.CW_NEW_SET_POINT
            self._ppm_stage = stage = 2
        if stage == 2:
            if ack:
                return bits
            self._ppm_stage = 0
        if self._ppm_pending is not None:
            self._set_out(TARGET_POSITION, self._ppm_pending)
            self._ppm_pending = None
            self._ppm_stage = 3
        return bits

    def write(self, send: Callable[[int, bytes], None]) -> None:
        """Fill the RxPDOs from this axis's own fields and send those that
        changed; the controlword PDO and the cyclic target's PDO go out
        every cycle."""
        mode = _mode_get(self.active_mode)
        cyclic_rx = -1
        if mode is not None:
            kind = mode.command_kind
            if mode.cyclic:
                if self.command_kind == kind and not self.halted:
                    if self.converter.dynamic[kind]:
                        raw, err = self.converter.convert(kind, self.command_value, self.env)
                        if err:
                            # An object the conversion reads changed: stop where
                            # we are rather than send garbage.
                            self.set_error(err)
                        else:
                            self.command_raw = raw
                    if not self.halted:
                        raw = self.command_raw
                        vals, dirty = self._out_vals, self._rx_dirty
                        for i, j in self._target_out[kind]:  # _set_target, inline: every cycle
                            if vals[i][j] != raw:
                                vals[i][j] = raw
                                dirty[i] = True
                cyclic_rx = self._cyclic_rx_of[kind]
            elif kind == "velocity" and self.command_kind == "velocity" and not self.halted:
                self._set_target("velocity", self.command_raw)
        if cyclic_rx >= 0 and self.target_state is None and self.held_state is _ENABLED \
                and self.state is not None and not self.halted:
            cw = cia402.CW_ENABLE_OPERATION  # what _controlword answers in a running cyclic mode
        else:
            cw = self._controlword(mode)
        vals, dirty = self._out_vals, self._rx_dirty
        for i, j in self._cw_out:
            if vals[i][j] != cw:
                vals[i][j] = cw
                dirty[i] = True
        self._last_cw = cw
        # The controlword PDO goes out every cycle, as with ros_canopen, so
        # drive and master stay in step even if a frame was lost; the cyclic
        # target's PDO too; the others when they change and every REFRESH
        # cycles. A PDO is packed again only when a value in it changed
        # (after a pack, the last frame sent holds exactly these values).
        self._tick += 1
        refresh = self._tick % REFRESH_CYCLES == 0
        last = self._rx_last
        cw_rx = self._cw_rx
        i = -1
        for cob_id, pack in self._rx_codec:
            i += 1
            if dirty[i]:
                data = pack(*vals[i])
                dirty[i] = False
                if data != last[i] or i == cw_rx or i == cyclic_rx or refresh:
                    last[i] = data
                    send(cob_id, data)
            elif i == cw_rx or i == cyclic_rx or refresh:
                send(cob_id, last[i])

    # --------------------------------------------------------- snapshot
    def snapshot(self) -> AxisSnapshot:
        # tuple.__new__ straight from the field values: what AxisSnapshot(...)
        # does, minus its Python-level __new__ (this runs per axis per cycle)
        return _tuple_new(AxisSnapshot, (
            self.name, self.node_id, self.key, self.position, self.velocity, self.effort, self.raw_position,
            self.statusword, self.state, self.mode_display, self.active_mode, self.nmt_state, self.error,
            self.halted, self.homing, self.ready, self.attached, self.target_state, self.held_state,
            self.last_emcy, self.error_register, self.heartbeat_ms, self.rebooted, self.command_kind,
            self.command_value, self.last_refusal,
            self._tx_keys, tuple(self._tx_vals),
            self._counters_view or self._counters(), self.limits, self.plan, self.status_seen_cycle))

    def _counters(self) -> Mapping[str, int]:
        view = self._counters_view
        if view is None:
            view = self._counters_view = MappingProxyType(dict(self.counters))
        return view


def initial_snapshot(cfg: NodeConfig, plan: NodePlan, limits: JointLimits) -> AxisSnapshot:
    """What status shows for an axis before the first init."""
    return AxisSnapshot(cfg.name, cfg.node_id, cfg.key, math.nan, math.nan, math.nan, 0, 0, None, 0, None,
                        "UNKNOWN", None, False, False, False, False, None, None, "", 0, 0, False, None, math.nan,
                        "", (), (), MappingProxyType({}), limits, plan, 0)


def env_for_check(snapshot: AxisSnapshot, initial_env: Mapping[str, float]) -> Dict[str, float]:
    """An environment for converting a command outside the cycle: the
    objects of the latest snapshot (plus those read by SDO at init)."""
    env: Dict[str, float] = dict(initial_env)
    for key, value in snapshot.readings.items():
        env[object_variable_name(key)] = value
    env["pos"], env["vel"], env["eff"] = snapshot.position, snapshot.velocity, snapshot.effort
    return env
