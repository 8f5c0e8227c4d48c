"""A node's way from reset to Operation Enabled over SDO, before any cycle
drives it: NMT reset or pre-operational, the plan's writes and PDOs, the
initial values the cycle's first RxPDOs repeat, and the CiA 402 walk.

Runs in the service holding the service lock (one thread per node at
once); it shares no state with the cycle but the inital environment it
publishes whole per node (``ControlCycle.initial_env``)."""
from __future__ import annotations

from dataclasses import replace
from types import MappingProxyType
from typing import Dict, Optional, Tuple

from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from .. import cia402
from ..cia402 import State
from ..objects import ObjectKey, find_variable
from ..units import object_variable_name
from .access import ObjectAccess
from .axis import Binding, holding_controlword
from .cycle import ControlCycle
from .link import NMT_ENTER_PRE_OPERATIONAL, NMT_RESET_NODE, Link
from .modes import (CONTROLWORD, MODES_DISPLAY, MODES_OF_OPERATION, STATUSWORD, TARGET_POSITION, TARGET_TORQUE,
                    TARGET_VELOCITY)
from .nodes import InitError, NodeTable, StateTimeout, Timeouts
from .pdo import RxPdo, TxPdo, enabled_maps
from .plan import HOMING_METHOD, PRODUCER_HEARTBEAT, RPDO_COMM, RPDO_MAP, TPDO_COMM, TPDO_MAP

_PDO_NOT_VALID, _RTR_NOT_ALLOWED = 0x80000000, 0x40000000
# What init's enabling writes before the cycle starts, so the first RxPDOs
# hold the drive where it is: the targets (position: where it stands), and
# the controlword enable operation.
_HOLD_TARGETS = (TARGET_POSITION, TARGET_VELOCITY, TARGET_TORQUE)
_SET_BY_ENABLE = frozenset(_HOLD_TARGETS + (CONTROLWORD,))
# Controlwords init may write on the way to Operation Enabled: fault reset
# (two), shutdown, switch on, enable operation, and one fault on the way.
_ENABLE_STEPS = 8
COMMAND_NAMES = {cia402.CW_DISABLE_VOLTAGE: "disable voltage", cia402.CW_QUICK_STOP: "quick stop",
                 cia402.CW_SHUTDOWN: "shutdown", cia402.CW_SWITCH_ON: "switch on",
                 cia402.CW_ENABLE_OPERATION: "enable operation", cia402.CW_FAULT_RESET: "fault reset"}


class NodeSetup:
    """Configuration and enabling of one node over SDO."""

    def __init__(self, nodes: NodeTable, link: Link, access: ObjectAccess, cycle: ControlCycle,
                 timeouts: Timeouts) -> None:
        self._nodes = nodes
        self._link = link
        self._clock = link.clock
        self._access = access
        self._cycle = cycle
        self._timeouts = timeouts

    def configure(self, name: str, reset: bool = True, hold: bool = True) -> Binding:
        """NMT reset (init) or enter pre-operational (recover: a reset would
        lose the drive's position counter), then everything the plan says,
        over SDO. ``hold``: see ``_read_initial`` (init's ``enable`` sets
        what it leaves out)."""
        node = self._nodes[name]
        nid = node.cfg.node_id
        link = self._link
        if reset:
            boot = link.boot[nid]
            boot.clear()
            link.nmt(NMT_RESET_NODE, nid)
            if not self._clock.wait_event(boot, self._timeouts.boot):
                raise InitError("%s (node %d): no boot-up within %g s after NMT reset"
                                % (name, nid, self._timeouts.boot))
        else:
            link.nmt(NMT_ENTER_PRE_OPERATIONAL, nid)
        step = "configuration"
        try:
            for w in node.plan.writes:
                step = "writing " + w.text
                self._access.download(name, w.key.index, w.key.subindex, w.data)
            step = "writing the PDO mapping"
            self._write_pdos(name)
            step = "reading the initial values"
            return self._read_initial(name, hold)
        except SdoAbortedError as e:
            raise InitError("%s (node %d): %s failed: %s" % (name, nid, step, e)) from None
        except SdoCommunicationError as e:
            raise InitError("%s (node %d): no SDO answer during configuration (%s): %s"
                            % (name, nid, step, e)) from None

    def _write_pdos(self, name: str) -> None:
        """The plan's PDO configuration, in CiA 301's order: invalidate, clear
        the mapping, write it, count, transmission type, validate; a PDO the
        plan leaves off is only invalidated. (canopen's
        Map.save does the same but also subscribes the map to its COB-ID,
        which the driver must not do for RxPDOs.)"""
        plan = self._nodes[name].plan
        access = self._access
        for maps, comm_base, map_base, rx in ((plan.rx, RPDO_COMM, RPDO_MAP, True),
                                              (plan.tx, TPDO_COMM, TPDO_MAP, False)):
            for mp in maps:
                comm, mapping = comm_base + mp.number - 1, map_base + mp.number - 1
                rtr = 0 if rx or mp.rtr_allowed else _RTR_NOT_ALLOWED
                access.write_u32(name, comm, 1, mp.cob_id | _PDO_NOT_VALID | rtr)
                if not (mp.enabled and mp.entries):
                    # a PDO left invalid is neither sent nor received: its
                    # mapping and timing would be transfers for nothing
                    continue
                access.write_u8(name, mapping, 0, 0)
                for sub, (key, bits) in enumerate(mp.entries, start=1):
                    access.write_u32(name, mapping, sub, key.index << 16 | key.subindex << 8 | bits)
                access.write_u8(name, mapping, 0, len(mp.entries))
                access.write_u8(name, comm, 2, mp.trans_type)
                if mp.event_timer is not None:
                    access.download(name, comm, 5, int(mp.event_timer).to_bytes(2, "little"))
                access.write_u32(name, comm, 1, mp.cob_id | rtr)

    def _read_initial(self, name: str, hold: bool = True) -> Binding:
        """Codecs and first values: every RPDO value the drive has (known or
        read), so the first RPDOs repeat it (profile velocity...); the
        objects conversions read that no TPDO carries. With ``hold``, the
        controlword that holds the drive's state and its position too;
        without, the position and what ``enable`` sets (_SET_BY_ENABLE)
        are left to it: it reads the position and writes the others."""
        node = self._nodes[name]
        access = self._access
        rx = tuple(RxPdo(node.od, m) for m in enabled_maps(node.plan.rx))
        tx = tuple(TxPdo(node.od, m) for m in enabled_maps(node.plan.tx))
        initial_out: Dict[ObjectKey, int] = {}
        for rpdo in rx:
            for key in rpdo.keys:
                if not hold and key in _SET_BY_ENABLE:
                    continue
                if key == CONTROLWORD:
                    initial_out[key] = holding_controlword(int(access.upload(name, STATUSWORD)))
                else:
                    initial_out[key] = int(access.known(name, key))
        tx_keys = {k for t in tx for k in t.keys}
        env: Dict[str, float] = {}
        cfg = node.cfg
        for expr in (cfg.pos_from_device, cfg.vel_from_device, cfg.eff_from_device,
                     cfg.pos_to_device, cfg.vel_to_device, cfg.eff_to_device):
            for key in expr.objects:
                if key not in tx_keys:
                    env[object_variable_name(key)] = float(access.known(name, key))
        self._cycle.initial_env[name] = MappingProxyType(dict(env))
        heartbeat_ms = int(access.known(name, PRODUCER_HEARTBEAT)) if PRODUCER_HEARTBEAT.index in node.od else 0
        return Binding(rx, tx, MappingProxyType(initial_out), MappingProxyType(env),
                       access.position(name) if hold else 0, heartbeat_ms, self._clock.now())

    def prepare(self, name: str) -> Tuple[Binding, int]:
        """One node's configuration (reset, parameters, PDOs, initial values)
        and its homing method."""
        binding = self.configure(name, hold=False)
        if HOMING_METHOD.index not in self._nodes[name].od:
            return binding, 0
        try:
            return binding, int(self._access.known(name, HOMING_METHOD))
        except (SdoAbortedError, SdoCommunicationError) as e:
            raise InitError("%s (node %d): reading the homing method 0x6098 failed: %s"
                            % (name, self._nodes[name].cfg.node_id, e)) from None

    def enable(self, name: str, binding: Binding, mode: Optional[int]) -> Tuple[Binding, int]:
        """Operation Enabled over SDO, before NMT start: the mode (if one was
        requested) written and confirmed, the targets set to what the cycle's
        first RxPDOs will carry (the position just read, velocity and torque
        0), then the CiA 402 walk, each controlword confirmed by reading the
        statusword. The binding returned starts the RxPDOs there, with
        controlword enable operation; and the statusword read last."""
        node = self._nodes[name]
        nid = node.cfg.node_id
        access = self._access
        step = "reading the statusword 0x6041"
        try:
            statusword = int(access.upload(name, STATUSWORD))
            out = dict(binding.initial_out)
            if mode is not None:
                step = "writing modes of operation 0x6060 = %d" % mode
                access.download(name, MODES_OF_OPERATION.index, 0, mode.to_bytes(1, "little", signed=True))
                step = "confirming modes of operation display 0x6061 = %d" % mode
                access.await_value(name, MODES_DISPLAY, lambda v: v == mode,
                                   "modes of operation display 0x6061 = %%d, not %d" % mode)
                out[MODES_OF_OPERATION] = mode
            step = "reading the position actual value 0x6064"
            position = access.position(name)
            for key, value in zip(_HOLD_TARGETS, (position, 0, 0)):
                step = "writing %s = %d (hold)" % (key, value)
                access.download(name, key.index, key.subindex, find_variable(node.od, key).encode_raw(value))
                out[key] = value
            for _ in range(_ENABLE_STEPS):
                state = cia402.state_or_none(statusword)
                if state == State.OPERATION_ENABLED:
                    break
                if state == State.FAULT:
                    # fault reset acts on the rising edge of bit 7
                    commands: Tuple[int, ...] = (cia402.CW_DISABLE_VOLTAGE, cia402.CW_FAULT_RESET)
                else:
                    cw = cia402.next_controlword(state, State.OPERATION_ENABLED) if state is not None else None
                    commands = (cw,) if cw is not None else ()  # none: the drive moves on by itself
                for cw in commands:
                    step = "writing controlword 0x6040 = 0x%04X (%s)" % (cw, COMMAND_NAMES.get(cw, "?"))
                    access.download(name, CONTROLWORD.index, 0, cw.to_bytes(2, "little"))
                step = "waiting to leave %s%s" % (state.value if state else "0x%04X" % statusword,
                                                  " after " + step[8:] if commands else "")
                statusword = access.await_value(name, STATUSWORD, lambda v, s=state: cia402.state_or_none(v) != s,
                                                "statusword 0x6041 = 0x%04X")
            else:
                raise InitError("%s (node %d): not operation enabled after %d steps (0x6041 = 0x%04X)"
                                % (name, nid, _ENABLE_STEPS, statusword))
        except SdoAbortedError as e:
            raise InitError("%s (node %d): enabling: %s failed: %s" % (name, nid, step, e)) from None
        except SdoCommunicationError as e:
            raise InitError("%s (node %d): no SDO answer while enabling (%s): %s" % (name, nid, step, e)) from None
        except StateTimeout as e:
            raise InitError("%s (node %d): enabling: %s: still %s after %g s" % (name, nid, step, e,
                                                                                 self._timeouts.state)) from None
        out[CONTROLWORD] = cia402.CW_ENABLE_OPERATION
        return replace(binding, initial_out=MappingProxyType(out), raw_position=position), statusword
