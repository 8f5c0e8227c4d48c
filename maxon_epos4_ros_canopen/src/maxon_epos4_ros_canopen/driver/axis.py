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
from typing import Any, Callable, Dict, Mapping, Optional, Tuple

from .. import cia402
from ..cia402 import State
from ..config_schema import SWITCHING_STATES, NodeConfig
from ..limits import JointLimits
from ..objects import ObjectKey
from ..result import OK, Result, fail, ok
from ..units import object_variable_name
from .check import Checked, check_command, state_problem
from .convert import Converter, FromDevice
from .inputs import Inputs
from .modes import (CONTROLWORD, MODES, MODES_DISPLAY, MODES_OF_OPERATION, Mode, POSITION_ACTUAL,
                    QUICK_STOP_OPTION_CODE, STATUSWORD)
from .outputs import Outputs
from .pdo import RxPdo, TpdoReceiver, TxPdo
from .plan import NodePlan
from .snapshot import AxisSnapshot, Counters

log = logging.getLogger("maxon_epos4_ros_canopen.driver")

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
# Transitions the drive makes by itself that are no error: the end of a
# quick stop ramp (option codes 1-4 end in Switch On Disabled).
_AUTOMATIC = {(State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED)}
_QUICK_STOPPED = (State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED)

# Bound once for the cycle's hot paths (a module global is one lookup, an
# enum member through its class several).
_ENABLED = State.OPERATION_ENABLED
_tuple_new = tuple.__new__
_CW_NO_FAULT_RESET = ~cia402.CW_FAULT_RESET_BIT


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
    """One drive's state; owned by the cycle thread. Its CiA 402 state work
    and commands are here; what the drive sends is taken in by its
    ``inputs`` (inputs.Inputs), what the driver sends goes out through its
    ``outputs`` (outputs.Outputs). Both belong to the axis alone."""

    # Slots: the cycle reads these for every axis every SYNC, and with this
    # many fields a slot is read faster than an instance dict's entry.
    __slots__ = ("cfg", "name", "node_id", "key", "od", "plan", "limits", "converter", "switching_state",
                 "quick_stop_option", "from_device", "counters", "inputs", "outputs", "_take_tpdos", "_silence",
                 "_send", "_readings", "position", "velocity", "effort", "raw_position", "statusword", "state",
                 "_seen_state", "mode_display", "env", "error", "target_state", "_confirm_after", "_requested_at",
                 "quick_stop_hold", "held_state", "fault_reset", "active_mode", "halted", "homing", "ready",
                 "attached", "command_kind", "command_value", "command_raw", "target_position", "last_refusal",
                 "_modes", "_settle", "_last_cw", "_sw_at", "_mode_at", "_pos_at", "_env_at", "_display_mapped",
                 "target_period")

    def __init__(self, cfg: NodeConfig, od: Any, plan: NodePlan, limits: JointLimits,
                 target_period: float = 0.0) -> None:
        """``target_period``: seconds from one cyclic target to the next as
        the drive applies them (the SYNC period; 0: unknown, and a CSP
        target is not limited by the joint's velocity)."""
        self.cfg = cfg
        self.target_period = target_period
        self.name = cfg.name
        self.node_id = cfg.node_id
        self.key = cfg.key
        self.od = od
        self.plan = plan
        self.limits = limits
        self.converter = Converter(cfg, od)
        self.switching_state = SWITCHING_STATE[cfg.switching_state]
        # 0x605A decides the way out of Quick Stop Active (cia402.next_controlword):
        # what init writes, until recover reads the drive's own value
        self.quick_stop_option: Optional[int] = plan.configured_value(od, QUICK_STOP_OPTION_CODE)
        self.from_device = FromDevice(cfg)
        self.counters = Counters()
        self.inputs = Inputs(self.name, self.node_id, self.counters)
        self.outputs = Outputs()
        # their methods the cycle calls for every axis, bound once
        self._take_tpdos, self._silence, self._send = self.inputs.take, self.inputs.silence, self.outputs.send
        self._readings = self.from_device.values
        # readings (ROS units) and what the drive reports
        self.position = math.nan
        self.velocity = math.nan
        self.effort = math.nan
        self.raw_position = 0
        self.statusword = 0
        self.state: Optional[State] = None
        # the last state a statusword showed (state is None again after
        # recover clears an error; this one only after a configuration)
        self._seen_state: Optional[State] = None
        self.mode_display = 0
        self.env: Dict[str, float] = {"pos": math.nan, "vel": math.nan, "eff": math.nan}
        self.error: Optional[str] = None
        # what the driver works towards
        self.target_state: Optional[State] = None
        self._confirm_after = 0  # inputs.status_seen_cycle when target_state was requested
        self._requested_at = 0.0  # monotonic time target_state was requested
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
        self.target_position = math.nan
        self.last_refusal = ""
        # this axis's own mode instances (the profile position handshake and
        # the homing bit are per drive); the one running is active_mode's
        self._modes: Dict[Optional[int], Mode] = {n: m.fresh() for n, m in MODES.items()}
        # Targets were set for holding this cycle: the controlword takes no
        # transition and keeps the halt bit until they went out (a drive may
        # apply the controlword's RPDO before the targets' at one SYNC).
        self._settle = False
        self._last_cw = 0
        # Where read finds what it interprets, worked out at attach: (TxPDO,
        # field) of the statusword, the modes display, the position, and of
        # each object a conversion reads.
        self._sw_at: Tuple[int, int] = (0, 0)
        self._mode_at: Optional[Tuple[int, int]] = None
        self._pos_at: Optional[Tuple[int, int]] = None
        self._env_at: Tuple[Tuple[str, int, int], ...] = ()
        self._display_mapped = True

    # ---------------------------------------------------------- binding
    def attach(self, binding: Binding, cycle: int, now: float) -> None:
        """Take a configured node's codecs and initial values; the drive's
        readings are unknown again until its TPDOs arrive."""
        self.outputs.bind(binding.rx, binding.initial_out)
        inputs = self.inputs
        inputs.bind(binding.tx, STATUSWORD, binding.configured_at, binding.heartbeat_ms, now, cycle)
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
        self.outputs.set(CONTROLWORD, first_cw)
        if self.active_mode is not None:
            self.outputs.set(MODES_OF_OPERATION, self.active_mode)
        in_at = inputs.at
        self._sw_at = in_at[STATUSWORD]
        self._mode_at = in_at.get(MODES_DISPLAY)
        self._pos_at = in_at.get(POSITION_ACTUAL)
        # A compact layout leaves modes of operation to SDO: the service that
        # switches modes confirms 0x6061 by SDO and tells the axis.
        self._display_mapped = self._mode_at is not None
        if not self._display_mapped:
            self.mode_display = 0  # unknown after a (re)configuration until confirmed
        names = []
        for expr in self.from_device.expressions + tuple(self.converter.expressions.values()):
            for key in expr.objects:
                names.append((object_variable_name(key), key))
        env_keys = tuple(dict(names).items())
        self._env_at = tuple((name, in_at[key][0], in_at[key][1]) for name, key in env_keys if key in in_at)
        for name, _ in env_keys:  # unknown (NaN) until a TPDO carries it
            self.env.setdefault(name, math.nan)
        self.env.update(binding.initial_env)
        self.raw_position = binding.raw_position
        self.state = self._seen_state = None
        self.statusword = 0
        self.target_state = None
        self.held_state = None
        self._last_cw = first_cw
        self.attached = True
        self.hold(binding.raw_position)
        # the first RxPDOs after a configuration carry every value anyway,
        # and no transition is asked yet: nothing to wait for
        self._settle = False

    def enabled_over_sdo(self, statusword: int) -> None:
        """The drive was brought to Operation Enabled over SDO before the
        cycle started (init), its statusword and, with a mode set, its 0x6061
        read back by SDO: the axis holds that state from its first RxPDO on,
        with the targets ``attach`` held."""
        self.statusword = statusword
        self._enabled()
        self.state = self.held_state = self._seen_state = State.OPERATION_ENABLED
        self.target_state = None
        self.fault_reset = False
        self._last_cw = cia402.CW_ENABLE_OPERATION
        self.outputs.set(CONTROLWORD, cia402.CW_ENABLE_OPERATION)
        if self.active_mode is not None:
            self.mode_display = self.active_mode

    def detach(self) -> None:
        """Stop touching the node (it is being configured over SDO)."""
        self.attached = False

    # ------------------------------------------------------------- read
    def read(self, receiver: TpdoReceiver, now: float, cycle: int, wall_offset: float = 0.0) -> None:
        """Take the TPDO frames that came since the last cycle (Inputs.take)
        and work out what they show; ``wall_offset``: time.time() minus
        time.monotonic(), for the readings' stamp."""
        vals = self._take_tpdos(receiver, now, cycle, wall_offset)
        si, sj = self._sw_at
        if vals[si] is None:
            return
        sw = vals[si][sj]
        if sw != self.statusword or self.state is None:
            try:
                state = cia402.state_from_statusword(sw)
            except ValueError:
                self.counters.add("undefined_statusword")
                state = self.state
            seen = self._seen_state
            if state is _ENABLED and seen is not None and seen is not _ENABLED:
                self._enabled()  # the drive came to Operation Enabled from another state
            if state is not None:
                self._seen_state = state
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
        self.position, self.velocity, self.effort = self._readings(env)
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
            inputs = self.inputs
            if (state == target and inputs.status_seen_cycle > self._confirm_after
                    and inputs.status_arrived > self._requested_at):
                self.target_state = None
                self.held_state = state
                if state != State.FAULT:
                    self.fault_reset = False
                return
            if state == State.FAULT and not self.fault_reset:
                self.set_error("drive is in fault%s" % self.inputs.emcy_suffix())
            return
        held = self.held_state
        if held is None or state == held:
            return
        if (held, state) in _AUTOMATIC or self.quick_stop_hold and self.halted and state in _QUICK_STOPPED:
            # the drive's own end of a quick stop, or the quick stop the
            # driver stopped it with (a cyclic mode's halt)
            self.held_state = state
            return
        # The drive left the state on its own (fault, quick stop input, or a
        # frame that lies): report it and stop with the drive's own means;
        # never cut the power of a drive that may be moving.
        what = "fault" if state in (State.FAULT, State.FAULT_REACTION_ACTIVE) else state.value
        if what != "fault":
            self.quick_stop_hold = True
        self.set_error("drive left %s, now %s%s" % (held.value, what, self.inputs.emcy_suffix() if what == "fault" else ""))

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
        """Stop the way the mode stops (modes.Mode.stop) without a value the
        driver cannot vouch for: the halt bit in the profile modes and
        homing (the drive decelerates on its profile), the drive's own quick
        stop in the cyclic modes (it ramps at 0x6085); the targets stay the
        last ones the driver itself sent. Power stays on."""
        self.halted = True
        self.command_kind = None
        self.command_value = math.nan
        mode = self._modes.get(self.active_mode)
        if mode is not None:
            mode.stop(self)

    def hold(self, raw_position: int) -> None:
        """Targets to 'stay where you are' at a position read by SDO: used
        before enabling and when switching modes, so nothing jumps. They go
        out in the next RxPDOs whether the driver sent the same values
        before or not (the drive may hold values someone else sent), before
        any controlword transition or release of the halt bit (_settle);
        in profile position a set-point of that position too."""
        self.command_kind = None
        self.command_value = math.nan
        for kind, value in (("position", raw_position), ("velocity", 0), ("effort", 0)):
            self.send_target(kind, value)
        self.command_raw = raw_position
        self._settle = True
        self.target_position = self.from_device.position_of(raw_position, self.env)
        mode = self._modes.get(self.active_mode)
        if mode is not None:
            mode.hold(self, raw_position)

    def _enabled(self) -> None:
        mode = self._modes.get(self.active_mode)
        if mode is not None:
            mode.enabled(self)

    # ---------------------------------------------------- what modes use
    def send_target(self, kind: str, value: int) -> None:
        """A command kind's target, sent in this cycle's RxPDOs whether it
        changed or not."""
        self.outputs.send_target(kind, value)

    def stop_with_quick_stop(self) -> None:
        """Hold the drive with quick stop until a state is requested."""
        self.quick_stop_hold = True

    # --------------------------------------------------------- watchdog
    def watch(self, now: float, cycle: int, period: float, pdo_timeout: float, pdo_cycles: int,
              reception: Optional[Tuple[float, float]] = None) -> None:
        """Heartbeat consumer, NMT state, boot-up and TxPDO watchdog for an
        enabled axis (monotonic time; see Inputs.silence for ``reception``)."""
        if not self.ready or not self.attached:
            return
        if self.inputs.rebooted:
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
        problem = self._silence(now, cycle, period, pdo_timeout, pdo_cycles, reception)
        if problem is not None:
            self.set_error(problem, sight_lost=True)

    # --------------------------------------------------------- requests
    def request_state(self, state: Optional[State], fault_reset: bool = False,
                      now: Optional[float] = None) -> None:
        """``now``: when it was requested, on the driver's clock (monotonic)."""
        self.target_state = state
        self.fault_reset = fault_reset
        self.quick_stop_hold = False
        # Only a statusword that comes after the request confirms it: the
        # last one may be stale (a drive that left PDO exchange quick-stopped
        # meanwhile) and would end the request at once. "After" by when it
        # arrived, too: one read from a receive backlog may have arrived
        # seconds before the request.
        self._confirm_after = self.inputs.status_seen_cycle
        self._requested_at = time.monotonic() if now is None else now

    def mode_confirmed(self, number: int) -> None:
        """0x6061 read by SDO (modes display not mapped to a TPDO)."""
        if not self._display_mapped:
            self.mode_display = number

    def set_mode(self, number: int, raw_position: int) -> None:
        self.active_mode = number
        self.outputs.set(MODES_OF_OPERATION, number)
        self.hold(raw_position)

    def set_output(self, key: ObjectKey, value: int) -> None:
        """A value set_object wrote by SDO to an object an RxPDO carries: the
        PDO carries the new value from now on."""
        self.outputs.set(key, value)

    def clear_error(self, statusword: int, quick_stop_option: Optional[int] = None) -> None:
        """An error cleared (recover), ``statusword`` and 0x605A read over SDO
        just now (None: not read). The statusword TPDO may be stale (a drive
        that left OPERATIONAL sent none): the state is unknown until a fresh
        one comes, and until then the controlword holds what the SDO answer
        shows."""
        if quick_stop_option is not None:
            self.quick_stop_option = quick_stop_option
        self.error = None
        self.inputs.rebooted = False
        self.halted = False
        self.last_refusal = ""
        self.quick_stop_hold = False
        self.state = None
        self.held_state = None
        self._last_cw = holding_controlword(statusword)

    # --------------------------------------------------------- commands
    def apply_command(self, kind: str, value: float) -> Result:
        """A command from a cycle callback, checked against the axis now."""
        checked = check_command(self, kind, value, self.limits, self.converter, self.env)
        if type(checked) is str:
            return self._refuse(checked)
        return self._take(checked)

    def take(self, checked: Checked) -> Result:
        """A command the caller's thread checked against a snapshot: taken
        unless the axis's state changed since (no second conversion)."""
        problem = state_problem(self, checked.kind)
        if problem:
            return self._refuse(problem)
        return self._take(checked)

    def _refuse(self, problem: str) -> Result:
        self.counters.add("refused_commands")
        self.last_refusal = problem
        return fail(problem)

    def _take(self, checked: Checked) -> Result:
        if checked.clipped:
            self.counters.add("clipped_commands")
        self.command_kind = checked.kind
        self.command_value = checked.value
        self.command_raw = checked.raw
        mode = self._modes.get(self.active_mode)
        if checked.kind == "position" and not (mode is not None and mode.cyclic and self._step_limited()):
            self.target_position = checked.value
        if mode is not None:
            mode.command(self, checked.raw)
        return ok("clipped to the joint limits (%s)" % self.limits.describe()) if checked.clipped else OK

    # ------------------------------------------------------------ write
    def _controlword(self, mode: Optional[Mode]) -> int:
        """The next controlword; ``mode`` is the running mode (write has it)."""
        state = self.state
        target = self.target_state
        if state is None:
            return self._last_cw & _CW_NO_FAULT_RESET
        if target is not None and state != target:
            if self._settle:
                return self._last_cw & _CW_NO_FAULT_RESET
            if state == State.FAULT:
                if not self.fault_reset:
                    return self._hold_cw()
                # Fault reset acts on the rising edge of bit 7.
                return 0 if self._last_cw & cia402.CW_FAULT_RESET_BIT else cia402.CW_FAULT_RESET
            cw = cia402.next_controlword(state, target, self.quick_stop_option)
            if cw is None:
                return self._last_cw & _CW_NO_FAULT_RESET
            if cw == cia402.CW_ENABLE_OPERATION and self._keeps_halt(mode):
                cw |= cia402.CW_HALT
            return cw
        cw = self._hold_cw()
        if cw != cia402.CW_ENABLE_OPERATION or mode is None or self.mode_display != mode.number:
            return cw
        return cw | mode.controlword_bits(self)

    def _keeps_halt(self, mode: Optional[Mode]) -> bool:
        """The halt bit stays set: halted, targets not yet out (_settle), or
        the mode not yet sure the drive holds the driver's own target."""
        return self.halted or self._settle or (mode is not None and mode.holding())

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
            if self.halted or self._settle:
                return cia402.CW_ENABLE_OPERATION | cia402.CW_HALT
            return cia402.CW_ENABLE_OPERATION
        if held is None:
            return self._last_cw & _CW_NO_FAULT_RESET
        return _HOLD.get(held, cia402.CW_DISABLE_VOLTAGE)

    def write(self, send: Callable[[int, bytes], None]) -> None:
        """Fill the RxPDOs from this axis's own fields and send them (see
        Outputs.send for which go out)."""
        mode = self._modes.get(self.active_mode)
        cyclic_rx = -1
        target_kind = None
        if mode is not None:
            kind = mode.command_kind
            if mode.cyclic:
                if self.command_kind == kind and not self.halted:
                    if kind == "position" and self.target_position != self.command_value:
                        self._step_position()
                    elif self.converter.dynamic[kind]:
                        raw, err = self.converter.convert(kind, self.command_value, self.env)
                        if err:
                            # An object the conversion reads changed: stop where
                            # we are rather than send garbage.
                            self.set_error(err)
                        else:
                            self.command_raw = raw
                    if not self.halted:
                        target_kind = kind
                cyclic_rx = self.outputs.cyclic_rx_of[kind]
        if cyclic_rx >= 0 and self.target_state is None and self.held_state is _ENABLED \
                and self.state is not None and not self.halted and not self._settle:
            cw = cia402.CW_ENABLE_OPERATION  # what _controlword answers in a running cyclic mode
        else:
            cw = self._controlword(mode)
        self._last_cw = cw
        self._settle = False
        self._send(send, cw, cyclic_rx, target_kind, self.command_raw)

    def _step_limited(self) -> bool:
        """Whether a CSP target moves toward a command in steps (the joint
        has a velocity limit, the period is known, and so is the target
        the drive holds now)."""
        return (self.limits.velocity is not None and self.target_period > 0.0
                and math.isfinite(self.target_position))

    def _step_position(self) -> None:
        """This SYNC's CSP target: the command, or as far toward it as the
        joint's velocity limit allows in one period. ros_canopen saturates
        a position command to that limit over the period too; in CSP the
        drive must reach each target within one SYNC, so a larger step
        (a command that jumps, a cycle a loaded host held up) would drive
        the joint faster than its limit."""
        goal = self.command_value
        if self._step_limited():
            here = self.target_position
            step = self.limits.velocity * self.target_period
            if goal - here > step:
                goal = here + step
            elif here - goal > step:
                goal = here - step
        raw, err = self.converter.convert("position", goal, self.env)
        if err:
            self.set_error(err)  # stop where we are rather than send garbage
            return
        self.target_position = goal
        self.command_raw = raw

    # --------------------------------------------------------- snapshot
    def snapshot(self) -> AxisSnapshot:
        # tuple.__new__ straight from the field values: what AxisSnapshot(...)
        # does, minus its Python-level __new__ (this runs per axis per cycle)
        inputs, counters = self.inputs, self.counters
        return _tuple_new(AxisSnapshot, (
            self.name, self.node_id, self.key, self.position, self.velocity, self.effort, self.raw_position,
            self.statusword, self.state, self.mode_display, self.active_mode, inputs.nmt_state, self.error,
            self.halted, self.homing, self.ready, self.attached, self.target_state, self.held_state,
            inputs.last_emcy, inputs.error_register, inputs.heartbeat_ms, inputs.rebooted, self.command_kind,
            self.command_value, self.last_refusal,
            inputs.keys, tuple(inputs.vals),
            counters.shown or counters.view(), self.limits, self.plan, inputs.status_seen_cycle, inputs.stamp,
            self.target_position, tuple(inputs.arrived), inputs.read_at, self._last_cw))
