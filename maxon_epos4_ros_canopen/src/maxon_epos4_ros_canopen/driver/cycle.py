"""The control cycle and its inbox.

Who owns what, under the rule stated in driver/__init__.py (docs/driver.md
has the picture):

* The cycle thread runs every ``sync/update_ms``: at the top of each cycle
  it drains the inbox (commands, state requests from the services,
  heartbeats and EMCYs from the CAN notifier), reads the TPDO and SYNC
  frames waiting in its own receiver (cycle_reception.py), reads the
  latest TPDO frames, publishes an immutable snapshot, runs the cycle callbacks (the
  trajectory controller), and sends the RxPDOs and SYNC. It owns the axes
  and ``ControlCycle``'s cycle state: ``axes``/``axis``/``by_node_id``,
  ``cycle_no``, ``snapshot`` (published whole), ``overruns``,
  ``bus_error``, ``send_failures`` and the private fields of a cycle.
* The service holding the service lock owns the thread's handles
  (``thread``, ``_stalled``) and silences a cycle that does not
  answer (``_silenced``, under the send lock). ``inbox``, ``abort`` and
  ``_cond`` are thread-safe; ``callbacks`` is replaced whole.
* Service calls (lifecycle.py, access.py) run in their callers' threads, one
  state-changing service at a time under the service lock; they own the
  link (link.py), the SDO clients, the configuration caches, and talk to
  the axes only through the inbox, and wait on snapshots.
* canopen's notifier thread only hands frames over: heartbeats and EMCYs
  to the inbox, and TPDOs to the receiver's latest-frame slots on an
  adapter where the cycle has no receiver of its own.
* ``limits`` and ``initial_env`` are written by whoever sets them (a
  service, ``set_limits``) as whole immutable mappings; the cycle learns
  of new limits through the inbox.
* The SYNC producer is started and stopped by the service while no cycle
  runs, and by the cycle thread (``RestartSync``) while one does. The bus
  error and its failure count are the cycle's: recover asks the cycle to
  clear them (``ClearBusError``), and only a cycle whose frames went out
  does.

While no cycle runs (before init, after shutdown) the service holding the
service lock owns the axes; starting the cycle thread hands them over and
joining it hands them back. A cycle thread that does not end within the
join timeout keeps its axes: it is silenced (it sends nothing more, see
``silence``) and no new cycle starts until it has ended.
"""
from __future__ import annotations

import logging
import math
import queue
import threading
from types import MappingProxyType
from typing import Any, Callable, Dict, List, Mapping, NamedTuple, Optional, Sequence, Tuple

import can

from ..cia402 import State
from ..clock import Task
from ..limits import JointLimits
from ..result import Result, fail, ok
from . import realtime
from .axis import Axis
from .check import check_command
from .cycle_reception import CYCLE_TASK
from .snapshot import AxisSnapshot, env_for_check, initial_snapshot
from .inbox import (Attach, ClearBusError, ClearError, Command, Detach, Emcy, Heartbeat, Hold, Homing,
                    ModeConfirmed, Ready, RestartSync, SetHeartbeat, SetLimits, SetMode, SetOutput, ShuttingDown,
                    StateRequest, StopInPlace, Together)
from .link import Link
from .nodes import InitError, NodeTable, Timeouts

log = logging.getLogger("maxon_epos4_ros_canopen.driver")

PDO_MISSING_CYCLES = 50
WALL_OFFSET_REFRESH = 1.0  # s
BUS_ERROR_CYCLES = 10  # cycles in a row whose frames were refused: a bus error
# the states a request may still ask for once shutdown has begun (ShuttingDown)
_STOP_STATES = (State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED)
_get_ident = threading.get_ident
_tuple_new = tuple.__new__


class DriverSnapshot(NamedTuple):
    """Everything the other threads may know of the axes, as of one cycle."""
    cycle: int
    axes: Mapping[str, AxisSnapshot]
    bus_error: Optional[str]
    foreign_frames: int


class ControlCycle:
    """The cycle thread, the axes it owns and its inbox (see the module's
    docstring). ``owner`` is what the cycle callbacks are called with."""

    def __init__(self, owner: Any, nodes: NodeTable, link: Link, timeouts: Timeouts,
                 inbox: "queue.SimpleQueue[Any]") -> None:
        config = link.config
        self.clock = link.clock
        self._owner = owner
        self._nodes = nodes
        self._link = link
        self._timeouts = timeouts
        self.update_ms = config.sync.update_ms
        self._period = config.sync.update_ms / 1000.0
        # TxPDOs come every SYNC (or event period): 50 of them missing, and
        # at least 1.5 s, is an error.
        self._pdo_timeout = max(1.5, PDO_MISSING_CYCLES * max(config.sync.interval_ms,
                                                               config.sync.update_ms) / 1000.0)
        self.limits: Mapping[str, JointLimits] = MappingProxyType({name: JointLimits() for name in nodes})
        self.initial_env: Dict[str, Mapping[str, float]] = {name: {} for name in nodes}
        self.snapshot = DriverSnapshot(0, MappingProxyType(
            {name: initial_snapshot(node.cfg, node.plan, JointLimits()) for name, node in nodes.items()}),
            None, 0)
        self.inbox = inbox
        self._cond = threading.Condition()
        self._waiters = 0  # threads in wait (under _cond): the cycle notifies only when there are some
        self.callbacks: Tuple[Callable[[Any], None], ...] = ()
        self.thread: Optional[Task] = None  # the clock's periodic task that runs the cycle
        self.ident: Optional[int] = None
        self._stalled: Optional[Task] = None  # a cycle thread that did not stop in time
        # held while the cycle sends; silenced: this cycle thread sends nothing more
        self._send_lock = threading.Lock()
        self._silenced = False
        self.abort = threading.Event()  # close(): cut service waits short
        # owned by the cycle thread while it runs
        self.axes: List[Axis] = []
        self.axis: Dict[str, Axis] = {}
        self.by_node_id: Dict[int, Axis] = {}
        self.cycle_no = 0
        self.overruns = 0
        self.realtime: Optional[realtime.Outcome] = None  # what the cycle thread got at its start
        self.bus_error: Optional[str] = None
        self.send_failures = 0
        self._shutting_down = False  # ShuttingDown came: only stopping state requests are taken
        self._clear_bus_error = False  # recover asked: the next cycle whose frames go out clears bus_error
        self._send_error: Optional[BaseException] = None
        self._out_frames: Dict[int, can.Message] = {}  # COB-ID -> the message _send reuses
        # the clock's wall time minus its monotonic time, read again every second (where a
        # clock read is a system call, once a cycle would cost): stamps readings
        self._wall_offset = 0.0
        self._wall_offset_at = -WALL_OFFSET_REFRESH

    # ========================================================== commands
    def set_command(self, name: str, kind: str, value: Any) -> Result:
        """See Driver.set_command."""
        if _get_ident() == self.ident:
            # a cycle callback (the trajectory controller), every cycle for
            # every joint: the axis by its name first, the lookups after
            axis = self.axis.get(name)
            if axis is not None:
                return axis.apply_command(kind, value)
        n = self._nodes.name(name)
        if n is None:
            return self._nodes.unknown(name)
        if _get_ident() == self.ident:
            axis = self.axis.get(n)
            if axis is None:
                return fail("%s is not initialized: call init" % n)
            return axis.apply_command(kind, value)
        snapshot = self.snapshot
        snap = snapshot.axes[n]
        limits = self.limits[n]
        checked = check_command(snap, kind, value, limits, self._nodes[n].converter,
                                env_for_check(snap, self.initial_env[n]))
        if type(checked) is str:
            return fail(checked)
        if snapshot.bus_error is not None:
            # the joint's error may be cleared (recover) while frames still
            # do not go out: nothing would reach the drive
            return fail("%s is in error (bus error: %s): call recover" % (n, snapshot.bus_error))
        self.inbox.put(Command(n, checked))
        if checked.clipped:
            return ok("clipped to the joint limits (%s)" % limits.describe())
        return ok()

    def set_limits(self, name: str, limits: JointLimits) -> None:
        new = dict(self.limits)
        new[name] = limits
        self.limits = MappingProxyType(new)
        self.post(SetLimits(name, limits))

    # ============================================================ inbox
    def post(self, *messages: Any) -> int:
        """Send messages to the cycle; returns the cycle number after which
        a snapshot shows their effect (see wait)."""
        seq = self.cycle_no
        for m in messages:
            self.inbox.put(m)
        return seq

    def _drain(self) -> None:
        batch = []
        inbox = self.inbox
        while True:
            try:
                batch.append(inbox.get_nowait())
            except queue.Empty:
                break
        if not batch:
            return
        # The last command of a joint in this batch is the one that counts;
        # everything else is handled in the order it came.
        last_command: Dict[str, int] = {}
        for i, m in enumerate(batch):
            if type(m) is Command:
                last_command[m.axis] = i
        for i, m in enumerate(batch):
            try:
                if type(m) is Command:
                    if last_command[m.axis] == i:
                        axis = self.axis.get(m.axis)
                        if axis is not None:
                            axis.take(m.checked)
                    continue
                self._handle(m)
            except Exception:
                log.exception("driver: handling %r failed", m)

    def _handle(self, m: Any) -> None:
        kind = type(m)
        if kind is Heartbeat:
            axis = self.by_node_id.get(m.node_id)
            if axis is not None:
                axis.inputs.on_heartbeat(m.data, m.time, axis.ready)
        elif kind is Emcy:
            axis = self.by_node_id.get(m.node_id)
            if axis is not None:
                axis.inputs.on_emcy(m.data, m.time)
        elif kind is StateRequest:
            if self._shutting_down and m.state not in _STOP_STATES:
                log.warning("%s: request for %s ignored: shutdown has begun", ", ".join(m.axes),
                            m.state.value if m.state else "no state")
                return
            for name in m.axes:
                self.axis[name].request_state(m.state, m.fault_reset, self.clock.now())
        elif kind is ShuttingDown:
            self._shutting_down = True
        elif kind is StopInPlace:
            for name in m.axes:
                self.axis[name].stop_in_place()
        elif kind is Hold:
            self.axis[m.axis].hold(m.raw_position)
        elif kind is SetMode:
            self.axis[m.axis].set_mode(m.mode, m.raw_position)
        elif kind is ModeConfirmed:
            self.axis[m.axis].mode_confirmed(m.mode)
        elif kind is Homing:
            self.axis[m.axis].homing = m.on
        elif kind is Ready:
            for name in m.axes:
                self.axis[name].ready = m.ready
        elif kind is ClearError:
            axis = self.axis[m.axis]
            axis.clear_error(m.statusword, m.quick_stop_option)
            # the watchdogs start afresh: silence from before recover (a bus
            # that was down) is not news; silence after it trips them again
            axis.inputs.restart(self.clock.now())
            axis.hold(m.raw_position)
        elif kind is Together:
            for part in m.messages:
                self._handle(part)
        elif kind is Detach:
            self.axis[m.axis].detach()
        elif kind is Attach:
            self.axis[m.axis].attach(m.binding, self.cycle_no, self.clock.now())
        elif kind is SetOutput:
            self.axis[m.axis].set_output(m.key, m.value)
        elif kind is SetHeartbeat:
            self.axis[m.axis].inputs.set_heartbeat(m.ms, self.clock.now())
        elif kind is SetLimits:
            axis = self.axis.get(m.axis)
            if axis is not None:
                axis.limits = m.limits
        elif kind is ClearBusError:
            self.send_failures = 0
            self._clear_bus_error = self.bus_error is not None
        elif kind is RestartSync:
            if self._link.sync is not None:
                self._link.start_sync()

    # ======================================================= start/stop
    def publish(self, axes: Sequence[Axis]) -> None:
        """A snapshot of axes no cycle runs (the calling service owns them),
        numbered as a cycle, so that a service waiting for a cycle after its
        post is not answered by an older one."""
        self.cycle_no += 1
        self.snapshot = DriverSnapshot(self.cycle_no, MappingProxyType({a.name: a.snapshot() for a in axes}),
                                       self.bus_error, self._link.foreign_frames[0])

    @property
    def stalled(self) -> bool:
        """A cycle thread that did not stop within the join timeout still runs."""
        return self._stalled is not None and self._stalled.alive

    def start(self, axes: List[Axis]) -> None:
        if self.stalled:
            raise InitError("the control cycle of the last session has not ended yet")
        self._stalled = None
        self._silenced = False
        self._shutting_down = False  # a new session (no cycle thread runs yet)
        self._link.open_sync()
        self.axes = axes
        self.axis = {a.name: a for a in axes}
        self.by_node_id = {a.node_id: a for a in axes}
        # What a previous session left in the inbox (a request its cycle
        # never took, heartbeats from the configuration) must not act on
        # this one; joint limits are the axes' already.
        while True:
            try:
                self.inbox.get_nowait()
            except queue.Empty:
                break
        for axis in axes:
            axis.limits = self.limits[axis.name]
        reception = self._link.reception
        if reception is not None:
            # what came since the link opened, whole: the first cycle then
            # starts from the latest frames, not from a budget's worth of old ones
            reception.poll(self.clock.now(), limit=1 << 30)
        # the clock runs the cycle: a thread of its own (with its own stop
        # event, so a thread that ends late never takes a later start's
        # for its own), or a stepped clock's event
        self._next_t = self.clock.now()
        self.thread = self.clock.periodic(CYCLE_TASK, self._period, self._run_once,
                                          on_thread_start=self._on_thread_start)

    def stop(self, join_timeout: Optional[float] = None) -> bool:
        """Stop the cycle thread and SYNC; False when the thread did not
        end within the join timeout (``join_timeout``, at most the
        configured one): it is silenced then, and keeps its axes (the
        caller must not touch them) until it ends."""
        thread, self.thread = self.thread, None
        stopped = True
        wait = self._timeouts.cycle_join if join_timeout is None else min(join_timeout, self._timeouts.cycle_join)
        if thread is not None:
            thread.stop()
            if not thread.join(wait):
                log.error("driver cycle thread did not stop within %g s: it sends nothing more, and no "
                          "cycle starts before it has ended", wait)
                self.silence()
                self._stalled = thread
                stopped = False
        self.ident = None
        self._link.close_sync()
        with self._cond:
            self._cond.notify_all()
        return stopped

    def silence(self) -> None:
        """From now on the running cycle thread sends no RxPDO and no SYNC:
        for a cycle that does not answer, before the drives are stopped over
        SDO, so that no frame it held back (enable operation) can undo the
        stop. Taken under the send lock: once this returns no send of the
        cycle is under way (unless one has blocked for a second)."""
        got = self._send_lock.acquire(timeout=1.0)
        self._silenced = True
        if got:
            self._send_lock.release()
        else:
            log.error("driver cycle blocked in a send for 1 s; silenced")

    def _on_thread_start(self) -> None:
        """In the cycle's own thread, before its first cycle: SCHED_FIFO
        where permitted (a stepped clock has no thread of its own)."""
        self.realtime = realtime.apply(self._link.config.realtime)

    def _run_once(self) -> Optional[float]:
        """One cycle, and when the next one is due (the clock's periodic task)."""
        self.ident = threading.get_ident()
        period = self._period
        next_t = self._next_t
        self.cycle()
        now = self.clock.now()
        due = self._paced(now)
        if due is not None:
            # Late: finished after the SYNC that followed its due time (a
            # quarter period before it), so RxPDOs of its own, some or all,
            # missed their SYNC; one more for every SYNC period skipped.
            missed_sync = next_t + 0.75 * period
            if now > missed_sync:
                self.overruns += int((now - missed_sync) // period) + 1
            next_t = due
        else:
            next_t += period
            if next_t < now:
                self.overruns += 1
                next_t = now
        self._next_t = next_t
        return next_t

    def _paced(self, now: float) -> Optional[float]:
        """With kernel-timed SYNC in the cycle's period: when the next cycle
        is due, a quarter period after the next SYNC (the drives' TPDOs
        answering it are in, and the RxPDOs have time to land); else None.

        The next SYNC is counted from the latest one heard, not from the
        producer's start: Linux's broadcast manager arms each expiry from
        the moment the last one fired, so its SYNCs fall behind a fixed
        schedule by every expiry's latency, and a cycle on the schedule
        would drift through them (periods with two targets, or none)."""
        link = self._link
        sync = link.sync
        if not link.sync_paced or sync is None:
            return None
        period, first_at = sync.period, sync.first_at
        if not period or first_at is None:  # stopped meanwhile, by a stop whose join timed out
            return None
        receiver = link.receiver
        heard = receiver.last_sync_heard() if receiver is not None else -math.inf
        if heard >= first_at - 0.5 * period:  # one of this producer's SYNCs
            return heard + (math.floor((now - heard) / period) + 1.25) * period
        try:
            return sync.next_after(now) + 0.25 * period
        except (RuntimeError, TypeError):
            return None

    # ============================================================ cycle
    def cycle(self) -> None:
        """One control cycle: inbox, readings, snapshot, callbacks, RPDOs and
        SYNC. Never raises: a failing part is logged and the rest runs."""
        self.cycle_no = cycle_no = self.cycle_no + 1
        now = self.clock.now()
        self._send_error = None
        if not self.inbox.empty():  # the usual cycle has no message: no get/Empty round
            try:
                self._drain()
            except Exception:
                log.exception("driver inbox failed")
        link = self._link
        receiver = link.receiver
        own_receiver = link.reception
        if own_receiver is not None:
            own_receiver.poll(now)
        period, pdo_timeout = self._period, self._pdo_timeout
        reception = link.receive_clock.progress
        if now - self._wall_offset_at >= WALL_OFFSET_REFRESH:
            self._wall_offset_at = now
            self._wall_offset = self.clock.wall() - now
        wall_offset = self._wall_offset
        snaps = {}
        for axis in self.axes:
            try:
                if axis.attached:
                    axis.read(receiver, now, cycle_no, wall_offset)
                    axis.watch(now, cycle_no, period, pdo_timeout, PDO_MISSING_CYCLES, reception)
            except Exception:
                log.exception("%s: reading failed", axis.name)
            snaps[axis.name] = axis.snapshot()
        self.snapshot = _tuple_new(DriverSnapshot, (cycle_no, MappingProxyType(snaps), self.bus_error,
                                                    link.foreign_frames[0]))
        owner = self._owner
        for fn in self.callbacks:
            try:
                fn(owner)
            except Exception:
                log.exception("cycle callback %r failed", fn)
        send = self._send
        with self._send_lock:
            if not self._silenced:
                for axis in self.axes:
                    try:
                        if axis.attached:
                            axis.write(send)
                    except Exception:
                        log.exception("%s: writing failed", axis.name)
                if link.sync_in_cycle and link.sync is not None:
                    try:
                        if receiver is not None:
                            receiver.sync_sent(self.clock.now())  # the bus does not echo it back to the receiver
                        link.sync.send()
                    except (can.CanError, OSError) as e:
                        self._send_error = e
        if self._send_error is None:  # _watch_bus's usual answer, without the call
            self.send_failures = 0
            if self._clear_bus_error:
                self._clear_bus_error = False
                self.bus_error = None
        else:
            self._watch_bus()
        # wait counts itself in before it looks at the snapshot, so a
        # waiter that is not counted yet will see this cycle's snapshot.
        if self._waiters:
            with self._cond:
                self._cond.notify_all()

    def _send(self, cob_id: int, data: bytes) -> None:
        """An RxPDO from the cycle thread (the only caller). One can.Message
        per COB-ID is reused, its bytes overwritten, as SyncProducer does:
        python-can's send turns the message into a frame before it returns
        (the virtual bus copies it), and building a Message per frame was a
        large part of the cycle."""
        msg = self._out_frames.get(cob_id)
        if msg is None or len(msg.data) != len(data):
            msg = self._out_frames[cob_id] = can.Message(arbitration_id=cob_id, data=data, is_extended_id=False)
        else:
            msg.data[:] = data
        try:
            self._link.bus.send(msg)
        except (can.CanError, OSError) as e:
            self._send_error = e

    def _watch_bus(self) -> None:
        """Frames refused in BUS_ERROR_CYCLES cycles in a row are a bus
        error, for as long as they go on: a joint whose error recover
        cleared meanwhile is in error again."""
        e = self._send_error
        if e is None:
            self.send_failures = 0
            return
        self.send_failures += 1
        if self.send_failures < BUS_ERROR_CYCLES:
            return
        if self.send_failures == BUS_ERROR_CYCLES:
            log.error("CAN bus error in %d cycles in a row: %s", BUS_ERROR_CYCLES, e)
        self.bus_error = str(e)
        self._clear_bus_error = False
        for axis in self.axes:
            if axis.error is None:
                axis.set_error("bus error: %s" % e, sight_lost=True)

    # ============================================================= waits
    def wait(self, pred: Callable[[DriverSnapshot], bool], timeout: float, after: int = -1) -> bool:
        """Wait until a snapshot newer than cycle ``after`` satisfies pred."""
        clock = self.clock
        deadline = clock.now() + timeout

        def done() -> bool:
            snap = self.snapshot
            return snap.cycle > after and pred(snap)
        if clock.stepped:  # the cycle runs in this wait, on this thread
            return clock.wait_until(lambda: done() or self.thread is None or self.abort.is_set(),
                                    timeout) and done()
        with self._cond:
            self._waiters += 1
            try:
                while not done():
                    remaining = deadline - clock.now()
                    if remaining <= 0 or self.thread is None or self.abort.is_set():
                        return done()
                    self._cond.wait(min(remaining, 0.5))
            finally:
                self._waiters -= 1
        return True

    def wait_cycles(self, n: int) -> None:
        target = self.cycle_no + n
        self.wait(lambda s: s.cycle >= target, max(1.0, n * self.update_ms / 100.0))

    def go(self, names: Sequence[str], state: State, fault_reset: bool = False,
           timeout: Optional[float] = None, stop_on_error: bool = True,
           together: Sequence[Any] = (), answer_cycles: Optional[int] = None) -> Optional[str]:
        """Drive joints to a CiA 402 state through the cycle; an error text or
        None. ``together``: requests the cycle takes in the same breath.
        ``answer_cycles``, for a state the drive takes at once (no ramp
        before it): stop waiting for a drive whose statusword TxPDO has not
        come for that many cycles, or came that many cycles after the
        request without showing the state (a drive that takes no RxPDO)."""
        names = tuple(names)
        if not names:
            return None
        after = self.post(Together(tuple(together) + (StateRequest(names, state, fault_reset),)))

        def there(a: AxisSnapshot) -> bool:
            # on a statusword that came after the request, not a stale one
            return a.held_state == state and a.target_state is None and a.state == state and a.status_cycle > after

        def unanswered(s: DriverSnapshot, a: AxisSnapshot) -> bool:
            return answer_cycles is not None and (s.cycle - max(a.status_cycle, after) > answer_cycles
                                                  or a.status_cycle - after > answer_cycles)

        def settled(s: DriverSnapshot) -> bool:
            return all(there(s.axes[n]) or (stop_on_error and s.axes[n].error) or unanswered(s, s.axes[n])
                       for n in names)
        reached = self.wait(settled, timeout or self._timeouts.state, after)
        snap = self.snapshot
        problems = []
        for n in names:
            a = snap.axes[n]
            if there(a):
                continue
            if a.error and stop_on_error:
                return "%s: %s" % (n, a.error)
            problems.append("%s did not reach %s (state %s, statusword 0x%04X%s)" % (
                n, state.value, a.state.value if a.state else "unknown", a.statusword,
                ", last EMCY " + a.last_emcy if a.last_emcy else ""))
        if problems:
            return "; ".join(problems)
        return None if reached else "timeout waiting for %s" % state.value
