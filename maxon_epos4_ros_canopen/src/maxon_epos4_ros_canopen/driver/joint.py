"""One drive seen as a ROS joint: readings in ROS units, the command, and
the per-cycle CiA 402 work (controlword, mode handshakes, PDO values).

Everything a cycle needs is prepared in ``bind()`` at init: PDO variables,
the expression environment, which RPDOs carry what. ``read()`` and
``write()`` then only move numbers; they run in the driver's cycle thread
under the driver lock, as does ``set_command`` (from any thread).
"""
from __future__ import annotations

import logging
import math
import struct
import threading
from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Tuple

from .. import cia402
from ..cia402 import State
from ..config import NodeConfig, SWITCHING_STATES
from ..objects import ObjectKey
from ..units import object_variable_name
from .plan import (CONTROLWORD, MODES_DISPLAY, MODES_OF_OPERATION, NodePlan, POSITION_ACTUAL,
                   STATUSWORD, TARGET_POSITION, TARGET_TORQUE, TARGET_VELOCITY)
from .result import Result, fail, ok

log = logging.getLogger("maxon_epos4_ros_canopen.driver")

PPM, PVM, HM, CSP, CSV, CST = 1, 3, 6, 8, 9, 10
# Which command a mode takes, and the object it goes to.
MODE_COMMAND = {PPM: "position", CSP: "position", PVM: "velocity", CSV: "velocity", CST: "effort"}
CYCLIC_MODES = (CSP, CSV, CST)
COMMAND_KINDS = ("position", "velocity", "effort")
REFRESH_CYCLES = 50  # RxPDOs that did not change are sent again this often
_KIND_OBJECT = {"position": TARGET_POSITION, "velocity": TARGET_VELOCITY, "effort": TARGET_TORQUE}

# Controlword that keeps the drive in each state once it is there.
_HOLD = {
    State.SWITCH_ON_DISABLED: cia402.CW_DISABLE_VOLTAGE,
    State.READY_TO_SWITCH_ON: cia402.CW_SHUTDOWN,
    State.SWITCHED_ON: cia402.CW_SWITCH_ON,
    State.OPERATION_ENABLED: cia402.CW_ENABLE_OPERATION,
    State.QUICK_STOP_ACTIVE: cia402.CW_QUICK_STOP,
}
SWITCHING_STATE = {n: State(v) for n, v in SWITCHING_STATES.items()}


class _Field:
    """One PDO-mapped value, read and written straight in the PDO's bytes.

    canopen's PdoVariable.raw formats a log message and walks the bit
    offsets on every access; at 100 Hz per object per axis that is most of
    the cycle, so the cycle uses a struct prepared at init instead (and
    falls back to .raw for fields that are not whole bytes).
    """

    __slots__ = ("var", "map", "st", "off")

    def __init__(self, var: Any) -> None:
        self.var = var
        self.map = var.pdo_parent
        st = var.od.STRUCT_TYPES.get(var.od.data_type)
        if st is not None and var.offset % 8 == 0 and var.length == st.size * 8:
            self.st, self.off = st, var.offset // 8
        else:
            self.st, self.off = None, 0

    def get(self) -> Any:
        if self.st is not None:
            return self.st.unpack_from(self.map.data, self.off)[0]
        return self.var.raw

    def set(self, value: Any) -> None:
        if self.st is not None:
            self.st.pack_into(self.map.data, self.off, value)
        else:
            self.var.raw = value


@dataclass(frozen=True)
class JointLimits:
    """Command limits in ROS units (from the URDF); None: not limited."""
    lower: Optional[float] = None
    upper: Optional[float] = None
    velocity: Optional[float] = None
    effort: Optional[float] = None


class Joint:
    def __init__(self, cfg: NodeConfig, od: Any, plan: NodePlan) -> None:
        self.cfg = cfg
        self.name = cfg.name
        self.node_id = cfg.node_id
        self.od = od
        self.plan = plan
        self.node: Any = None           # canopen RemoteNode, set at init
        self.sdo_lock = threading.Lock()
        self.limits = JointLimits()
        self.switching_state = SWITCHING_STATE[cfg.switching_state]
        # readings (ROS units)
        self.position = math.nan
        self.velocity = math.nan
        self.effort = math.nan
        self.statusword = 0
        self.state: Optional[State] = None
        self.mode_display = 0
        self.raw_position = 0
        # node status
        self.nmt_state = "UNKNOWN"
        self.last_emcy = ""
        self.error_register = 0
        self.error: Optional[str] = None
        self.heartbeat_ms = 0
        self.last_heartbeat = 0.0
        self.rebooted = False
        # TxPDO watchdog: last statusword PDO timestamp seen, and when (cycle, time)
        self.pdo_seen_ts = 0.0
        self.pdo_seen_cycle = 0
        self.pdo_seen_time = 0.0
        # what the cycle works towards
        self.target_state: Optional[State] = None
        self._target_reached = False
        self.fault_reset = False        # allowed to reset a fault (recover/init only)
        self.active_mode: Optional[int] = None  # mode the driver switched to (None: none yet)
        self.requested_mode: Optional[int] = None  # asked for before init
        self.halted = False
        self.homing = False
        self.ready = False              # driver initialized and the joint enabled once
        self.configuring = False        # init/recover is (re)configuring it over SDO
        self._command_kind: Optional[str] = None
        self._command_value = math.nan
        self._command_raw = 0
        self._command_dynamic = False
        self._ppm_pending: Optional[int] = None
        self._ppm_stage = 0             # see _ppm_bits
        self._tick = 0
        self._last_cw = 0
        self.cache: Dict[ObjectKey, Any] = {}
        self._env: Dict[str, float] = {"pos": math.nan, "vel": math.nan, "eff": math.nan}
        self._tx: Dict[ObjectKey, Any] = {}
        self._rx: Dict[ObjectKey, Any] = {}
        self._rx_maps: List[Tuple[Any, bytes]] = []
        self._env_sources: List[Tuple[str, Any]] = []

    # ----------------------------------------------------------- binding
    def bind(self, node: Any) -> None:
        """Attach the configured canopen node and prepare the cycle's tables."""
        self.node = node
        self._tx = {}
        self._rx = {}
        maps = []
        for pdo_map in node.tpdo.map.values():
            if pdo_map.enabled:
                for var in pdo_map.map:
                    self._tx[ObjectKey(var.index, var.subindex)] = var
        for pdo_map in node.rpdo.map.values():
            if pdo_map.enabled and pdo_map.map:
                maps.append(pdo_map)
                for var in pdo_map.map:
                    self._rx[ObjectKey(var.index, var.subindex)] = var
        self._rx_maps = [(m, b"") for m in maps]
        self._sw = _Field(self._tx[STATUSWORD])
        self._mode_var = _Field(self._tx[MODES_DISPLAY])
        self._pos_var = _Field(self._tx[POSITION_ACTUAL])
        self._cw_var = _Field(self._rx[CONTROLWORD])
        self._mode_out = _Field(self._rx[MODES_OF_OPERATION])
        self._target = {k: _Field(self._rx[o]) for k, o in _KIND_OBJECT.items()}
        self._env_sources = []
        for expr in (self.cfg.pos_from_device, self.cfg.vel_from_device, self.cfg.eff_from_device,
                     self.cfg.pos_to_device, self.cfg.vel_to_device, self.cfg.eff_to_device):
            for key in expr.objects:
                name = object_variable_name(key)
                if key in self._tx and all(n != name for n, _ in self._env_sources):
                    self._env_sources.append((name, _Field(self._tx[key])))
                self._env.setdefault(name, math.nan)
        self._cyclic_map = {}
        for kind, field in self._target.items():
            self._cyclic_map[kind] = field.map

    def status_pdo_time(self) -> float:
        """When the TxPDO with the statusword last arrived (0: never)."""
        return self._sw.map.timestamp or 0.0

    def tx_var(self, key: ObjectKey) -> Any:
        return self._tx.get(key)

    def rx_var(self, key: ObjectKey) -> Any:
        return self._rx.get(key)

    def set_env(self, key: ObjectKey, value: float) -> None:
        """Value of an object a conversion uses that no TPDO carries (read by SDO)."""
        self._env[object_variable_name(key)] = float(value)

    # ------------------------------------------------------------ cycle
    def read(self) -> None:
        """Take the latest TPDO values; compute the state and ROS readings."""
        try:
            sw = self._sw.get()
            mode = self._mode_var.get()
            raw_position = self._pos_var.get()
            env = self._env
            for name, field in self._env_sources:
                env[name] = field.get()
        except struct.error:
            return  # a short PDO (corrupt frame): keep the last readings
        self.statusword = sw
        try:
            state = cia402.state_from_statusword(sw)
        except ValueError:
            state = self.state
        self.state = state
        self.mode_display = mode
        self.raw_position = raw_position
        env["pos"], env["vel"], env["eff"] = self.position, self.velocity, self.effort
        self.position = self.cfg.pos_from_device.evaluate(env)
        self.velocity = self.cfg.vel_from_device.evaluate(env)
        self.effort = self.cfg.eff_from_device.evaluate(env)
        self._supervise(state)

    def _supervise(self, state: Optional[State]) -> None:
        target = self.target_state
        if target is None or state is None:
            return
        if state == target:
            self._target_reached = True
            if state != State.FAULT:
                self.fault_reset = False
            return
        if self._target_reached:
            # The drive left the state on its own (fault, quick stop input...):
            # never drive it back automatically, that is recover's decision.
            what = "fault" if state in (State.FAULT, State.FAULT_REACTION_ACTIVE) else state.value
            self.set_error("drive left %s, now %s%s" % (
                target.value, what, (": " + self.last_emcy) if self.last_emcy and "fault" in what else ""))

    def set_error(self, text: str) -> None:
        if self.error is None:
            log.error("%s (node %d): %s", self.name, self.node_id, text)
        self.error = text
        self.target_state = None
        self._target_reached = False
        self._hold_position()
        self.halted = True

    def request_state(self, state: Optional[State], fault_reset: bool = False) -> None:
        self.target_state = state
        self._target_reached = False
        self.fault_reset = fault_reset

    def state_reached(self, state: State) -> bool:
        return self.state == state

    def _controlword(self) -> int:
        state = self.state
        target = self.target_state
        if state is None:
            return self._last_cw & ~cia402.CW_FAULT_RESET_BIT
        if target is not None and state != target:
            if state == State.FAULT:
                if not self.fault_reset:
                    return cia402.CW_DISABLE_VOLTAGE
                # Fault reset acts on the rising edge of bit 7.
                return 0 if self._last_cw & cia402.CW_FAULT_RESET_BIT else cia402.CW_FAULT_RESET
            cw = cia402.next_controlword(state, target)
            if cw is None:
                return self._last_cw & ~cia402.CW_FAULT_RESET_BIT
            if cw == cia402.CW_ENABLE_OPERATION and self.halted:
                cw |= cia402.CW_HALT
            return cw
        cw = _HOLD.get(state, cia402.CW_DISABLE_VOLTAGE)
        if state != State.OPERATION_ENABLED:
            return cw
        if self.halted:
            cw |= cia402.CW_HALT
        mode = self.mode_display
        if mode == HM:
            if self.homing:
                cw |= cia402.CW_HOMING_START
        elif mode == PPM:
            cw |= self._ppm_bits()
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
            self._target["position"].set(self._ppm_pending)
            self._ppm_pending = None
            self._ppm_stage = 3
        return bits

    def write(self, send: Any) -> None:
        """Fill the RPDOs and send those that changed (cyclic targets always)."""
        if self._command_dynamic and self._command_kind is not None and not self.halted:
            self._convert_command()
        if self.mode_display in CYCLIC_MODES and self._command_kind is not None and not self.halted:
            self._target[self._command_kind].set(self._command_raw)
        elif self.mode_display == PVM and self._command_kind == "velocity" and not self.halted:
            self._target["velocity"].set(self._command_raw)
        cw = self._controlword()
        self._cw_var.set(cw)
        self._last_cw = cw
        if self.active_mode is not None:
            self._mode_out.set(self.active_mode)
        cyclic = self._cyclic_map.get(MODE_COMMAND.get(self.mode_display, ""), None) \
            if self.mode_display in CYCLIC_MODES else None
        # The controlword PDO goes out every cycle, as with ros_canopen, so
        # drive and master stay in step even if a frame was lost (a receive
        # queue overflowing on a loaded drive or host); the cyclic target's
        # PDO too; the others when they change and every REFRESH cycles.
        self._tick += 1
        refresh = self._tick % REFRESH_CYCLES == 0
        cw_map = self._cw_var.map
        maps = self._rx_maps
        for i, (pdo_map, last) in enumerate(maps):
            data = bytes(pdo_map.data)
            if data != last or pdo_map is cyclic or pdo_map is cw_map or refresh:
                send(pdo_map.cob_id, data)
                maps[i] = (pdo_map, data)

    def resend_all(self) -> None:
        """Forget what was sent so the next cycle sends every RPDO again."""
        self._rx_maps = [(m, b"") for m, _ in self._rx_maps]

    # --------------------------------------------------------- commands
    def _hold_position(self) -> None:
        """Targets to 'stay where you are': actual position, zero velocity
        and torque; the active command is dropped."""
        self._command_kind = None
        self._command_value = math.nan
        self._command_dynamic = False
        if not self._rx:
            return
        self._target["position"].set(self.raw_position)
        self._target["velocity"].set(0)
        self._target["effort"].set(0)
        if self.mode_display == PPM or self.active_mode == PPM:
            self._ppm_pending = self.raw_position
        else:
            self._ppm_pending = None

    def reset_targets(self) -> None:
        """Targets to the actual position so that nothing jumps on enable."""
        self._hold_position()

    def check_command(self, kind: str, value: float) -> Optional[str]:
        if kind not in COMMAND_KINDS:
            return "unknown command kind %r (position, velocity, effort)" % kind
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            return "command must be a number"
        if not math.isfinite(value):
            return "%s command %r refused: not a finite number" % (kind, value)
        if self.error:
            return "%s is in error (%s): call recover" % (self.name, self.error)
        if not self.ready:
            return "%s is not initialized: call init" % self.name
        if self.halted:
            return "%s is halted: call recover before sending commands" % self.name
        if self.state != State.OPERATION_ENABLED:
            return "%s is not operation enabled (state %s)" % (
                self.name, self.state.value if self.state else "unknown")
        if self.homing:
            return "%s is homing" % self.name
        wanted = MODE_COMMAND.get(self.active_mode or 0)
        if wanted is None:
            return "%s has no mode for commands yet (start a controller)" % self.name
        if wanted != kind:
            return "%s is in mode %s, which takes %s commands, not %s" % (
                self.name, cia402.mode_name(self.active_mode), wanted, kind)
        lim = self.limits
        if kind == "position":
            if lim.lower is not None and value < lim.lower or lim.upper is not None and value > lim.upper:
                return "position %g outside the joint limits [%g, %g]" % (value, lim.lower, lim.upper)
        elif kind == "velocity":
            if lim.velocity is not None and abs(value) > lim.velocity:
                return "velocity %g beyond the joint's limit %g" % (value, lim.velocity)
        elif lim.effort is not None and abs(value) > lim.effort:
            return "effort %g beyond the joint's limit %g" % (value, lim.effort)
        return None

    def _to_device(self, kind: str, value: float) -> Tuple[Optional[int], Optional[str]]:
        expr = {"position": self.cfg.pos_to_device, "velocity": self.cfg.vel_to_device,
                "effort": self.cfg.eff_to_device}[kind]
        env = self._env
        env[{"position": "pos", "velocity": "vel", "effort": "eff"}[kind]] = value
        raw = expr.evaluate(env)
        if not math.isfinite(raw):
            return None, "%s %g converts to %r by %r: refused" % (kind, value, raw, expr.text)
        raw_int = int(round(raw))
        od = self._target[kind].var.od
        bits = len(od)
        lo, hi = -(1 << (bits - 1)), (1 << (bits - 1)) - 1
        if not lo <= raw_int <= hi:
            return None, "%s %g converts to %d, outside %s's range %d..%d" % (
                kind, value, raw_int, "0x%04X" % od.index, lo, hi)
        return raw_int, None

    def _convert_command(self) -> None:
        raw, err = self._to_device(self._command_kind, self._command_value)
        if err is None:
            self._command_raw = raw
        else:
            # The conversion went bad while running (an object it reads
            # changed): stop where we are rather than send garbage.
            self.set_error(err)

    def set_command(self, kind: str, value: float) -> Result:
        problem = self.check_command(kind, value)
        if problem:
            return fail(problem)
        raw, err = self._to_device(kind, float(value))
        if err:
            return fail(err)
        expr = {"position": self.cfg.pos_to_device, "velocity": self.cfg.vel_to_device,
                "effort": self.cfg.eff_to_device}[kind]
        self._command_kind = kind
        self._command_value = float(value)
        self._command_raw = raw
        self._command_dynamic = bool(expr.objects)
        if self.active_mode == PPM:
            self._ppm_pending = raw
        return ok()

    @property
    def command(self) -> Tuple[Optional[str], float]:
        return self._command_kind, self._command_value

    @property
    def mode(self) -> int:
        """The drive's mode of operation display (0x6061), for users."""
        return self.mode_display

    def mode_name(self) -> str:
        return cia402.mode_name(self.mode_display)
