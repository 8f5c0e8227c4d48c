"""Test support for this folder, written once: the clocks, the condition
wait, the frame recorder, a canopen client on a clock, and the simulator
rig (``sim_rig``). Tests run on a stepped clock (virtual time, one thread,
no outcome depending on thread scheduling) unless they prove real-time
threading; docs/testing.md lists those."""
import collections
import itertools
import math
import os
import threading
from typing import Any, Callable, Deque, Iterator, List, Optional

import can
import canopen
import pytest

from maxon_epos4_ros_canopen.clock import REAL, Clock, SteppedClock
from maxon_epos4_ros_canopen.driver.sdo import ClockedRemoteNode
from maxon_epos4_ros_canopen.cia402 import state_from_statusword
from maxon_epos4_ros_canopen.config import load_config
from maxon_epos4_ros_canopen.driver import Driver
from maxon_epos4_ros_canopen.objects import load_dictionary
from maxon_epos4_ros_canopen.sim import NodeConfig, Simulator

from driver_support import (CHANCE_CYCLES, DCF1, GENEROUS_MASTER_CONSUMER, J1, SEED_UNITS, SYNC_MS,
                            TIMEOUT)
from search_share import every_nth_parametrization

_channels = itertools.count()
# How long the test's own client waits for an SDO answer on the wall clock:
# canopen's 0.3 s is a drive's answer time, not how long a loaded host may
# leave the simulator's thread unscheduled. It only bounds a failure.
REAL_SDO_TIMEOUT = 5.0
_NODE1 = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
                      "config", "epos4_node1.dcf")


def pytest_collection_modifyitems(config: Any, items: List[Any]) -> None:
    """Under SEARCH_SHARE=N, each parametrized test takes one case in N, at
    least one (search_share.py)."""
    kept, left = every_nth_parametrization(items)
    if left:
        config.hook.pytest_deselected(items=left)
        items[:] = kept


def wait_on(clock: Clock, condition: Callable[[], bool], timeout: float = 10.0) -> bool:
    """Whether ``condition`` came to hold within ``timeout`` s of ``clock``
    (a stepped clock runs its events meanwhile; a real one polls)."""
    return clock.wait_until(condition, timeout)


class FrameRecorder:
    """Every frame another sender put on a virtual channel, with the
    clock's time it was seen; frames sent through ``bus`` itself are not
    recorded. On a stepped clock the clock's pump hands frames over; on
    the real clock a thread reads them."""

    def __init__(self, clock: Clock, channel: str) -> None:
        self.clock = clock
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.log: List[tuple] = []            # (time, frame) of every frame, for the whole run
        self._fresh: Deque[can.Message] = collections.deque()  # not yet taken
        self._lock = threading.Lock()
        self._run = True
        self._thread: Optional[threading.Thread] = None
        if clock.stepped:
            clock.add_pump(self.bus, self._seen)
        else:
            self._thread = threading.Thread(target=self._read, name="frame_recorder", daemon=True)
            self._thread.start()

    def _seen(self, msg: can.Message) -> None:
        with self._lock:
            self.log.append((self.clock.now(), msg))
            self._fresh.append(msg)

    def _read(self) -> None:
        while self._run:
            try:
                msg = self.bus.recv(timeout=0.05)
            except (can.CanError, OSError, ValueError):
                return
            if msg is not None:
                self._seen(msg)

    def take(self) -> List[can.Message]:
        """The frames seen since the last take (every frame, on the stepped
        clock; those the reader thread got to, on the real one)."""
        if self.clock.stepped:
            self.clock.deliver()
        with self._lock:
            frames = list(self._fresh)
            self._fresh.clear()
        return frames

    def next(self, timeout: float) -> Optional[can.Message]:
        """The next frame not taken yet, waiting up to ``timeout`` s."""
        if not wait_on(self.clock, lambda: bool(self._fresh), timeout):
            return None
        with self._lock:
            return self._fresh.popleft()

    def expect(self, match: Callable[[can.Message], bool], timeout: float = 5.0) -> Optional[can.Message]:
        """The first frame not taken yet that satisfies ``match`` (frames
        before it are taken too), or None after ``timeout`` s."""
        end = self.clock.now() + timeout
        while True:
            msg = self.next(max(0.0, end - self.clock.now()))
            if msg is None:
                return None
            if match(msg):
                return msg

    def text(self) -> bytes:
        """The log as bytes, one line per frame: time, COB-ID, flags, data."""
        return b"".join(("%.6f %03X %s %s\n" % (t, m.arbitration_id, "R" if m.is_remote_frame else "D",
                                                 bytes(m.data).hex())).encode() for t, m in self.log)

    def close(self) -> None:
        self._run = False
        if self.clock.stepped:
            self.clock.remove_pump(self.bus)
        elif self._thread is not None:
            self._thread.join(5.0)
        self.bus.shutdown()


def add_remote(net: canopen.Network, clock: Clock, node_id: int, dcf: str) -> canopen.RemoteNode:
    """A canopen RemoteNode on ``net`` whose SDO client waits on ``clock``.
    Its dictionary is the one load_dictionary parsed once for every test
    (a client reads it, never writes it)."""
    node = ClockedRemoteNode(node_id, load_dictionary(dcf, node_id), clock)
    if not clock.stepped:
        node.sdo.RESPONSE_TIMEOUT = REAL_SDO_TIMEOUT
    net.add_node(node)
    return node


def connect_network(clock: Clock, channel: str) -> canopen.Network:
    """A canopen Network on ``channel`` whose frames ``clock`` hands over
    (a notifier thread on the real clock, the clock's pump on a stepped
    one). Its nodes' SDO clients must wait on the clock too: add_remote."""
    net = canopen.Network(can.Bus(interface="virtual", channel=channel))
    net.NOTIFIER_SHUTDOWN_TIMEOUT = 1.0
    net.notifier = clock.notifier(net.bus, net.listeners, 0.05)
    return net


_counter = itertools.count()


class SimRig:
    """Simulator + canopen client + frame recorder on one private virtual
    channel. ``clock``: a SteppedClock of its own unless given (REAL for
    the tests that prove the simulator's real-time loop)."""

    def __init__(self, nodes: List[NodeConfig], tick: float = 0.002, clock: Optional[Clock] = None):
        self.clock = SteppedClock() if clock is None else clock
        self.channel = "virtual_epos4_test_%d_%d" % (os.getpid(), next(_counter))
        self.simbus = can.Bus(interface="virtual", channel=self.channel)
        self.recorder = FrameRecorder(self.clock, self.channel)
        self.raw = self.recorder.bus  # the test's own frames: sent, not recorded
        self.sim = Simulator(self.simbus, nodes, tick=tick, clock=self.clock).start()
        self.net = connect_network(self.clock, self.channel)

    def remote(self, node_id: int, dcf: str = _NODE1) -> canopen.RemoteNode:
        return add_remote(self.net, self.clock, node_id, dcf)

    def send(self, cob_id: int, data: bytes = b"", remote: bool = False) -> None:
        self.raw.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False,
                                  is_remote_frame=remote, dlc=0 if remote else len(data)))

    def send_periodic(self, msg: can.Message, period: float) -> Any:
        """``msg`` every ``period`` s from now, on the rig's clock (stop())."""
        return self.clock.send_periodic(self.raw, [msg], period, "rig_periodic")

    def drain(self) -> None:
        self.recorder.take()

    def expect(self, match: Callable[[can.Message], bool], timeout: float = 5.0) -> Optional[can.Message]:
        """First frame seen by the recorder that satisfies ``match``, or None."""
        return self.recorder.expect(match, timeout)

    def handled(self, seconds: float = 0.0, timeout: float = 10.0) -> List[can.Message]:
        """Evidence for a check that a drive did NOT do something: wait
        until the simulator has handled every frame sent before this call
        and its clock ran on for at least ``seconds`` (counted in its
        ticks, Simulator.ticks: two more than the period needs), then the
        frames the recorder saw meanwhile: everything the nodes sent."""
        start = self.sim.ticks
        ticks = 2 + int(math.ceil(seconds / self.sim.tick_period))
        assert self.wait(lambda: self.sim.ticks >= start + ticks, timeout), "the simulator stands still"
        return self.recorder.take()

    def collect(self, seconds: float) -> List[can.Message]:
        """The frames seen over the next ``seconds`` s."""
        self.clock.sleep(seconds)
        return self.recorder.take()

    def wait(self, condition: Callable[[], bool], timeout: float = 10.0) -> bool:
        return wait_on(self.clock, condition, timeout)

    def close(self) -> None:
        if self.sim is None:
            return
        sim, self.sim = self.sim, None
        sim.stop()
        self.net.disconnect()
        self.recorder.close()
        self.simbus.shutdown()




class DriverRig:
    """Simulator + driver + a frame recorder on one virtual channel, on
    ``clock`` (a SteppedClock of its own unless given: REAL for the tests
    of real-time threading)."""

    def __init__(self, channel: str, clock: Optional[Clock] = None) -> None:
        self.clock = SteppedClock() if clock is None else clock
        self.channel = channel
        self.sim: Optional[Simulator] = None
        self.driver: Any = None
        self.buses: List[can.BusABC] = []
        self.recorder = FrameRecorder(self.clock, channel)
        self.sniffer = self.recorder.bus  # forged frames go out here (and are not recorded)
        self.frames: List[can.Message] = []

    def _bus(self) -> can.BusABC:
        bus = can.Bus(interface="virtual", channel=self.channel)
        self.buses.append(bus)
        return bus

    def start(self, nodes=((1, DCF1, J1),), defaults=None, sim_dcfs=None, hard_stop=None,
              master_consumer=GENEROUS_MASTER_CONSUMER, **top):
        sim_nodes = []
        for i, (nid, dcf, _) in enumerate(nodes):
            sim_dcf = sim_dcfs[i] if sim_dcfs else dcf
            sim_nodes.append(NodeConfig(nid, sim_dcf, hard_stop))
        self.sim = Simulator(self._bus(), sim_nodes, clock=self.clock).start()
        params = {"bus": {"device": "virtual:" + self.channel},
                  "sync": {"interval_ms": SYNC_MS, "overflow": 0},
                  "heartbeat": {"rate": 20, "msg": "77f#05"},
                  "nodes": {"node%d" % nid: {"id": nid, "name": name, "eds_file": dcf}
                            for nid, dcf, name in nodes},
                  "defaults": dict(SEED_UNITS, switching_state=2)}
        if "heartbeat" in top and top["heartbeat"] is None:
            master_consumer = None  # no master heartbeat: init derives no consumer either
        defaults = dict(defaults or {})
        defaults["dcf_overlay"] = dict(master_consumer or {}, **defaults.get("dcf_overlay", {}))
        params["defaults"].update(defaults)
        params.update(top)
        # Generous waits: they only bound how long a failure takes on a loaded host.
        self.driver = Driver(load_config(params, "test"), homing_timeout=30.0, state_timeout=10.0,
                             clock=self.clock)
        return self.driver

    def until(self, pred: Callable[[], bool], timeout: float = TIMEOUT) -> bool:
        """Whether ``pred`` came to hold within ``timeout`` s of the rig's clock."""
        return wait_on(self.clock, pred, timeout)

    def read(self, index, sub=0, node=1):
        return self.sim.read(node, index, sub)

    def state(self, node=1):
        return state_from_statusword(self.read(0x6041, node=node))

    def _collect(self) -> List[can.Message]:
        self.frames.extend(self.recorder.take())
        return self.frames

    def drain(self) -> None:
        """Forget every frame seen so far."""
        self._collect()
        self.frames = []

    def sent(self, cob_id: int) -> List[bytes]:
        """Payloads sent to cob_id since the last drain()."""
        return [bytes(m.data) for m in self._collect() if m.arbitration_id == cob_id]

    def sim_ran(self, seconds: float = 0.0) -> bool:
        """Wait until the simulator handled every frame queued before this
        call and its clock ran on for at least ``seconds`` (counted in its
        ticks, Simulator.ticks: two more than the period needs, as a loop
        that fell behind ticks twice in a row once)."""
        start = self.sim.ticks
        ticks = 2 + int(math.ceil(seconds / self.sim.tick_period))
        return self.until(lambda: self.sim.ticks >= start + ticks)

    def had_the_chance(self, cycles: int = CHANCE_CYCLES) -> None:
        """Evidence for a check that something did NOT happen: the driver
        runs ``cycles`` more cycles (each sends the controlword, the cyclic
        RxPDOs and, on this bus, the SYNC), then the simulated drive has
        handled every frame they sent. A cycle publishes its snapshot
        before it sends: cycle n+1's snapshot means cycle n has sent."""
        start = self.driver.cycles
        assert self.until(lambda: self.driver.cycles > start + cycles), (
            "the driver ran %d of %d cycles" % (self.driver.cycles - start, cycles))
        assert self.sim_ran(), "the simulator stands still"

    def close(self) -> None:
        if self.driver is not None:
            self.driver.close()
            self.driver = None
        if self.sim is not None:
            self.sim.stop()
            self.sim = None
        self.recorder.close()
        for bus in self.buses:
            bus.shutdown()
        self.buses = []


@pytest.fixture
def clock() -> SteppedClock:
    """A stepped clock of the test's own."""
    return SteppedClock()


def _made_and_closed(build: Callable[..., Any]) -> Iterator[Callable[..., Any]]:
    """A fixture's body: yields a factory of ``build``'s rigs and closes
    each rig it made after the test."""
    made: List[Any] = []

    def make(*args: Any, **kwargs: Any) -> Any:
        made.append(build(*args, **kwargs))
        return made[-1]
    yield make
    for rig in made:
        rig.close()


@pytest.fixture
def sim_rig():
    """``sim_rig(nodes, tick=0.002, clock=None)``: a SimRig, closed after
    the test; on a stepped clock of its own unless given one."""
    yield from _made_and_closed(SimRig)


@pytest.fixture
def make_driver_rig(request):
    """``make_driver_rig(clock=None)``: a DriverRig (on a stepped clock of
    its own unless given one), closed after the test."""
    yield from _made_and_closed(
        lambda clock=None: DriverRig("drv_%s_%d" % (request.node.name, next(_channels)), clock))


@pytest.fixture
def driver_rig(make_driver_rig):
    """A DriverRig on a stepped clock of its own, closed after the test."""
    return make_driver_rig()


@pytest.fixture
def real_driver_rig(make_driver_rig):
    """A DriverRig on the wall clock: for the tests of real-time threading."""
    return make_driver_rig(REAL)

__all__ = ["REAL", "DriverRig", "FrameRecorder", "SimRig", "add_remote", "connect_network", "wait_on"]
