"""Bringing drives to rest and disabling them: through the cycle for the
drives it hears, over SDO for the others, each judged by the drive's own
SDO answers. Runs in the service holding the service lock.

Shutdown gives its steps a deadline (``until``, deadline.py): every SDO
transfer ends by it, and a wait for the cycle past it still lasts
``grace`` (its controlword goes out); what it cut short is noted on it."""
from __future__ import annotations

import logging
from typing import List, Optional, Sequence

from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from .. import cia402
from ..cia402 import State
from ..objects import ObjectKey
from .access import ObjectAccess
from .cycle import ControlCycle
from .deadline import Deadline, DeadlinePassed
from .inbox import StateRequest
from .modes import CONTROLWORD, STATUSWORD, VELOCITY_ACTUAL
from .nodes import InitError, NodeTable, StateTimeout, Timeouts, each_node_collect
from .plan import HEARTBEAT_CONSUMER_1

log = logging.getLogger("maxon_epos4_ros_canopen.driver")

QUICK_STOP_DECELERATION = ObjectKey(0x6085)
_STANDSTILL = 2  # |0x606C| at or below this is standing still
# Shutdown goes through the cycle for a drive whose statusword TxPDO came
# within this many cycles, over SDO for the others; and over SDO for one
# that has not taken quick stop or disable voltage (transitions a drive
# makes at once) this many cycles after the cycle asked it.
HEARD_CYCLES = 20
# A controlword through the cycle at or past shutdown's deadline is still
# waited for this many cycles (at least PDO_GRACE_MIN s): it goes out, and
# the drive can confirm it.
PDO_GRACE_CYCLES = 10
PDO_GRACE_MIN = 0.1


def _share(until: Optional[Deadline], ways: int) -> Optional[Deadline]:
    return None if until is None else until.share(ways)


class Stopping:
    """Quick stop, standstill and disable voltage (see the module's docstring)."""

    def __init__(self, nodes: NodeTable, access: ObjectAccess, cycle: ControlCycle, timeouts: Timeouts) -> None:
        self._nodes = nodes
        self._access = access
        self._cycle = cycle
        self._clock = cycle.clock
        self._timeouts = timeouts
        # s: see PDO_GRACE_CYCLES
        self.grace = max(PDO_GRACE_CYCLES * cycle.update_ms / 1000.0, PDO_GRACE_MIN)

    def pdo_wait(self, until: Optional[Deadline]) -> float:
        """How long a step through the cycle waits for the drives: the state
        timeout, and with a deadline the time left but at least ``grace``."""
        if until is None:
            return self._timeouts.state
        return min(self._timeouts.state, max(until.left(), self.grace))

    def _describe(self, name: str) -> str:
        return "%s (node %d)" % (name, self._nodes[name].cfg.node_id)

    def disable_all(self, names: Sequence[str]) -> List[str]:
        """Disable every node over SDO (no cycle runs): the problems."""
        _, errors = each_node_collect(self._nodes, names, lambda name: self.stop_and_disable(
            name, "disabling after the failed init"), self._clock)
        return [errors[n] for n in names if n in errors]

    def stop_and_disable_by_pdo(self, names: Sequence[str], until: Optional[Deadline] = None) -> List[str]:
        """Quick stop, standstill and disable voltage through the cycle; the
        names now in Switch On Disabled or Fault. The power goes off only
        once a drive's standstill is read over SDO (a TxPDO anyone could
        have sent proves nothing); one not confirmed is left to SDO (or, past
        ``until``, in quick stop)."""
        cycle = self._cycle
        snap = cycle.snapshot.axes
        enabled = [n for n in names if snap[n].state == State.OPERATION_ENABLED]
        err = cycle.go(enabled, State.QUICK_STOP_ACTIVE, stop_on_error=False, answer_cycles=HEARD_CYCLES,
                       timeout=self.pdo_wait(until))
        self._note_pdo_step(until, "quick stop through the cycle", err)
        snap = cycle.snapshot.axes
        # Braking, maybe: the drives quick-stopped just now (options 0-2 end
        # the quick stop in Switch On Disabled by themselves) and any drive
        # in Quick Stop Active already, which something else quick-stopped
        # (its quick stop input, another master, the driver's own hold) and
        # may still be on its ramp. Disable voltage before their standstill
        # would let them coast.
        stopping = [n for n in names if snap[n].state == State.QUICK_STOP_ACTIVE
                    or (n in enabled and snap[n].state == State.SWITCH_ON_DISABLED)]
        at_rest = self._wait_standstill(stopping, until)
        # disabled: those at rest, and those not driven when shutdown began
        # (Switched On and below)
        to_disable = [n for n in names if n in at_rest or (n not in enabled and n not in stopping)]
        live = [n for n in to_disable if snap[n].state not in (State.FAULT, None)]
        err = cycle.go(live, State.SWITCH_ON_DISABLED, stop_on_error=False, answer_cycles=HEARD_CYCLES,
                       timeout=self.pdo_wait(until))
        self._note_pdo_step(until, "disable voltage through the cycle", err)
        snap = cycle.snapshot.axes
        return [n for n in to_disable if snap[n].state in (State.SWITCH_ON_DISABLED, State.FAULT)]

    def _note_pdo_step(self, until: Optional[Deadline], step: str, err: Optional[str]) -> None:
        if err and until is not None and until.passed:
            until.note("%s: %s" % (step, err))

    def _wait_standstill(self, names: Sequence[str], until: Optional[Deadline] = None) -> List[str]:
        """Wait until each drive has stopped on its quick stop ramp (or left
        Quick Stop Active by itself at its end), at most the ramp's time
        from the velocity and 0x6085 (quick stop deceleration) plus a
        margin, all drives at once; the names confirmed at rest.
        With ``until`` each read gets its share of the time left: a drive
        that does not answer in its share is waited for no longer (it stays
        in quick stop) and leaves the others their turn."""
        deadline = self._clock.now()
        waiting: List[str] = []
        for i, name in enumerate(names):
            try:
                deadline = max(deadline, self._quick_stop_deadline(name, _share(until, len(names) - i)))
            except DeadlinePassed as e:
                until.note("%s: waiting for standstill: %s" % (self._describe(name), e))  # type: ignore[union-attr]
                continue
            except (SdoAbortedError, SdoCommunicationError):
                deadline = max(deadline, self._clock.now() + self._timeouts.state)
            waiting.append(name)
        if until is not None:
            deadline = min(deadline, until.at)
        at_rest: List[str] = []
        while waiting:
            round_names = list(waiting)
            for i, name in enumerate(round_names):
                if self._cycle.snapshot.axes[name].state == State.SWITCH_ON_DISABLED:
                    at_rest.append(name)  # the end of the ramp (options 0-2)
                    waiting.remove(name)
                    continue
                try:
                    velocity = int(self._access.upload(name, VELOCITY_ACTUAL, _share(until, len(round_names) - i)))
                    if abs(velocity) <= _STANDSTILL:
                        at_rest.append(name)
                        waiting.remove(name)
                except DeadlinePassed as e:
                    waiting.remove(name)
                    until.note("%s: waiting for standstill: %s" % (self._describe(name), e))  # type: ignore[union-attr]
                except (SdoAbortedError, SdoCommunicationError):
                    pass  # not known yet: asked again until the deadline
            if not waiting or self._clock.now() > deadline:
                break
            self._clock.sleep(0.02 if until is None else min(0.02, until.left()))
        if until is not None and until.passed:
            for name in waiting:
                until.note("%s: waiting for standstill (still moving or unconfirmed)" % self._describe(name))
        return at_rest

    def rest_before_hold(self, names: Sequence[str]) -> List[str]:
        """recover holds each drive at the position it reads next: wait
        until every drive the driver is not driving (not Operation Enabled,
        or halted, or in error: coasting unpowered, ramping on its quick
        stop or its halt) stands still, read over SDO, at most the state
        timeout. A position read while the shaft still turns would pull the
        drive back once enabled. The problems: drives still moving."""
        snap = self._cycle.snapshot.axes
        waiting = [n for n in names if snap[n].state != State.OPERATION_ENABLED or snap[n].halted or snap[n].error]
        deadline = self._clock.now() + self._timeouts.state
        velocity = {}
        while waiting:
            for name in list(waiting):
                velocity[name] = int(self._access.upload(name, VELOCITY_ACTUAL))
                if abs(velocity[name]) <= _STANDSTILL:
                    waiting.remove(name)
            if not waiting or self._clock.now() > deadline:
                break
            self._clock.sleep(0.02)
        return ["%s (node %d) still moves (0x606C = %d) after %g s: recover once it stands still"
                % (n, self._nodes[n].cfg.node_id, velocity[n], self._timeouts.state) for n in waiting]

    def stop_and_disable(self, name: str, why: str = "shutting down", until: Optional[Deadline] = None) -> None:
        """Shutdown of one drive, judged by its own SDO answers: quick stop,
        standstill, disable voltage. A drive that left OPERATIONAL by
        itself (its heartbeat consumer tripped, 0x1029) takes no RxPDO and
        sends no TxPDO, and a TxPDO anyone could have sent proves nothing:
        SDO reaches and answers in OPERATIONAL and PRE-OPERATIONAL alike.
        Each controlword goes to the cycle first, so the RxPDO carries the
        same command and none still on its way can undo it (enable
        operation takes Quick Stop Active back to Operation Enabled,
        transition 16). ``until``: the SDO transfers end by it (DeadlinePassed
        is reported like a missing answer, and noted on it)."""
        nid = self._nodes[name].cfg.node_id
        access = self._access
        step = "reading the statusword 0x6041"
        try:
            state = cia402.state_or_none(int(access.upload(name, STATUSWORD, until)))
            if state == State.OPERATION_ENABLED:
                step = "quick stop"
                self._command(name, State.QUICK_STOP_ACTIVE, cia402.CW_QUICK_STOP, until)
                state = State.QUICK_STOP_ACTIVE
            if state == State.QUICK_STOP_ACTIVE:
                # quick-stopped just now, or before by something else (its
                # heartbeat consumer, its quick stop input): it may still
                # brake, and without voltage it would coast
                step = "waiting for standstill"
                state = self._standstill(name, until)
            if state in (State.QUICK_STOP_ACTIVE, State.SWITCHED_ON, State.READY_TO_SWITCH_ON):
                step = "disable voltage"
                self._command(name, State.SWITCH_ON_DISABLED, cia402.CW_DISABLE_VOLTAGE, until)
                step = "confirming switch_on_disabled"
                access.await_value(name, STATUSWORD, lambda v: cia402.state_or_none(v) == State.SWITCH_ON_DISABLED,
                                   "statusword 0x6041 = 0x%%04X after %g s" % self._timeouts.state, until)
        except (SdoAbortedError, SdoCommunicationError, StateTimeout) as e:
            if isinstance(e, DeadlinePassed) and until is not None:
                until.note("%s (node %d): %s over SDO: %s" % (name, nid, why, step))
            raise InitError("%s (node %d): %s: %s: %s" % (name, nid, why, step, e)) from None

    def _command(self, name: str, state: State, controlword: int, until: Optional[Deadline] = None) -> None:
        """``controlword`` to the drive over SDO, once the cycle's RxPDO (if
        a cycle runs) carries it too."""
        cycle = self._cycle
        if cycle.thread is not None:
            after = cycle.post(StateRequest((name,), state, False))
            if not cycle.wait(lambda s: True, 1.0 if until is None else min(1.0, self.pdo_wait(until)), after):
                # a cycle that does not answer may still send what it holds
                # (enable operation) after this controlword: it sends nothing more
                log.error("%s: the control cycle did not take the %s request: silenced", name, state.value)
                cycle.silence()
        self._access.download(name, CONTROLWORD.index, 0, controlword.to_bytes(2, "little"), until)

    def _quick_stop_deadline(self, name: str, until: Optional[Deadline] = None) -> float:
        """When a drive's quick stop ramp must be done (monotonic): its time
        from 0x606C and 0x6085 read over SDO, plus a margin, at most the
        state timeout."""
        access = self._access
        velocity = abs(int(access.upload(name, VELOCITY_ACTUAL, until)))
        deceleration = int(access.upload(name, QUICK_STOP_DECELERATION, until)) if \
            QUICK_STOP_DECELERATION.index in self._nodes[name].od else 0
        ramp = velocity / deceleration if deceleration > 0 else self._timeouts.state
        return self._clock.now() + min(1.5 * ramp + 0.5, self._timeouts.state)

    def _standstill(self, name: str, until: Optional[Deadline] = None) -> Optional[State]:
        """Wait until the drive has stopped on its quick stop ramp (or left
        Quick Stop Active by itself at its end), at most the ramp's time
        from the velocity and 0x6085 (quick stop deceleration) plus a
        margin (and until ``until``); the state it is in then. Raises
        StateTimeout when it still moves (DeadlinePassed at ``until``)."""
        deadline = self._quick_stop_deadline(name, until)
        if until is not None:
            deadline = min(deadline, until.at)
        access = self._access
        while True:
            state = cia402.state_or_none(int(access.upload(name, STATUSWORD, until)))
            if state != State.QUICK_STOP_ACTIVE:
                return state
            velocity = int(access.upload(name, VELOCITY_ACTUAL, until))
            if abs(velocity) <= _STANDSTILL:
                return state
            if self._clock.now() > deadline:
                if until is not None and until.passed:
                    raise until.passed_error("still moving (0x606C = %d)" % velocity)
                raise StateTimeout("still moving (0x606C = %d) when the quick stop time ran out" % velocity)
            self._clock.sleep(0.02 if until is None else min(0.02, until.left()))

    def release_heartbeat_consumers(self, names: Sequence[str], until: Optional[Deadline] = None) -> None:
        """A drive disabled by shutdown need not watch the master any more:
        stop its heartbeat consumer so the master's heartbeat ending now is
        no fault (best effort; each drive its share of the time left)."""
        watching = [n for n in names if any(w.key == HEARTBEAT_CONSUMER_1 for w in self._nodes[n].plan.writes)]
        for i, name in enumerate(watching):
            if until is not None and until.passed:
                until.note("%s: releasing its heartbeat consumer (skipped)" % self._describe(name))
                continue
            try:
                self._access.download(name, HEARTBEAT_CONSUMER_1.index, HEARTBEAT_CONSUMER_1.subindex, bytes(4),
                                      _share(until, len(watching) - i))
            except Exception as e:
                if isinstance(e, DeadlinePassed) and until is not None:
                    until.note("%s: releasing its heartbeat consumer: %s" % (self._describe(name), e))
                log.warning("%s: heartbeat consumer left on: %s", name, e)
