"""Bus plumbing: the CAN bus and canopen network, NMT, reception (TPDOs,
heartbeats, EMCYs, foreign frames), the SDO clients, and the master's
heartbeat and SYNC producers.

``Link``'s fields are written by the service holding the driver's service
lock (open, close, SYNC start and stop); canopen's notifier thread only
hands frames over (heartbeats and EMCYs to the cycle's inbox, SDO answers
to their clients) and counts foreign frames. TxPDOs and SYNC frames go to a
receiver the cycle reads itself (``reception``, cycle_reception.py), or,
on an adapter that cannot open one, through the notifier to the
receiver's latest-frame slots. The cycle reads ``bus``, ``receiver``,
``reception``, ``receive_clock`` and the SYNC fields."""
from __future__ import annotations

import logging
import socket
import threading
from types import MappingProxyType
from typing import Any, Callable, Dict, Mapping, Optional, Union

import can
import canopen
from can.interfaces.virtual import VirtualBus

from ..can_device import max_receive_lag
from ..clock import REAL, Clock
from ..config_schema import DriverConfig
from .bus import SYNC_COB_ID, HeartbeatProducer, ReceiveClock, SyncProducer, is_socketcan, open_bus, unread_frames
from .cycle_reception import CYCLE_TASK, BusReceiver, CycleReception, RawCanReceiver
from .inbox import Emcy, Heartbeat
from .nodes import InitError, NodeTable, Timeouts
from .pdo import TpdoReceiver, enabled_maps, sync_driven
from .sdo import GuardedSdoClient

log = logging.getLogger("maxon_epos4_ros_canopen.driver")
canopen_log = logging.getLogger("canopen.network")  # where MessageListener logs a subscriber's error

NMT_START, NMT_STOP, NMT_ENTER_PRE_OPERATIONAL, NMT_RESET_NODE = 0x01, 0x02, 0x80, 0x81
_KERNEL_FILTER_MAX = 512  # CAN_RAW_FILTER_MAX of Linux
# How long the reader thread waits in one receive call: closing the bus
# waits for it to come out (canopen's Network uses 1 s). An idle bus then
# wakes the thread 10 times a second, which costs nothing measurable.
NOTIFIER_TIMEOUT = 0.1


class _ReceiveErrors(can.Listener):
    """Handles the CAN notifier's receive errors: logged (at most once a
    second) and waited out, so its reader thread keeps running.

    The notifier keeps the error as its ``exception``, and canopen's Network
    raises that again on every later send (SDO requests included): cleared
    here, or an interface that was down once would fail every SDO for good."""

    def __init__(self, notifier: can.Notifier, clock: Clock) -> None:
        self._notifier = notifier
        self._clock = clock
        self._logged = 0.0

    def on_message_received(self, msg: can.Message) -> None:
        pass

    def on_error(self, exc: Exception) -> None:
        self._notifier.exception = None
        now = self._clock.now()
        if now - self._logged > 1.0:
            self._logged = now
            log.error("CAN receive error: %s", exc)
        self._clock.sleep(0.1)  # a downed interface fails every read at once


class _Reception(_ReceiveErrors):
    """The notifier's one listener: the receive clock, then canopen's
    dispatch, then receive errors as _ReceiveErrors.

    What the three listeners (ReceiveClock, canopen's MessageListener,
    _ReceiveErrors) did one after the other, in that order, in one call:
    the notifier thread runs this for every frame on the bus, and each
    listener was a call through can.Listener.__call__ as well. The
    dispatch is canopen's Network.notify with MessageListener's guard:
    error and remote frames go to no subscriber, a subscriber's exception
    is logged and the next frame handled."""

    def __init__(self, receive_clock: ReceiveClock, network: canopen.Network, clock: Clock) -> None:
        super().__init__(None, clock)  # type: ignore[arg-type]  # the notifier is set once it exists
        self._stamp = receive_clock.on_message_received
        self._subscribers = network.subscribers  # canopen's own dict: later subscriptions count
        self._scanner = network.scanner

    def on_message_received(self, msg: can.Message) -> None:
        self._stamp(msg)
        if msg.is_error_frame or msg.is_remote_frame:
            return
        can_id = msg.arbitration_id
        try:
            callbacks = self._subscribers.get(can_id)
            if callbacks:
                data, timestamp = msg.data, msg.timestamp
                for callback in callbacks:
                    callback(can_id, data, timestamp)
            self._scanner.on_message_received(can_id)
        except Exception as e:  # as canopen's MessageListener: the notifier goes on
            canopen_log.error(str(e))

    # can.Notifier calls the listener itself: no second call through can.Listener.__call__
    __call__ = on_message_received


class Link:
    """The driver's side of the bus (see the module's docstring)."""

    def __init__(self, config: DriverConfig, nodes: NodeTable, timeouts: Timeouts,
                 post: Callable[[Any], None], external_bus: Optional[can.BusABC] = None,
                 clock: Clock = REAL, pdo_bus: Union[can.BusABC, socket.socket, None] = None) -> None:
        """``pdo_bus``: with ``external_bus``, a bus that carries the
        drives' TxPDOs and SYNC to the cycle, or a socket that carries them
        as SocketCAN frames (see cycle_reception.py)."""
        self.config = config
        # Every timer and wait of the driver's parts: real time, or a test's
        # stepped clock (clock.py); the parts take it from here.
        self.clock = clock
        self._nodes = nodes
        self._timeouts = timeouts
        self._post = post  # to the cycle's inbox: heartbeats and EMCYs
        self.external_bus = external_bus
        self.pdo_bus = pdo_bus
        self.bus: Optional[can.BusABC] = None
        self.network: Optional[canopen.Network] = None
        self.sdo: Mapping[str, GuardedSdoClient] = MappingProxyType({})
        self.receiver: Optional[TpdoReceiver] = None
        self.reception: Optional[CycleReception] = None  # None: TxPDOs come through the notifier
        self.receive_clock = ReceiveClock(clock=clock)  # written by the notifier thread only
        self.boot: Dict[int, threading.Event] = {}
        self.heartbeat: Optional[HeartbeatProducer] = None
        self.sync: Optional[SyncProducer] = None
        self.sync_paced = False     # SYNC from the kernel, the cycle paced between SYNCs
        self.sync_in_cycle = False  # SYNC sent by the cycle
        self.foreign_frames = [0]  # written by the notifier thread only

    # ========================================================== open/close
    def open(self) -> None:
        if self.external_bus is not None:
            self.bus = self.external_bus
        else:
            try:
                self.bus = open_bus(self.config.bus)
            except Exception as e:  # OSError, CanError, ValueError from python-can
                raise InitError("cannot open CAN device %r: %s" % (self.config.bus.device, e)) from None
        network = canopen.Network(self.bus)
        # first, so that every subscriber takes its frame's times from it
        self.receive_clock = clock = ReceiveClock(unread_frames(self.bus), max_receive_lag(self.bus),
                                                  clock=self.clock)
        # canopen's connect() with a bus given only starts a notifier: the
        # clock's (python-can's thread, or a stepped clock's pump), here with
        # one listener that stamps, dispatches to the network's subscribers
        # and handles receive errors: python-can's notifier ends its reader
        # thread on the first receive error (an interface going down) unless
        # a listener handles it; this one does, so reception resumes when
        # the interface is up again.
        reception = _Reception(clock, network, self.clock)
        network.notifier = self.clock.notifier(self.bus, [reception], NOTIFIER_TIMEOUT)
        reception._notifier = network.notifier
        self.network = network
        self.receiver = receiver = TpdoReceiver({m.cob_id: m.length for node in self._nodes.values()
                                                 for m in enabled_maps(node.plan.tx)}, clock.times,
                                                [c for node in self._nodes.values() for c in sync_driven(node.plan.tx)])
        self.reception = self._open_cycle_reception(receiver)
        if self.reception is None:
            for cob in receiver.cob_ids:
                network.subscribe(cob, receiver.on_frame)
            network.subscribe(SYNC_COB_ID, receiver.on_sync)  # the kernel's SYNC, or another producer's
        if not self.config.bus.loopback:
            # With loopback off the driver never hears its own frames: one on
            # its RxPDO COB-IDs comes from another master. It is counted and
            # otherwise ignored.
            for node in self._nodes.values():
                for m in enabled_maps(node.plan.rx):
                    network.subscribe(m.cob_id, self._on_foreign_frame)
        sdo = {}
        post = self._post
        now = self.clock.now
        for name, node in self._nodes.items():
            nid = node.cfg.node_id
            client = GuardedSdoClient(0x600 + nid, 0x580 + nid, node.od, clock, self.clock)
            client.network = network
            client.RESPONSE_TIMEOUT = self._timeouts.sdo
            network.subscribe(0x580 + nid, client.on_response)
            sdo[name] = client
            boot = self.boot.setdefault(nid, threading.Event())

            def on_heartbeat(can_id: int, data: Any, _ts: float, boot: threading.Event = boot) -> None:
                payload = bytes(data)
                if payload == b"\x00":
                    boot.set()
                # stamped with when it arrived, not when this thread got to it
                post(Heartbeat(can_id - 0x700, payload, clock.progress[1]))

            def on_emcy(can_id: int, data: Any, _ts: float) -> None:
                post(Emcy(can_id - 0x80, bytes(data), now()))
            network.subscribe(0x700 + nid, on_heartbeat)
            network.subscribe(0x80 + nid, on_emcy)
        self.sdo = MappingProxyType(sdo)
        self._filter_in_kernel(network)
        if self.config.heartbeat is not None:
            self.heartbeat = HeartbeatProducer(self.bus, self.config.heartbeat, self.clock)
            self.heartbeat.start()

    def _open_cycle_reception(self, receiver: TpdoReceiver) -> Optional[CycleReception]:
        """The cycle's own receiver of TxPDOs and SYNC where the bus allows
        a second one (cycle_reception.py); None: the notifier's path."""
        ids = receiver.cob_ids + (SYNC_COB_ID,)
        bus, clock = self.bus, self.clock
        source: Any = None
        try:
            if isinstance(self.pdo_bus, socket.socket):
                source = RawCanReceiver(self.pdo_bus, owned=False)
            elif self.pdo_bus is not None:
                source = BusReceiver(clock.frame_reader(self.pdo_bus, CYCLE_TASK), ids)
            elif self.external_bus is not None:
                return None  # a caller's bus: no second receiver on it
            elif is_socketcan(bus) and not clock.stepped:
                source = RawCanReceiver.open(bus.channel, ids)
            elif isinstance(bus, VirtualBus) and clock.stepped:
                # Stepped runs take the cycle's own receiver; on the wall
                # clock python-can's virtual bus keeps the notifier's path
                # (that of adapters without a second receiver), so that the
                # fast suite's real-time tests run that path too.
                second = can.Bus(interface="virtual", channel=bus.channel_id)
                source = BusReceiver(clock.frame_reader(second, CYCLE_TASK), ids, second.shutdown)
            else:
                return None
        except (OSError, can.CanError) as e:
            log.warning("no receiver of its own for the cycle (%s): TxPDOs come through the notifier", e)
            return None
        return CycleReception(source, receiver, clock, max_receive_lag(bus))

    def _filter_in_kernel(self, network: canopen.Network) -> None:
        """On a SocketCAN bus of its own, the driver has the kernel drop
        every frame nobody here subscribed to: a busy or hostile bus then
        costs the notifier thread (and through the GIL the cycle) nothing
        for frames the driver ignores anyway."""
        ids = sorted(network.subscribers)
        if self.external_bus is not None or not is_socketcan(self.bus) or len(ids) > _KERNEL_FILTER_MAX:
            return
        try:
            self.bus.set_filters([{"can_id": i, "can_mask": 0x7FF, "extended": False} for i in ids])
        except (OSError, can.CanError) as e:
            log.warning("CAN receive filters not set (%s): every frame reaches the driver", e)

    def _on_foreign_frame(self, _can_id: int, _data: Any, _ts: float) -> None:
        self.foreign_frames[0] += 1

    def close(self) -> None:
        for what, fn in (("heartbeat producer", self._stop_heartbeat), ("CAN network", self._close_network)):
            try:
                fn()
            except Exception as e:  # closing must go on whatever a part says
                log.warning("closing the %s: %s", what, e)

    def _stop_heartbeat(self) -> None:
        if self.heartbeat is not None:
            heartbeat, self.heartbeat = self.heartbeat, None
            heartbeat.stop()

    def _close_network(self) -> None:
        network, self.network = self.network, None
        self.sdo = MappingProxyType({})
        reception, self.reception = self.reception, None
        if reception is not None:
            reception.close()
        if network is not None and network.notifier is not None:
            # the notifier's reader wakes every NOTIFIER_CYCLE: wait longer
            # than that, or shutting the bus below it pulls its socket away
            # mid-read ("Bad file descriptor")
            network.notifier.stop(network.NOTIFIER_CYCLE + 1.0)
        bus, self.bus = self.bus, None
        if bus is not None and self.external_bus is None:
            bus.shutdown()

    def nmt(self, command: int, node_id: int) -> None:
        # Raw NMT frames: canopen's NmtMaster looks its state up in a table
        # and raises on a state byte CiA 301 does not define.
        self.network.send_message(0, bytes([command, node_id]))

    # ================================================================ SYNC
    def open_sync(self) -> None:
        """The SYNC producer for a cycle about to start (none without SYNC)."""
        sync = self.config.sync
        if sync.interval_ms > 0:
            # When SYNC and cycle share a period the cycle sends each SYNC
            # right after its RxPDOs, so every SYNC carries fresh targets.
            # With sync/kernel_timer (the default) the kernel's broadcast manager sends
            # SYNC (SocketCAN; no scheduling delay of this process moves a
            # SYNC) and the cycle is paced between two SYNCs (see the
            # cycle's run): its RxPDOs only have to land before the next one.
            # Without a kernel timer (python-can's virtual bus, no can-bcm)
            # the cycle sends SYNC itself: a second thread would only add its
            # own jitter.
            self.sync = SyncProducer(self.bus, sync.overflow, self.clock)
            self.start_sync()

    def start_sync(self) -> None:
        sync, producer = self.config.sync, self.sync
        same_period = sync.interval_ms == sync.update_ms
        if same_period and not (sync.kernel_timer and is_socketcan(self.bus)):  # no kernel timer: no thread either
            producer.stop()
            self.sync_paced, self.sync_in_cycle = False, True
            return
        producer.start(sync.interval_ms / 1000.0)
        self.sync_paced = same_period and producer.kernel_timed
        self.sync_in_cycle = same_period and not producer.kernel_timed
        if self.sync_in_cycle:
            producer.stop()

    def close_sync(self) -> None:
        if self.sync is not None:
            try:
                self.sync.stop()
            except Exception as e:
                log.warning("stopping SYNC: %s", e)
            self.sync = None
        self.sync_paced = self.sync_in_cycle = False
