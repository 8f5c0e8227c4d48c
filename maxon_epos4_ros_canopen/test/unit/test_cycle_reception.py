"""The cycle's own receiver of TxPDOs and SYNC (driver/cycle_reception.py):
what a forged, short, repeated or missing frame and a failing receiver do
to it, and that the driver runs on it over python-can's virtual bus."""
from __future__ import annotations

import logging
import socket
import struct
import time
from typing import List, Optional, Tuple

import can

from driver_support import DCF1, J1, SYNC_MS, ppm_ready
from maxon_epos4_ros_canopen.cia402 import State
from maxon_epos4_ros_canopen.clock import SteppedClock
from maxon_epos4_ros_canopen.config import load_config
from maxon_epos4_ros_canopen.driver import Driver
from maxon_epos4_ros_canopen.driver.cycle_reception import (
    CAN_EFF_FLAG, CAN_ERR_FLAG, CAN_RTR_FLAG, MIN_BUDGET, SO_TIMESTAMPNS, CycleReception, RawCanReceiver, Received,
    parse_frame)
from maxon_epos4_ros_canopen.driver.pdo import TpdoReceiver, sync_driven
from maxon_epos4_ros_canopen.sim import NodeConfig, Simulator

STATUS_TPDO, CONTROL_RPDO, SYNC = 0x181, 0x201, 0x080


def can_frame(can_id: int, data: bytes, length: Optional[int] = None) -> bytes:
    n = len(data) if length is None else length
    return struct.pack("=IB3x8s", can_id, n, data)


def stamp(sec: int, nsec: int) -> List[Tuple[int, int, bytes]]:
    return [(socket.SOL_SOCKET, SO_TIMESTAMPNS, struct.pack("@ll", sec, nsec))]


# ------------------------------------------------------------ parse_frame
def test_a_standard_data_frame_is_parsed_with_its_kernel_stamp():
    assert parse_frame(can_frame(0x181, b"\x37\x02\x10\x00"), stamp(1700000000, 250_000_000)) == (
        0x181, b"\x37\x02\x10\x00", 1700000000.25)


def test_a_short_frame_keeps_its_length_for_the_receiver_to_reject():
    assert parse_frame(can_frame(0x181, b"\x37"), ()) == (0x181, b"\x37", None)
    assert parse_frame(can_frame(SYNC, b""), ()) == (SYNC, b"", None)


def test_extended_remote_error_oversized_and_truncated_frames_are_no_frames():
    data = b"\x37\x02\x00\x00"
    assert parse_frame(can_frame(0x181 | CAN_EFF_FLAG, data), ()) is None
    assert parse_frame(can_frame(0x181 | CAN_RTR_FLAG, data), ()) is None
    assert parse_frame(can_frame(0x181 | CAN_ERR_FLAG, data), ()) is None
    assert parse_frame(can_frame(0x181, data, length=9), ()) is None
    assert parse_frame(can_frame(0x181, data)[:12], ()) is None


def test_a_stamp_of_another_kind_or_too_short_is_no_stamp():
    frame = can_frame(0x181, b"\x00\x00")
    assert parse_frame(frame, [(socket.SOL_SOCKET, 29, struct.pack("@ll", 5, 0))])[2] is None
    assert parse_frame(frame, [(socket.SOL_SOCKET, SO_TIMESTAMPNS, b"\x01\x02")])[2] is None


# -------------------------------------------------------- RawCanReceiver
def test_the_socketcan_receiver_takes_standard_data_frames_with_their_kernel_stamps():
    """RawCanReceiver on a socket that carries SocketCAN frames (a
    socketpair here): each standard data frame with the kernel's receive
    stamp, a short one with its length (the TPDO receiver rejects it);
    extended, remote, error, oversized, truncated and CAN FD sized frames
    are no frames; at most ``limit`` a read; an empty socket ends a read."""
    mine, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    receiver = RawCanReceiver(mine, owned=False)
    try:
        before = time.time()
        for frame in (can_frame(0x181, b"\x37\x02\x10\x00"),
                      can_frame(0x181 | CAN_EFF_FLAG, b"\x37\x02"),
                      can_frame(0x181 | CAN_RTR_FLAG, b""),
                      can_frame(0x181 | CAN_ERR_FLAG, bytes(8)),
                      can_frame(0x181, bytes(8), length=9),
                      can_frame(0x181, bytes(8))[:12],
                      can_frame(0x181, bytes(8)) + bytes(56),  # a CAN FD frame's size
                      can_frame(0x281, b"\x01"),
                      can_frame(SYNC, b"")):
            theirs.send(frame)
        after = time.time()
        frames, error = receiver.take(2)
        assert error is None
        assert [(c, d) for c, d, _ in frames] == [(0x181, b"\x37\x02\x10\x00"), (0x281, b"\x01")]
        assert all(before - 0.001 <= t <= after + 0.001 for _, _, t in frames)
        assert [(c, d) for c, d, _ in receiver.take(10)[0]] == [(SYNC, b"")]
        assert receiver.take(10) == ([], None)
    finally:
        receiver.close()
    theirs.send(can_frame(0x181, bytes(6)))
    assert len(mine.recv(16)) == 16  # not the receiver's to close
    owned = RawCanReceiver(theirs)
    owned.close()
    assert theirs.fileno() == -1
    mine.close()


# --------------------------------------------------------- CycleReception
class Source:
    """A receiver that hands out what a test put in it, up to the limit
    asked, and then the error it was told to raise (once)."""

    def __init__(self) -> None:
        self.waiting: List[Received] = []
        self.error: Optional[BaseException] = None
        self.closed = False

    def take(self, limit: int):
        out, self.waiting = self.waiting[:limit], self.waiting[limit:]
        error, self.error = self.error, None
        return out, error

    def close(self) -> None:
        self.closed = True


def reception(clock: SteppedClock) -> Tuple[CycleReception, TpdoReceiver, Source]:
    receiver = TpdoReceiver({STATUS_TPDO: 6, 0x281: 8}, sync_driven=[STATUS_TPDO])
    source = Source()
    return CycleReception(source, receiver, clock, 60.0), receiver, source


def test_frames_count_from_their_kernel_stamp_not_from_when_the_cycle_reads_them(clock):
    r, receiver, source = reception(clock)
    clock.advance(1.0)
    source.waiting = [(SYNC, b"", clock.wall() - 0.004), (STATUS_TPDO, bytes(6), clock.wall() - 0.003)]
    assert r.poll(clock.now()) == 2
    data, read_at, arrived = receiver.latest(STATUS_TPDO)
    assert (data, read_at) == (bytes(6), 1.0)
    assert abs(arrived - 0.997) < 1e-6  # wall times near 1.7e9 s carry about 0.2 us
    assert abs(receiver.last_sync_heard() - 0.996) < 1e-6
    assert abs(r.lag() - 0.003) < 1e-6


def test_the_lag_is_none_once_a_read_finds_nothing_waiting(clock):
    """A receiver that found its socket empty is behind by nothing: drives
    that went silent must not leave the last frame's wait in diagnostics."""
    r, _, source = reception(clock)
    clock.advance(1.0)
    source.waiting = [(STATUS_TPDO, bytes(6), clock.wall() - 0.003)]
    r.poll(clock.now())
    assert abs(r.lag() - 0.003) < 1e-6
    clock.advance(0.01)
    assert r.poll(clock.now()) == 0
    assert r.lag() == 0.0
    source.error = OSError(100, "Network is down")
    clock.advance(0.01)
    r.poll(clock.now())
    assert r.lag() == 0.0  # an error read nothing and tells nothing of a backlog


def test_a_frame_of_the_wrong_length_is_counted_and_never_taken(clock):
    r, receiver, source = reception(clock)
    source.waiting = [(STATUS_TPDO, bytes(6), None), (STATUS_TPDO, b"\xff\xff", None)]
    r.poll(clock.now())
    assert receiver.latest(STATUS_TPDO)[0] == bytes(6)
    assert receiver.rejected[STATUS_TPDO] == 1


def test_a_second_frame_in_one_sync_period_is_a_conflict(clock):
    r, receiver, source = reception(clock)
    wall = clock.wall()
    source.waiting = [(SYNC, b"", wall + 0.000), (STATUS_TPDO, bytes(6), wall + 0.001),
                      (STATUS_TPDO, bytes(6), wall + 0.002),  # repeated by a forger
                      (SYNC, b"", wall + 0.010), (STATUS_TPDO, bytes(6), wall + 0.011)]
    clock.advance(0.02)
    r.poll(clock.now())
    assert receiver.conflicts[STATUS_TPDO] == 1


def test_a_cob_id_the_receiver_does_not_know_is_ignored(clock):
    r, receiver, source = reception(clock)
    source.waiting = [(0x182, bytes(6), None)]
    assert r.poll(clock.now()) == 1
    assert receiver.latest(STATUS_TPDO) is None and receiver.anomalies == 0


def test_at_most_the_budget_is_read_per_cycle_and_the_rest_in_the_next(clock):
    """A flood of forged frames cannot hold the cycle in its read: the
    backlog waits for the next cycles."""
    r, receiver, source = reception(clock)
    assert r.budget == MIN_BUDGET
    source.waiting = [(STATUS_TPDO, b"\x01", None)] * (2 * MIN_BUDGET + 5)
    assert [r.poll(clock.now()) for _ in range(4)] == [MIN_BUDGET, MIN_BUDGET, 5, 0]
    assert r.full_reads == 2
    assert receiver.rejected[STATUS_TPDO] == 2 * MIN_BUDGET + 5


def test_a_receive_error_is_counted_logged_once_a_second_and_reading_goes_on(clock, caplog):
    r, receiver, source = reception(clock)
    caplog.set_level(logging.ERROR, logger="maxon_epos4_ros_canopen.driver")
    for _ in range(10):  # an interface that is down: every read fails, 10 cycles in 0.1 s
        source.error = OSError(100, "Network is down")
        assert r.poll(clock.now()) == 0
        clock.advance(0.01)
    assert r.errors == 10
    assert len([rec for rec in caplog.records if "Network is down" in rec.getMessage()]) == 1
    source.waiting = [(STATUS_TPDO, bytes(6), None)]
    assert r.poll(clock.now()) == 1
    assert receiver.latest(STATUS_TPDO) is not None


def test_a_receiver_that_raises_what_nobody_foresaw_does_not_end_the_cycle(clock):
    r, _, source = reception(clock)

    def broken(limit):
        raise RuntimeError("a receiver broken in a new way")
    source.take = broken
    assert r.poll(clock.now()) == 0
    assert isinstance(r.last_error, RuntimeError)


# ------------------------------------------------------ the driver on it
def test_a_flood_of_short_statusword_frames_is_counted_while_the_cycle_runs_every_period(driver_rig):
    """Ten budgets of forged short frames on the statusword TxPDO at once:
    every one is counted, none is taken for the drive's statusword, and
    the cycle runs (and sends its SYNC) every period while it reads the
    backlog, a budget a cycle."""
    rig = driver_rig
    d = ppm_ready(rig)
    frames = 10 * MIN_BUDGET
    bad_before = d.joints[J1].counters.get("bad_tpdo", 0)
    rig.drain()
    start = d.cycles
    for _ in range(frames):
        rig.sniffer.send(can.Message(arbitration_id=STATUS_TPDO, data=b"\x00", is_extended_id=False))
    assert rig.until(lambda: d.joints[J1].counters.get("bad_tpdo", 0) - bad_before == frames)
    cycles = d.cycles - start
    assert cycles >= 10, "the backlog was read in %d cycles" % cycles
    syncs = [m for m in rig._collect() if m.arbitration_id == SYNC]
    assert len(syncs) >= cycles - 1
    assert d.status()[0]["cycles_late"] == 0
    rig.had_the_chance(5)
    assert d.joints[J1].state == State.OPERATION_ENABLED and d.joints[J1].error is None
    assert d.set_command(J1, "position", 1500).success
    assert rig.until(lambda: abs(rig.read(0x6064) - 1500) < 5)


def driver_moved_beside(clock, channel: str, bus, pdo_bus) -> Driver:
    """A driver of node 1 on ``bus`` (virtual channel ``channel``) that reads
    its TxPDOs from ``pdo_bus``, initialized in profile position and moved
    to 2000: its readings show that the TxPDOs reach it. The caller closes it."""
    params = {"bus": {"device": "virtual:" + channel}, "sync": {"interval_ms": SYNC_MS, "overflow": 0},
              "nodes": {"node1": {"id": 1, "name": J1, "eds_file": DCF1}},
              "defaults": {"pos_to_device": "pos", "pos_from_device": "obj6064", "vel_to_device": "vel",
                           "vel_from_device": "obj606C", "eff_to_device": "rint(eff)", "eff_from_device": "0",
                           "switching_state": 2}}
    d = Driver(load_config(params, "test"), bus=bus, pdo_bus=pdo_bus, clock=clock, state_timeout=10.0)
    try:
        assert d.init().success
        assert d.switch_mode([J1], 1).success
        assert d.set_command(J1, "position", 2000).success
        assert clock.wait_until(lambda: abs(d.joints[J1].position - 2000) < 5, 10.0)
    except BaseException:
        d.close()
        raise
    return d


def test_a_driver_given_a_bus_reads_its_txpdos_from_the_pdo_bus_given_beside_it(clock):
    """Driver(config, bus=..., pdo_bus=...): the caller's bus for
    everything, a second one on the same channel for the cycle's TxPDOs
    and SYNC (as the benchmarks run the driver)."""
    channel = "pdo_bus_given"
    sim_bus = can.Bus(interface="virtual", channel=channel)
    bus = can.Bus(interface="virtual", channel=channel)
    pdo_bus = can.Bus(interface="virtual", channel=channel)
    real_recv = bus.recv

    def recv(timeout=None):
        """The caller's bus filters out TxPDOs and SYNC, as the kernel
        would: they reach the driver through pdo_bus or not at all."""
        while True:
            msg = real_recv(timeout)
            if msg is None or not (msg.arbitration_id == SYNC or 0x180 <= msg.arbitration_id < 0x500):
                return msg
    bus.recv = recv
    sim = Simulator(sim_bus, [NodeConfig(1, DCF1)], clock=clock).start()
    try:
        driver_moved_beside(clock, channel, bus, pdo_bus).close()
    finally:
        sim.stop()
        for b in (sim_bus, bus, pdo_bus):
            b.shutdown()


def test_a_driver_given_a_socket_reads_its_txpdos_from_it_as_socketcan_frames(clock):
    """Driver(config, bus=..., pdo_bus=<socket>): the drives' TxPDOs come
    as SocketCAN frames on a socket (a socketpair, as the cycle benchmark
    runs the driver), read by the driver's SocketCAN receiver; a short
    forged statusword frame on it is counted, an extended one ignored, and
    the caller's socket stays open after close."""
    channel = "pdo_socket_given"
    sim_bus = can.Bus(interface="virtual", channel=channel)
    bus = can.Bus(interface="virtual", channel=channel)
    mine, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    real_send = sim_bus.send

    def send(msg, timeout=None):
        """The simulated drive's TxPDOs go to the socket alone."""
        if 0x180 <= msg.arbitration_id < 0x500:
            theirs.send(can_frame(msg.arbitration_id, bytes(msg.data)))
        else:
            real_send(msg, timeout)
    sim_bus.send = send
    sim = Simulator(sim_bus, [NodeConfig(1, DCF1)], clock=clock).start()
    d = driver_moved_beside(clock, channel, bus, mine)
    try:
        bad = d.joints[J1].counters.get("bad_tpdo", 0)
        theirs.send(can_frame(STATUS_TPDO, b"\x08"))  # a forged short statusword
        theirs.send(can_frame(STATUS_TPDO | CAN_EFF_FLAG, b"\x08\x00"))  # extended: no TxPDO of a drive
        assert clock.wait_until(lambda: d.joints[J1].counters.get("bad_tpdo", 0) == bad + 1, 10.0)
        cycles = d.cycles
        assert clock.wait_until(lambda: d.cycles >= cycles + 5, 10.0)
        assert d.joints[J1].counters.get("bad_tpdo", 0) == bad + 1
        assert d.joints[J1].state == State.OPERATION_ENABLED and d.joints[J1].error is None
    finally:
        d.close()
        sim.stop()
        sim_bus.shutdown()
        bus.shutdown()
    theirs.send(can_frame(STATUS_TPDO, bytes(6)))
    assert len(mine.recv(16)) == 16  # the caller's socket: still open
    mine.close()
    theirs.close()
