"""Run many virtual EPOS4 nodes on one python-can bus, in one thread.

One loop receives frames, routes them by COB-ID to the nodes and advances
all nodes every ``tick`` seconds; SYNC advances them too before TPDOs are
sampled.  Calls from other threads (fault injection, inspection) go through
``call()`` so that only the loop thread ever touches a node or the bus.

On a stepped clock (clock.SteppedClock) there is no loop thread: the clock
delivers each frame to ``handle`` and runs the tick as a periodic event, on
the thread that advances its time.
"""
from __future__ import annotations

import logging
import os
import queue
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Optional, Set, Tuple, Union

import can
import canopen

from ..can_device import ArrivalClock, DeliveryDelay, max_receive_lag, open_device
from ..clock import Clock, Task
from .drive import VirtualEpos4
from .objects import initial_values, load_od
from ..rawcan import CAN_EFF_FLAG, CAN_ERR_FLAG, CAN_RTR_FLAG, RawSocketcan, socketcan_socket

log = logging.getLogger(__name__)
# A loop pass woken this much later than it asked to be was stalled (s).
STALL = 0.05


@dataclass
class NodeConfig:
    """One simulated node: id, its DCF/EDS and an optional hard stop (increments)."""

    node_id: int
    dcf: str
    hard_stop: Optional[Tuple[float, float]] = None


def parse_node_spec(spec: str) -> NodeConfig:
    """``ID:PATH`` or ``ID:PATH:MIN:MAX`` (hard stop in increments) -> NodeConfig."""
    parts = spec.split(":")
    try:
        node_id = int(parts[0], 0)
    except ValueError:
        raise ValueError("node spec %r: expected ID:PATH[:MIN:MAX]" % spec) from None
    if len(parts) not in (2, 4) or not parts[1]:
        raise ValueError("node spec %r: expected ID:PATH[:MIN:MAX]" % spec)
    if not 1 <= node_id <= 127:
        raise ValueError("node id %d outside 1..127" % node_id)
    hard_stop = None
    if len(parts) == 4:
        hard_stop = (float(parts[2]), float(parts[3]))
        if hard_stop[0] >= hard_stop[1]:
            raise ValueError("hard stop %r: MIN must be below MAX" % spec)
    return NodeConfig(node_id, parts[1], hard_stop)


class Simulator:
    """Virtual EPOS4 nodes on ``bus``."""

    def __init__(self, bus: can.BusABC, nodes: List[NodeConfig], tick: float = 0.005,
                 clock: Union[Callable[[], float], Clock] = time.monotonic, statistics: bool = False):
        """``clock``: a Clock (a stepped one runs the simulator on its
        events), or a function of the time (the loop thread runs on it).
        ``statistics``: keep ``busy_time`` and ``cpu_seconds`` (for
        benchmarks: they cost three clock reads a loop pass)."""
        ids = [n.node_id for n in nodes]
        if len(set(ids)) != len(ids):
            raise ValueError("node ids must be unique: %s" % ids)
        self.bus = bus
        # a SocketCAN bus is read and written on its socket directly (../rawcan.py)
        sock = socketcan_socket(bus)
        self._raw: Optional[RawSocketcan] = RawSocketcan(sock) if sock is not None else None
        self.tick_period = tick
        self.statistics = statistics
        self.scheduler: Optional[Clock] = clock if isinstance(clock, Clock) and clock.stepped else None
        if isinstance(clock, Clock):
            wall = clock.wall
            clock = clock.now
        else:
            wall = time.time
        self.clock = clock
        # When the frame being handled reached the host, on ``clock``; the
        # time now whenever no frame waits. The nodes' heartbeat consumers
        # run on it, so frames queued while this loop was starved (a loaded
        # host) count from when they came, as a real drive would see them.
        self.bus_time = clock()
        self._clock_read = self.bus_time  # the loop's latest reading of the clock at the end of a pass
        self._next_tick: Optional[float] = None  # when the loop ticks next (set when it starts)
        self._stood_still_for = 0.0  # how long the loop stood still, in all (see _bus_time_now)
        self._arrival = ArrivalClock(clock, max_receive_lag(bus), wall=wall)
        # when the socket was last found empty, and how late the kernel
        # makes frames readable: an empty socket proves bus time only up
        # to that delay before it was found empty
        self._empty_at = self.bus_time
        self._delivery = DeliveryDelay()
        self.frames_in = 0
        self.frames_out = 0
        # Loop passes that advanced the nodes on the clock (about one per
        # ``tick``). A pass first handles the frames queued for it (up to a
        # burst of 256), so once this grew by 2 the simulator has handled
        # what was queued when it was read; and it grows only while the
        # simulator runs and its time goes on. Tests wait on it, not sleep.
        self.ticks = 0
        self.busy_time = 0.0  # wall time of the loop passes' work (with ``statistics``)
        self.bus_error: Optional[str] = None  # why receiving fails, while it does
        self.send_error: Optional[str] = None  # why sending fails, while it does
        self.frames_lost = 0  # frames that could not be sent
        self.cpu_seconds = 0.0  # CPU time of the loop thread (with ``statistics``)
        self._cpu0 = 0.0
        self._calls: "queue.Queue[Tuple[Callable[[], Any], dict]]" = queue.Queue()
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._tick_task: Optional[Task] = None
        self._routes: Dict[int, List[VirtualEpos4]] = {}
        self._sync_routes: Dict[int, List[VirtualEpos4]] = {}
        # what each node is routed for now, and the nodes whose COB-IDs may
        # have changed since (see _rebuild_routes)
        self._routed: Dict[int, Tuple[Tuple[int, ...], int]] = {}
        self._changed: Set[int] = set()
        now = clock()
        self.nodes: Dict[int, VirtualEpos4] = {}
        # The nodes of one file share its object dictionary (types, limits);
        # each keeps its own power-on values, which $NODEID makes differ.
        shared_ods: Dict[str, canopen.ObjectDictionary] = {}
        for cfg in nodes:
            own = load_od(cfg.dcf, cfg.node_id)
            od = shared_ods.setdefault(os.path.realpath(cfg.dcf), own)
            self.nodes[cfg.node_id] = VirtualEpos4(
                cfg.node_id, od, self._transmit, now, hard_stop=cfg.hard_stop,
                on_routes_changed=lambda node_id=cfg.node_id: self._mark_routes(node_id),
                initial=None if od is own else initial_values(own), bus_time=self._bus_time_now)
        self._order = {node_id: i for i, node_id in enumerate(self.nodes)}
        self._routes_dirty = True

    # --------------------------------------------------------------- bus
    def _transmit(self, cob_id: int, data: bytes, remote: bool) -> None:
        try:
            if self._raw is not None and len(data) <= 8:
                try:
                    self._raw.send(cob_id, data, remote)
                except OSError as exc:  # as python-can reports it
                    raise can.CanOperationError("Failed to transmit: %s" % exc.strerror, exc.errno) from None
            else:
                self.bus.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False,
                                          is_remote_frame=remote, dlc=len(data) if not remote else 0))
            self.frames_out += 1
        except can.CanError as exc:  # bus full or down: the frame is lost, as on a real bus
            self.frames_lost += 1
            if self.send_error is None:
                log.warning("send 0x%03X failed: %s (further failures counted, not logged)", cob_id, exc)
            self.send_error = str(exc)
            return
        if self.send_error is not None:
            log.info("sending again; %d frames lost after: %s", self.frames_lost, self.send_error)
            self.send_error = None

    def _mark_routes(self, node_id: Optional[int] = None) -> None:
        """A node's COB-IDs may have changed (None: any node's)."""
        self._changed.update(self.nodes if node_id is None else (node_id,))
        self._routes_dirty = True

    def _rebuild_routes(self) -> None:
        """Route the changed nodes' COB-IDs anew. Only their own entries
        move: a master configuring 127 nodes writes thousands of PDO
        parameters, and routing all nodes again after each one would cost
        more than everything else the simulator does. Each COB-ID's nodes
        stay in node order (a SYNC's TPDOs go out in that order)."""
        changed, self._changed = self._changed, set()
        order = self._order
        for node_id in changed:
            node = self.nodes.get(node_id)
            if node is None:
                continue
            new = (tuple(node.cob_ids()), node.sync_cob)
            old = self._routed.get(node_id, ((), None))
            if new == old:
                continue
            for table, old_cobs, new_cobs in ((self._routes, old[0], new[0]),
                                              (self._sync_routes, () if old[1] is None else (old[1],), (new[1],))):
                for cob in set(old_cobs):
                    kept = [n for n in table[cob] if n is not node]
                    if kept:
                        table[cob] = kept
                    else:
                        del table[cob]
                for cob in new_cobs:
                    table.setdefault(cob, []).append(node)
                for cob in set(new_cobs):
                    table[cob].sort(key=lambda n: order[n.node_id])
            self._routed[node_id] = new
        self._routes_dirty = False

    def handle(self, msg: can.Message, now: float) -> None:
        """Route one received frame."""
        if msg.is_extended_id or msg.is_error_frame:
            return
        self._route(msg.arbitration_id, bytes(msg.data), msg.is_remote_frame, now)

    def _route(self, cob: int, data: bytes, remote: bool, now: float) -> None:
        """Route one received frame with an 11-bit identifier."""
        self.frames_in += 1
        if cob == 0x000:
            if len(data) == 2:
                for node in self.nodes.values():
                    if data[1] in (0, node.node_id):
                        node.on_nmt(data[0], now)
        elif cob in self._sync_routes:
            for node in self._sync_routes[cob]:
                node.on_sync(now)
        else:
            for node in self._routes.get(cob, ()):
                node.on_frame(cob, data, remote, now)
        if self._routes_dirty:
            self._rebuild_routes()

    def _bus_time_now(self) -> float:
        """The nodes' supervision clock: bus time without the time this
        loop stood still, which no frame could fill."""
        return self.bus_time - self._stood_still_for

    def _stood_still(self, late: float) -> bool:
        """Whether a clock reading ``late`` s after it was expected means
        the loop stood still; the time counts in ``_stood_still_for``."""
        if late <= STALL:
            return False
        self._stood_still_for += late
        return True

    # -------------------------------------------------------------- loop
    def _receive(self, timeout: float) -> Optional[Tuple[int, bytes, bool, float]]:
        """The next frame as (COB-ID, or -1 for a frame no node takes (an
        extended identifier, an error frame); data; remote; time stamp), or
        None after ``timeout`` s. An interface that is down (a cut bus)
        stops no drive's control loop: the drives go on moving, supervising
        and serving calls; the outage is logged once."""
        try:
            if self._raw is not None:
                try:
                    raw = self._raw.recv(timeout)
                except OSError as exc:  # as python-can reports it
                    raise can.CanOperationError("Failed to receive: %s" % exc.strerror, exc.errno) from None
                frame: Optional[Tuple[int, bytes, bool, float]] = None
                if raw is not None:
                    can_id, data, stamp = raw
                    frame = (-1 if can_id & (CAN_EFF_FLAG | CAN_ERR_FLAG) else can_id & 0x7FF,
                             data, bool(can_id & CAN_RTR_FLAG), stamp)
            else:
                msg = self.bus.recv(timeout=timeout)
                frame = None if msg is None else (
                    -1 if msg.is_extended_id or msg.is_error_frame else msg.arbitration_id,
                    bytes(msg.data), msg.is_remote_frame, msg.timestamp)
        except can.CanError as exc:
            if self.bus_error is None:
                log.warning("receiving: %s: the drives run on without the bus", exc)
            self.bus_error = str(exc)
            time.sleep(min(timeout, self.tick_period))
            return None
        if self.bus_error is not None:
            log.info("receiving again after: %s", self.bus_error)
            self.bus_error = None
        return frame

    def step(self, timeout: float) -> None:
        """Receive for up to ``timeout`` s, then tick if due (one loop pass).

        The clock is read when the receive returns and after each frame;
        again at the end only after a tick or calls (work that takes
        time), else the pass's last reading stands for its end and for the
        next pass's start (run() starts it at once). Where reading the clock
        is a system call (user-mode Linux: about 25 µs), readings are much
        of what a pass costs."""
        entered = self._clock_read
        due = entered + max(0.0, timeout)
        frame = self._receive(max(0.0, timeout))
        start = time.perf_counter() if self.statistics else 0.0
        now = self.clock()
        # This process (or the whole host) stood still: woken much later
        # than asked, or the clock jumped between two readings where no
        # wait was asked for (while handling a frame).
        # A frame the bus carried meanwhile may not have reached the socket
        # yet, and a producer on the same host stood still too; a real
        # drive never stalls, so the heartbeat consumers' clock leaves that
        # time out, and bus time waits for the next pass's frames.
        stalled = self._stood_still(now - due)
        if self._routes_dirty:
            self._rebuild_routes()
        burst = 0
        empty_at = now  # when the socket was found empty (this pass's receive found nothing)
        while frame is not None:  # drain a burst (RPDOs + SYNC) before ticking
            cob, data, remote, stamp = frame
            arrival = self._arrival.arrival(stamp, now)
            self._delivery.frame(arrival, self._empty_at, now)
            self.bus_time = max(self.bus_time, arrival)
            if cob >= 0:
                self._route(cob, data, remote, now)
            burst += 1
            frame = self._receive(0.0) if burst < 256 else None
            handled = empty_at = self.clock()
            stalled = self._stood_still(handled - now) or stalled
            if frame is not None:
                now = handled
        if burst < 256:
            self._empty_at = empty_at
            if not stalled:
                # the socket is empty: every frame sent up to the kernel's
                # delivery delay before is read, and the loop is up to date
                self.bus_time = max(self.bus_time, empty_at - self._delivery.delay(empty_at))
        last = empty_at  # the pass's latest clock reading
        if not self._calls.empty():
            while not self._calls.empty():
                fn, box = self._calls.get_nowait()
                try:
                    box["result"] = fn()
                except Exception as exc:  # returned to the caller, never kills the loop
                    box["error"] = exc
                box["done"].set()
            last = None
        if now >= self._next_tick:
            self._tick(now)
            self._next_tick = max(self._next_tick + self.tick_period, now)
            last = None
        if self.statistics:
            self.busy_time += time.perf_counter() - start
            self.cpu_seconds = time.thread_time() - self._cpu0
        self._clock_read = self.clock() if last is None else last

    def _tick(self, now: float) -> None:
        """Advance every node the clock has not advanced lately."""
        recent = now - 0.5 * self.tick_period  # nodes a SYNC just advanced can wait
        for node in self.nodes.values():
            if node.t < recent:
                node.tick(now)
        self.ticks += 1

    def _stepped_frame(self, msg: can.Message) -> None:
        """A frame the stepped clock delivers (stamped with its time)."""
        now = self.clock()
        if self._routes_dirty:
            self._rebuild_routes()
        self.bus_time = max(self.bus_time, now)
        try:
            self.handle(msg, now)
        except Exception:  # keep serving the other nodes, as the loop does
            log.exception("virtual EPOS4 frame error")

    def _stepped_tick(self) -> None:
        now = self.clock()
        self.bus_time = max(self.bus_time, now)
        try:
            self._tick(now)
        except Exception:
            log.exception("virtual EPOS4 tick error")

    def run(self, passes: Optional[int] = None) -> None:
        """Serve until stop() (blocks); with ``passes``, that many passes of
        the loop (a test that scripts the bus and the clock runs it so)."""
        if self._next_tick is None:
            self._next_tick = self._clock_read = self.clock()
            if self.statistics:
                self._cpu0 = time.thread_time()
            self._rebuild_routes()
        done = 0
        while not self._stop.is_set() and (passes is None or done < passes):
            done += 1
            try:
                self.step(self._next_tick - self._clock_read)
            except Exception:  # keep serving the other nodes
                log.exception("virtual EPOS4 loop error")

    def start(self) -> "Simulator":
        if self.scheduler is not None:
            self._rebuild_routes()
            self.scheduler.add_pump(self.bus, self._stepped_frame, "virtual_epos4")
            self._tick_task = self.scheduler.periodic("virtual_epos4", self.tick_period, self._stepped_tick)
            return self
        self._thread = threading.Thread(target=self.run, name="virtual_epos4", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        if self._tick_task is not None:
            self._tick_task.stop()
            self._tick_task = None
            self.scheduler.remove_pump(self.bus)
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None

    def call(self, fn: Callable[[], Any], timeout: float = 5.0) -> Any:
        """Run ``fn`` in the loop thread (or now, if no loop runs); return its result."""
        if self._thread is None or threading.current_thread() is self._thread:
            return fn()
        box: Dict[str, Any] = {"done": threading.Event()}
        self._calls.put((fn, box))
        if not box["done"].wait(timeout):
            raise TimeoutError("simulator loop did not answer")
        if "error" in box:
            raise box["error"]
        return box.get("result")

    def inject_fault(self, node_id: int, fault: str, error_code: int = 0,
                     duration: float = 0.0) -> str:
        """Fault injection for tests and the ROS service; raises ValueError on bad input."""
        node = self.nodes.get(node_id)
        if node is None:
            raise ValueError("no simulated node %d (have %s)" % (node_id, sorted(self.nodes)))
        return self.call(lambda: node.inject(fault, self.clock(), error_code, duration))

    def read(self, node_id: int, index: int, sub: int = 0) -> Any:
        """Value of an object of a node, read in the loop thread (for tests)."""
        return self.call(lambda: self.nodes[node_id].store.get(index, sub, None))


def open_bus(device: str) -> can.BusABC:
    """The bus of a ``bus/device`` string (can_device.py): ``vcan0``, ``virtual:NAME``,
    ``INTERFACE:CHANNEL``; a CanDeviceError naming the device when it cannot be opened."""
    return open_device(device)


def node_configs_from_param(value: Any, config_dir: str,
                            find_package: Optional[Callable[[str], str]] = None) -> List[NodeConfig]:
    """The ``nodes`` parameter of the ROS node as NodeConfigs.

    Either a string of ``ID:DCF[:MIN:MAX]`` separated by spaces (DCF relative
    to ``config_dir``) or a list of dicts ``{id, eds_file, eds_pkg?, hard_stop?}``
    (``eds_file`` relative to the package ``eds_pkg`` when given, else to
    ``config_dir``).  Raises ValueError with the offending entry.
    """
    import os

    def resolve(path: str, pkg: Optional[str] = None) -> str:
        if pkg:
            if find_package is None:
                raise ValueError("eds_pkg %r given but no package lookup available" % pkg)
            return os.path.join(find_package(pkg), path)
        return path if os.path.isabs(path) else os.path.join(config_dir, path)

    configs: List[NodeConfig] = []
    if isinstance(value, str):
        for spec in value.split():
            cfg = parse_node_spec(spec)
            cfg.dcf = resolve(cfg.dcf)
            configs.append(cfg)
    elif isinstance(value, list):
        for entry in value:
            if not isinstance(entry, dict) or "id" not in entry or "eds_file" not in entry:
                raise ValueError("nodes entry %r: expected {id, eds_file, eds_pkg?, hard_stop?}" % (entry,))
            node_id = entry["id"]
            if not isinstance(node_id, int) or not 1 <= node_id <= 127:
                raise ValueError("nodes entry %r: id must be an integer 1..127" % (entry,))
            hard_stop = entry.get("hard_stop")
            if hard_stop is not None:
                if (not isinstance(hard_stop, list) or len(hard_stop) != 2
                        or not all(isinstance(x, (int, float)) for x in hard_stop) or hard_stop[0] >= hard_stop[1]):
                    raise ValueError("nodes entry %r: hard_stop must be [min, max] with min < max" % (entry,))
                hard_stop = (float(hard_stop[0]), float(hard_stop[1]))
            configs.append(NodeConfig(node_id, resolve(str(entry["eds_file"]), entry.get("eds_pkg")), hard_stop))
    else:
        raise ValueError("nodes must be a string 'ID:DCF ...' or a list of {id, eds_file}")
    if not configs:
        raise ValueError("nodes is empty")
    for cfg in configs:
        if not os.path.isfile(cfg.dcf):
            raise ValueError("node %d: no such DCF/EDS file %s" % (cfg.node_id, cfg.dcf))
    return configs
