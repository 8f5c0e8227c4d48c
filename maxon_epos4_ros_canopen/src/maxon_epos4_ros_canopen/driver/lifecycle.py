"""The driver's services that change the drives' state: init, recover,
halt, shutdown and switch_mode, one at a time (the service lock).

``Lifecycle`` owns ``initialized``, the requested modes and the service
lock; it reaches the drives over SDO (access.py, configure.py,
stopping.py) and the axes only through the cycle's inbox, waiting on its
snapshots (cycle.py states the ownership rule)."""
from __future__ import annotations

import logging
import threading
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

import can
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from .. import cia402
from ..cia402 import State
from ..result import Result, fail, ok
from .access import ObjectAccess
from .axis import SWITCHING_STATE, Axis, Binding
from .budget import check_budget
from .configure import NodeSetup
from .cycle import ControlCycle, DriverSnapshot
from .deadline import Deadline
from .inbox import (Attach, ClearBusError, ClearError, Detach, Hold, Homing, ModeConfirmed, Ready, RestartSync,
                    SetMode, ShuttingDown, StateRequest, StopInPlace)
from .link import NMT_START, NMT_STOP, Link
from .modes import (HOMING, MODES_DISPLAY, MODES_OF_OPERATION, QUICK_STOP_OPTION_CODE, STATUSWORD, mode_of,
                    supported_modes_text)
from .nodes import InitError, NodeTable, Timeouts, each_node, each_node_collect
from .plan import HOMING_METHOD, MODE_TARGETS
from .stopping import HEARD_CYCLES, Stopping

log = logging.getLogger("maxon_epos4_ros_canopen.driver")

# Shutdown's deadline keeps this many times the wait for a controlword
# through the cycle (Stopping.grace) for what runs after its SDO steps: the
# disable voltage through the cycle, two cycles for the drives stopped over
# SDO, stopping the cycle, NMT stop, closing the bus (at most half of it).
_TAIL_GRACES = 3


class Lifecycle:
    """init, recover, halt, shutdown, close and switch_mode (see the
    module's docstring)."""

    def __init__(self, nodes: NodeTable, link: Link, cycle: ControlCycle, access: ObjectAccess,
                 timeouts: Timeouts) -> None:
        self.config = link.config
        self._nodes = nodes
        self._link = link
        self._clock = link.clock
        self._cycle = cycle
        self._access = access
        self._timeouts = timeouts
        self._setup = NodeSetup(nodes, link, access, cycle, timeouts)
        self._stopping = Stopping(nodes, access, cycle, timeouts)
        self.service = threading.Lock()
        self.initialized = False
        self._tearing_down = False  # a teardown runs: close must not cut its waits short
        self._requested_modes: Dict[str, Optional[int]] = {name: None for name in nodes}

    # ============================================================== init
    def init(self) -> Result:
        """ros_canopen's init: reset, configure, start, home, enable."""
        if not self.service.acquire(blocking=False):
            return fail("another driver service is running")
        try:
            if self.initialized:
                return ok("already initialized")
            if self._cycle.stalled:
                return fail("the control cycle of the last session has not ended yet (it stalled): "
                            "init refused, so that two cycles never drive the drives")
            try:
                return self._init()
            except InitError as e:
                self._teardown()
                return fail(str(e))
            except Exception as e:  # never let a surprise kill the node
                log.exception("init failed")
                self._teardown()
                return fail("init failed: %s" % e)
        finally:
            self.service.release()

    def _init(self) -> Result:
        cycle, link = self._cycle, self._link
        cycle.bus_error = None
        cycle.send_failures = 0
        cycle.abort.clear()
        warning = check_budget(self.config, [node.plan for node in self._nodes.values()])
        if warning:
            log.warning("%s", warning)
        link.open()
        names = list(self._nodes)
        # Everything init needs from a node is read while it is configured,
        # all nodes at once; none is enabled unless every one is configured.
        prepared = each_node(self._nodes, names, self._setup.prepare, self._clock)
        # A mode requested before init is set before enabling; a node that
        # homes first gets it after homing, through the cycle, as before.
        modes = {name: None if prepared[name][1] else self._requested_modes[name] for name in names}
        enabled = self._enable_all(names, {name: prepared[name][0] for name in names}, modes)
        try:
            axes = []
            sync = self.config.sync
            # a drive applies cyclic targets at SYNC (at the cycle without one)
            target_period = (sync.interval_ms if sync.interval_ms > 0 else sync.update_ms) / 1000.0
            now = self._clock.now()
            for name in names:
                node = self._nodes[name]
                binding, statusword = enabled[name]
                axis = Axis(node.cfg, node.od, node.plan, cycle.limits[name], target_period)
                axis.active_mode = modes[name]
                axis.attach(binding, cycle.cycle_no, now)
                axis.enabled_over_sdo(statusword)
                axis.ready = True
                axes.append(axis)
            for axis in axes:
                link.nmt(NMT_START, axis.node_id)
            now = self._clock.now()
            for axis in axes:
                axis.inputs.restart(now)
            # The axes are this thread's until the cycle starts: their first
            # snapshot shows them enabled and ready without waiting for it.
            cycle.publish(axes)
            cycle.start(axes)
        except BaseException:
            if cycle.thread is None:  # no cycle to disable them: do it over SDO
                problems = self._stopping.disable_all(names)
                if problems:
                    log.error("init: %s", "; ".join(problems))
            raise
        for name in names:
            method = prepared[name][1]
            if method:
                r = self._home(name, method)
                if not r:
                    raise InitError(r.message)
                mode = self._requested_modes[name]
                if mode is not None:
                    r = self._switch(name, mode, force=True)
                    if not r:
                        raise InitError(r.message)
        self.initialized = True
        text = ", ".join("%s (node %d, PDOs from %s)" % (n, self._nodes[n].cfg.node_id, self._nodes[n].plan.source)
                         for n in names)
        return ok("initialized " + text)

    def _enable_all(self, names: Sequence[str], bindings: Mapping[str, Binding],
                    modes: Mapping[str, Optional[int]]) -> Dict[str, Tuple[Binding, int]]:
        """Every node to Operation Enabled over SDO, at once; when one fails,
        every node is disabled again before the error is raised."""
        results, errors = each_node_collect(self._nodes, names,
                                            lambda n: self._setup.enable(n, bindings[n], modes[n]), self._clock)
        if errors:
            problems = [errors[n] for n in names if n in errors]
            problems.extend(self._stopping.disable_all(names))
            raise InitError("; ".join(problems))
        return results

    def _home(self, name: str, method: int) -> Result:
        cycle = self._cycle
        r = self._switch(name, HOMING.number, force=True)
        if not r:
            return fail("homing of %s: %s" % (name, r.message))
        after = cycle.post(Homing(name, True))
        start = after + 3
        sw_done = cia402.SW_HOMING_ATTAINED | cia402.SW_TARGET_REACHED

        def finished(s: DriverSnapshot) -> bool:
            a = s.axes[name]
            if a.error:
                return True
            if s.cycle < start:
                return False
            return (a.statusword & sw_done) == sw_done or bool(a.statusword & cia402.SW_HOMING_ERROR)
        done = cycle.wait(finished, self._timeouts.homing, after)
        position = self._access.position(name)
        cycle.wait(lambda s: True, 1.0, cycle.post(Homing(name, False), Hold(name, position)))
        a = cycle.snapshot.axes[name]
        if a.error:
            return fail("homing of %s (method %d): %s" % (name, method, a.error))
        if a.statusword & cia402.SW_HOMING_ERROR:
            return fail("homing of %s (method %d) failed: homing error bit set%s" % (
                name, method, ", last EMCY " + a.last_emcy if a.last_emcy else ""))
        if not done:
            return fail("homing of %s (method %d) not finished within %g s" % (name, method,
                                                                              self._timeouts.homing))
        log.info("%s homed (method %d)", name, method)
        return ok()

    # ====================================================== mode switch
    def switch_mode(self, joint_names: Any, mode: Any) -> Result:
        """See Driver.switch_mode."""
        if isinstance(mode, bool) or not isinstance(mode, int) or mode_of(mode) is None:
            return fail("mode %r is not supported (supported: %s)" % (mode, supported_modes_text()))
        if isinstance(joint_names, str):
            joint_names = [joint_names]
        if not isinstance(joint_names, (list, tuple)) or not joint_names:
            return fail("joint_names must be a list of joint names, got %r" % (joint_names,))
        names = []
        for name in joint_names:
            n = self._nodes.name(name)
            if n is None:
                return self._nodes.unknown(name)
            plan = self._nodes[n].plan
            if not plan.supports(mode):
                return fail("%s cannot run mode %d (%s): its %s PDO layout carries no %s (layout modes: %s)" % (
                    n, mode, cia402.mode_name(mode), plan.source,
                    ", ".join(str(k) for k in MODE_TARGETS[mode]) or "controlword",
                    ", ".join(cia402.mode_name(m) for m in plan.modes) or "all"))
            names.append(n)
        if not self.initialized:
            for n in names:
                self._requested_modes[n] = mode
            return ok("mode %d will be set at init" % mode)
        for n in names:
            self._requested_modes[n] = mode
            r = self._switch(n, mode)
            if not r:
                return r
        return ok()

    def _switch(self, name: str, mode: int, force: bool = False) -> Result:
        try:
            return self._switch_steps(name, mode, force)
        except (SdoAbortedError, SdoCommunicationError) as e:
            return fail("mode switch of %s: %s" % (name, e))

    def _switch_steps(self, name: str, mode: int, force: bool) -> Result:
        cycle, access = self._cycle, self._access
        a = cycle.snapshot.axes[name]
        if a.error:
            return fail("%s is in error (%s): call recover" % (name, a.error))
        if not force and a.active_mode == mode and a.mode_display == mode and a.held_state == State.OPERATION_ENABLED:
            return self._hold_released(name, cycle.post(Hold(name, access.position(name))))
        position = access.position(name)
        cycle.post(Hold(name, position))
        node = self._nodes[name]
        err = cycle.go([name], SWITCHING_STATE[node.cfg.switching_state])
        if err:
            return fail("mode switch of %s: %s" % (name, err))
        # A drive that was turning (a velocity command) may still turn out of
        # Operation Enabled: the position the new mode holds is read once it
        # stands still, or the drive would pull back to where it was.
        moving = self._stopping.rest_before_hold([name])
        if moving:
            return fail("mode switch of %s: %s" % (name, "; ".join(moving)))
        position = access.position(name)
        cycle.post(SetMode(name, mode, position))
        if MODES_OF_OPERATION not in node.plan.rx_keys():
            access.download(name, MODES_OF_OPERATION.index, 0, mode.to_bytes(1, "little", signed=True))
        if MODES_DISPLAY in node.plan.tx_keys():
            confirmed = cycle.wait(lambda s: s.axes[name].mode_display == mode or bool(s.axes[name].error),
                                   self._timeouts.state)
        else:
            confirmed = int(access.upload(name, MODES_DISPLAY)) == mode
            if confirmed:
                cycle.post(ModeConfirmed(name, mode))
        a = cycle.snapshot.axes[name]
        if not confirmed or a.error:
            return fail("%s did not confirm mode %s (0x6061 = %d)" % (name, cia402.mode_name(mode), a.mode_display))
        after = cycle.post(Hold(name, access.position(name)))
        err = cycle.go([name], State.OPERATION_ENABLED)
        if err:
            return fail("mode switch of %s: %s" % (name, err))
        log.info("%s in mode %s", name, cia402.mode_name(mode))
        return self._hold_released(name, after)

    def _hold_released(self, name: str, after: int) -> Result:
        """Wait until the hold posted after cycle ``after`` let go of the
        halt bit. A hold goes out with it (Axis.hold), in profile position
        until the drive acknowledged the held set-point: a mode switch
        returns once a controlword without it went out, so the drive takes
        commands at once when the caller hears back. The snapshot after the
        one of the cycle that took the hold is the first to show the
        controlword that cycle sent. A halted axis keeps the bit (recover
        lets go of it)."""
        cycle = self._cycle

        def released(s: DriverSnapshot) -> bool:
            a = s.axes[name]
            return bool(a.error) or a.halted or not a.controlword & cia402.CW_HALT
        if not cycle.wait(released, self._timeouts.state, after + 1):
            return fail("mode switch of %s: the drive did not take the held position (halt bit still set after %g s)"
                        % (name, self._timeouts.state))
        a = cycle.snapshot.axes[name]
        return fail("%s is in error (%s): call recover" % (name, a.error)) if a.error else ok()

    # ================================================ halt/recover/shutdown
    def halt(self) -> Result:
        """See Driver.halt."""
        if not self.initialized:
            return fail("driver not initialized: call init")
        cycle = self._cycle
        names = tuple(self._nodes)
        snap = cycle.snapshot.axes
        quick = tuple(n for n in names if self._nodes[n].cfg.halt_mode == "quick_stop"
                      and snap[n].held_state == State.OPERATION_ENABLED and not snap[n].error)
        after = cycle.post(StopInPlace(names))
        if quick:
            after = cycle.post(StateRequest(quick, State.QUICK_STOP_ACTIVE))

            def stopping(s: DriverSnapshot) -> bool:
                return all(s.axes[n].error or (s.axes[n].target_state is None and s.axes[n].held_state in (
                    State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED)) for n in quick)
            if not cycle.wait(stopping, self._timeouts.state, after):
                return fail("halt: quick stop not confirmed by %s" % ", ".join(
                    n for n in quick if cycle.snapshot.axes[n].held_state != State.QUICK_STOP_ACTIVE))
        cycle.wait(lambda s: True, 1.0, after + 1)
        return ok("halted" + (" (quick stop)" if quick else ""))

    def recover(self) -> Result:
        """See Driver.recover."""
        if not self.service.acquire(blocking=False):
            return fail("another driver service is running")
        try:
            if not self.initialized:
                return fail("driver not initialized: call init")
            return self._recover()
        except (SdoAbortedError, SdoCommunicationError) as e:
            return fail("recover: %s" % e)
        except Exception as e:
            log.exception("recover failed")
            return fail("recover failed: %s" % e)
        finally:
            self.service.release()

    def _recover(self) -> Result:
        cycle, link, access = self._cycle, self._link, self._access
        names = list(self._nodes)
        # Restart the periodic senders: cheap, and afterwards they surely
        # run, whatever the bus did to them while it failed.
        if link.heartbeat is not None:
            link.heartbeat.stop()
            link.heartbeat.start()
            if cycle.snapshot.bus_error is not None:
                # The drives heard no master heartbeat while the bus failed:
                # their consumers may trip any moment now. Two heartbeat
                # periods after the restart each has heard one or tripped,
                # so the fault reset below comes after the trip, not before.
                self._clock.sleep(2 * link.heartbeat.period_s)
        # The cycle restarts the SYNC producer it sends with, and counts
        # send failures afresh: a bus still failing is a bus error again.
        after_bus = cycle.post(RestartSync(), ClearBusError())
        notes = []
        rehome = []
        reconfigured: List[str] = []
        for name in names:
            a = cycle.snapshot.axes[name]
            rebooted = a.rebooted and self._reboot_confirmed(name)
            if rebooted or a.nmt_state in ("STOPPED", "PRE-OPERATIONAL", "INITIALISING", "LOST"):
                # Configure the node again: one that rebooted lost its
                # configuration, and one that was silent or left OPERATIONAL
                # may have lost or been given another. Only a rebooted node
                # is reset: a reset restarts the position counter, and
                # pre-operational is enough to write the rest.
                cycle.wait(lambda s: not s.axes[name].attached, 2.0, cycle.post(Detach(name)))
                try:
                    binding = self._setup.configure(name, reset=rebooted)
                except InitError as e:
                    return fail("recover: %s" % e)
                link.nmt(NMT_START, self._nodes[name].cfg.node_id)
                cycle.post(Attach(name, binding))
                reconfigured.append(name)
                if rebooted:
                    # an incremental encoder restarts at 0: the position
                    # reference is gone, homing (if configured) finds it again
                    method = int(access.known(name, HOMING_METHOD)) if HOMING_METHOD.index in self._nodes[name].od \
                        else 0
                    if method:
                        rehome.append((name, method))
                    else:
                        notes.append("%s rebooted: its position reference is lost (no homing method configured)"
                                     % name)
        for name in names:
            if name not in reconfigured:
                # a drive whose 0x1017 is 0 says nothing of its NMT state: one
                # that left OPERATIONAL by itself (its communication error
                # behaviour, 0x1029) is started again; harmless otherwise
                link.nmt(NMT_START, self._nodes[name].cfg.node_id)
        # Each drive's state is read over SDO only once the controlword the
        # cycle holds it with (quick stop, for one it lost sight of) and a
        # SYNC after it went out since it was started: the drive answers in
        # the order frames came, so the answer shows that controlword's
        # effect, and no TxPDO the drive sent before it can come after the
        # request below and confirm a state the drive is about to leave.
        # The cycle that takes the attach sends it (in-cycle SYNC, or the
        # kernel's SYNC before the next cycle): two cycles on, it is out.
        if not cycle.wait(lambda s: True, self._timeouts.state, cycle.post() + 2):
            return fail("recover: the control cycle did not run for %g s" % self._timeouts.state)
        moving = self._stopping.rest_before_hold(names)
        if moving:
            return fail("recover: " + "; ".join(moving))
        clear = []
        for name in names:
            try:
                # 0x605A as the drive has it now (set_object may have changed
                # it): it decides the way out of Quick Stop Active
                option = int(access.upload(name, QUICK_STOP_OPTION_CODE)) \
                    if QUICK_STOP_OPTION_CODE.index in self._nodes[name].od else None
                clear.append(ClearError(name, access.position(name), int(access.upload(name, STATUSWORD)), option))
            except (SdoAbortedError, SdoCommunicationError) as e:
                return fail("recover: %s (node %d): reading its position, statusword and 0x605A: %s"
                            % (name, self._nodes[name].cfg.node_id, e))
        err = cycle.go(names, State.OPERATION_ENABLED, fault_reset=True, together=clear)
        if err:
            return fail("recover: " + err)
        cycle.wait(lambda s: True, 1.0, cycle.post(Ready(tuple(names), True)))
        for name, method in rehome:
            mode = cycle.snapshot.axes[name].active_mode
            r = self._home(name, method)
            if not r:
                return fail("recover: %s rebooted and lost its position reference; %s" % (name, r.message))
            notes.append("%s rebooted: homed again (method %d)" % (name, method))
            if mode is not None:
                r = self._switch(name, mode, force=True)
                if not r:
                    return fail("recover: " + r.message)
        for name in names:
            a = cycle.snapshot.axes[name]
            if a.active_mode is not None and a.mode_display != a.active_mode:
                r = self._switch(name, a.active_mode, force=True)
                if not r:
                    return fail("recover: " + r.message)
        cycle.wait_cycles(2)
        # frames going out again ends the bus error; frames still refused
        # make it a bus error again (and the joints with it)
        cycle.wait(lambda s: s.bus_error is None or any(a.error for a in s.axes.values()),
                   self._timeouts.state, after_bus)
        # a drive confirmed enabled above may have left it since (one still
        # finishing a quick stop it began by itself): not "recovered" then
        snap = cycle.snapshot
        again = ["%s: %s" % (n, snap.axes[n].error) for n in names if snap.axes[n].error]
        if again:
            return fail("recover: in error again before recover ended: " + "; ".join(again))
        if snap.bus_error is not None:
            return fail("recover: bus error: frames still refused (%s)" % snap.bus_error)
        return ok("recovered" + ("; " + "; ".join(notes) if notes else ""))

    def _reboot_confirmed(self, name: str) -> bool:
        """Whether a drive a boot-up (heartbeat 0x00) was heard from really
        rebooted. Anyone can send that frame; the drive's own SDO answer
        decides: a drive that rebooted is in Switch On Disabled (or Not Ready
        to Switch On, or Fault), never powered. One found powered did not
        reboot, and is neither reset (its position counter would restart)
        nor reported as rebooted."""
        try:
            statusword = int(self._access.upload(name, STATUSWORD))
        except (SdoAbortedError, SdoCommunicationError):
            return True  # no answer: booting, perhaps; configuring it anew is the way to a known state
        state = cia402.state_or_none(statusword)
        if state in (None, State.SWITCH_ON_DISABLED, State.NOT_READY_TO_SWITCH_ON, State.FAULT):
            return True
        log.warning("%s (node %d): a boot-up was heard, but the drive is %s (0x6041 = 0x%04X): not rebooted",
                    name, self._nodes[name].cfg.node_id, state.value, statusword)
        return False

    def shutdown(self) -> Result:
        """See Driver.shutdown."""
        with self.service:
            return self._shutdown(Deadline(self._clock, self._timeouts.shutdown))

    def _shutdown(self, deadline: Deadline) -> Result:
        if not self.initialized and self._link.network is None:
            return ok("driver was not initialized")
        problems = self._teardown(deadline)
        if problems:
            return fail("shut down with problems: " + "; ".join(problems))
        return ok("shut down")

    def _tail(self) -> float:
        """s of shutdown's deadline kept for its steps after the SDO ones."""
        return min(_TAIL_GRACES * self._stopping.grace, self._timeouts.shutdown / 2)

    def _teardown(self, deadline: Optional[Deadline] = None) -> List[str]:
        """Bring every drive the driver can reach to rest and disable it; a
        drive that does not answer does not keep the others running, and
        the whole ends by ``deadline`` (shutdown's, from now unless given):
        the SDO steps get only the time left before it (less the tail), the
        steps that stop drives by PDO and NMT and close the bus always run.
        The problems, the last naming the steps the deadline cut short."""
        if deadline is None:
            deadline = Deadline(self._clock, self._timeouts.shutdown)
        self._tearing_down = True
        try:
            return self._teardown_steps(deadline)
        finally:
            self._tearing_down = False

    def _teardown_steps(self, deadline: Deadline) -> List[str]:
        cycle, link, stopping = self._cycle, self._link, self._stopping
        # the waits of the stop itself must run, whoever asked for it (a
        # close that set the abort for the service this teardown ends)
        cycle.abort.clear()
        sdo_until = deadline.earlier(self._tail())
        problems: List[str] = []
        names = list(self._nodes)
        if cycle.thread is not None:
            snap = cycle.snapshot.axes
            cycle.post(ShuttingDown(), StopInPlace(tuple(names)))
            attached = [n for n in names if snap[n].attached]
            # The drives the cycle hears are stopped and disabled through it,
            # all at once; those it does not hear (a drive that left
            # OPERATIONAL by itself takes no RxPDO and sends no TxPDO) and
            # those it could not bring there, one by one over SDO.
            # Heard means statusword TxPDOs coming: a heartbeat's NMT state
            # (anyone can forge one) does not decide the way.
            now = cycle.snapshot.cycle
            heard = [n for n in attached if now - snap[n].status_cycle <= HEARD_CYCLES]
            done = stopping.stop_and_disable_by_pdo(heard, sdo_until)
            # released before the SDO way's drives take their turn: one of
            # them that does not answer then takes no time from these
            stopping.release_heartbeat_consumers(done, sdo_until)
            rest = [n for n in attached if n not in done]
            _, errors = each_node_collect(self._nodes, rest, lambda n: stopping.stop_and_disable(n, until=sdo_until),
                                          self._clock)
            if rest:
                # a drive still in OPERATIONAL then shows its last state on the bus too
                cycle.wait_cycles(2)
            problems.extend(errors[n] for n in rest if n in errors)
            stopping.release_heartbeat_consumers([n for n in rest if n not in errors], sdo_until)
        # a cycle thread that stalled must not hold the rest past the deadline for long
        stopped = cycle.stop(max(deadline.left(), 1.0))
        if stopped:
            # The cycle thread is gone: the axes are this thread's again.
            for axis in cycle.axes:
                axis.ready = False
                if axis.active_mode is not None:
                    self._requested_modes[axis.name] = axis.active_mode
        else:
            # A stalled cycle thread keeps its axes (silenced) until it ends.
            problems.append("the control cycle did not stop within %g s"
                            % min(max(deadline.left(), 1.0), self._timeouts.cycle_join))
            for name, a in cycle.snapshot.axes.items():
                if a.active_mode is not None:
                    self._requested_modes[name] = a.active_mode
        problems.extend(self._nmt_stop_all(stopped))
        if cycle.axes and stopped:
            cycle.publish(cycle.axes)
        link.close()
        self.initialized = False
        report = deadline.report()
        if report:
            log.warning("shutdown: %s", report)
            problems.append(report)
        return problems

    def _nmt_stop_all(self, stopped: bool) -> List[str]:
        """NMT stop to every node (the problems); the axes say STOPPED when
        ``stopped`` (the cycle thread is gone and they are this thread's)."""
        problems: List[str] = []
        link, cycle = self._link, self._cycle
        if link.network is None:
            return problems
        for node in self._nodes.values():
            try:
                link.nmt(NMT_STOP, node.cfg.node_id)
            except (can.CanError, OSError) as e:
                problems.append("NMT stop of %s: %s" % (node.cfg.name, e))
                continue
            axis = cycle.axis.get(node.cfg.name)
            if axis is not None and stopped:
                axis.inputs.nmt_state = "STOPPED"
        return problems

    def close(self) -> None:
        """See Driver.close: within the shutdown deadline from now, also
        when a service does not let go of the driver in time."""
        try:
            deadline = Deadline(self._clock, self._timeouts.shutdown)
            if not self._tearing_down:
                self._cycle.abort.set()  # a service still waiting (homing, a state) gives up
            # the wait for the service is part of the deadline: what follows keeps the tail
            if not self._clock.acquire(self.service, max(0.0, deadline.left() - self._tail())):
                self._stop_without_service(deadline)
                return
            try:
                self._cycle.abort.clear()  # shutdown's own waits (quick stop) must run
                if self.initialized or self._link.network is not None:
                    r = self._shutdown(deadline)
                    if not r:
                        log.error("close: %s", r.message)
            finally:
                self.service.release()
        except Exception:
            log.exception("close failed")

    def _stop_without_service(self, deadline: Deadline) -> None:
        """close() when a service held the driver until the deadline (an init
        stuck on a silent bus, say): what stops the drives runs without it.
        Quick stop through the cycle (a disable would need the standstill
        read over SDO, which the service may hold), the cycle stopped (the
        service's waits end at once), NMT stop to every node, the bus closed
        (its transfers fail and it ends)."""
        cycle, link = self._cycle, self._link
        names = tuple(self._nodes)
        done = []
        if cycle.thread is not None:
            snap = cycle.snapshot.axes
            quick = tuple(n for n in names if snap[n].held_state == State.OPERATION_ENABLED and snap[n].attached)
            cycle.post(ShuttingDown(), StopInPlace(names))
            if quick:
                cycle.post(StateRequest(quick, State.QUICK_STOP_ACTIVE))
            # the cycle's waits end at the abort the service got: a plain
            # sleep lets the controlword go out for a few cycles
            self._clock.sleep(self._stopping.grace)
            done.append("quick stop through the cycle" + (" (%s)" % ", ".join(quick) if quick else ""))
            stopped = cycle.stop(max(deadline.left(), 1.0))
            done.append("cycle stopped" if stopped else "cycle silenced (it did not stop)")
        problems = self._nmt_stop_all(False)
        if link.network is not None and not problems:
            done.append("NMT stop to every node")
        link.close()
        done.append("bus closed")
        deadline.note("waiting for the driver service that held it: standstill over SDO, disable voltage and "
                      "releasing the heartbeat consumers skipped")
        log.error("close: a driver service still held the driver at the %s: %s; %s",
                  deadline, ", ".join(done), "; ".join(problems + [deadline.report() or ""]))
