"""The simulator's own SocketCAN frames (rawcan.py) against
python-can's: the same bytes to the kernel, the same frame read back, and
a simulator that serves a "SocketCAN" bus through them. This host's
kernel has no SocketCAN: a socketpair stands in for the CAN socket (the
bytes are the same, only the kernel's time stamp is missing)."""
import random
import socket
import struct

import can
import pytest
from can.interfaces.socketcan import SocketcanBus
from can.interfaces.socketcan import socketcan as pcan

from maxon_epos4_ros_canopen.sim import NodeConfig, Simulator
from maxon_epos4_ros_canopen import rawcan
from sim_support import NODE1

FRAMES = 3000


def _messages(rng: random.Random):
    """Frames the simulator sends: 11-bit identifiers, 0-8 bytes, some remote (DLC 0)."""
    for _ in range(FRAMES):
        cob = rng.randrange(0x800)
        if rng.random() < 0.1:
            yield cob, b"", True
        else:
            yield cob, bytes(rng.randrange(256) for _ in range(rng.randrange(9))), False


def test_a_frame_is_written_as_python_can_writes_it():
    rng = random.Random(1)
    for cob, data, remote in _messages(rng):
        ours = rawcan.encode(cob, data, remote)
        theirs = pcan.build_can_frame(can.Message(arbitration_id=cob, data=data, is_extended_id=False,
                                                  is_remote_frame=remote, dlc=0 if remote else len(data)))
        assert len(ours) == len(theirs) == rawcan.CAN_MTU
        # what the kernel reads: identifier and flags, length, data (python-can
        # versions differ in the len8_dlc byte, which counts only from 9 up)
        assert pcan.dissect_can_frame(ours) == pcan.dissect_can_frame(theirs), (cob, data, remote)
        assert ours[8:] == theirs[8:]


class _FakeSocket:
    """recvmsg as a SocketCAN socket answers it: the frame, its time stamp."""

    def __init__(self, frame: bytes, stamp: tuple, flags: int = 0) -> None:
        self.answer = (frame, [(socket.SOL_SOCKET, 35, struct.pack("@ll", *stamp))], flags, ("vcan0",))

    def recvmsg(self, *args):
        return self.answer


def test_a_frame_is_read_as_python_can_reads_it():
    rng = random.Random(2)
    for _ in range(FRAMES):
        can_id = rng.randrange(0x800)
        kind = rng.random()
        if kind < 0.1:
            can_id |= rawcan.CAN_RTR_FLAG
        elif kind < 0.2:
            can_id = rng.randrange(1 << 29) | rawcan.CAN_EFF_FLAG
        elif kind < 0.25:
            can_id |= rawcan.CAN_ERR_FLAG
        length = rng.randrange(9)
        data = bytes(rng.randrange(256) for _ in range(8))
        frame = struct.pack("=IBB1xB", can_id, length, 0, length) + data
        stamp = (rng.randrange(1_600_000_000, 1_900_000_000), rng.randrange(1_000_000_000))
        fake = _FakeSocket(frame, stamp)
        msg = pcan.capture_message(fake)
        ours_id, ours_data, ours_stamp = rawcan.decode(*fake.recvmsg()[:2])
        assert ours_stamp == msg.timestamp  # the same float
        assert bool(ours_id & rawcan.CAN_EFF_FLAG) == msg.is_extended_id
        assert bool(ours_id & rawcan.CAN_RTR_FLAG) == msg.is_remote_frame
        assert bool(ours_id & rawcan.CAN_ERR_FLAG) == msg.is_error_frame
        assert ours_id & (0x1FFFFFFF if msg.is_extended_id else 0x7FF) == msg.arbitration_id
        assert ours_data == bytes(msg.data)


def test_receive_waits_only_when_asked_and_send_writes_one_frame():
    mine, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    try:
        raw = rawcan.RawSocketcan(mine)
        assert raw.recv(0.0) is None  # nothing waiting: no wait
        assert raw.recv(0.01) is None  # nothing within the timeout
        theirs.send(rawcan.encode(0x601, b"\x40\x00\x10\x00\x00\x00\x00\x00", False))
        theirs.send(rawcan.encode(0x701, b"", True))
        assert raw.recv(1.0)[:2] == (0x601, b"\x40\x00\x10\x00\x00\x00\x00\x00")
        assert raw.recv(0.0)[:2] == (0x701 | rawcan.CAN_RTR_FLAG, b"")
        raw.send(0x581, b"\x43\x00\x10\x00\x92\x01\x02\x00", False)
        assert theirs.recv(100) == rawcan.encode(0x581, b"\x43\x00\x10\x00\x92\x01\x02\x00", False)
        theirs.setblocking(False)
        mine.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
        with pytest.raises(OSError):  # no room: an error, never a wait
            for _ in range(100000):
                raw.send(0x181, b"\x00" * 8, False)
    finally:
        mine.close()
        theirs.close()


class _PairBus(SocketcanBus):
    """python-can's SocketCAN bus on one end of a socketpair (no AF_CAN on
    this host): its own send and receive, only the socket differs."""

    def __init__(self, sock: socket.socket) -> None:  # noqa: super().__init__ would open an AF_CAN socket
        self.socket = sock
        self.channel = "pair"
        self.channel_info = "socketpair"
        self._is_filtered = False
        self._bcm_sockets = {}
        can.BusABC.__init__(self, channel="pair")

    def _apply_filters(self, filters) -> None:
        self._is_filtered = False


def test_the_simulator_serves_a_socketcan_bus_through_its_socket():
    mine, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    bus = _PairBus(mine)
    sim = Simulator(bus, [NodeConfig(1, NODE1)], tick=0.005)
    assert sim._raw is not None, "a SocketCAN bus is not read on its socket"
    theirs.settimeout(5.0)

    def answer(request_cob: int, request: bytes, remote: bool = False, expect: int = 0x581) -> bytes:
        theirs.send(rawcan.encode(request_cob, request, remote))
        for _ in range(100):  # passes of the loop, each waiting at most a tick
            sim.run(passes=1)
            try:
                while True:
                    can_id, _, _, data = pcan.dissect_can_frame(theirs.recv(100, socket.MSG_DONTWAIT))
                    if can_id & 0x7FF == expect:
                        return data
            except BlockingIOError:
                continue
        raise AssertionError("no answer on 0x%03X" % expect)
    try:
        assert answer(0x000, bytes([0x81, 1]), expect=0x701) == b"\x00"  # reset node: boot-up
        device_type = sim.nodes[1].store.get(0x1000, 0)
        assert answer(0x601, struct.pack("<BHB4x", 0x40, 0x1000, 0)) == \
            struct.pack("<BHBI", 0x43, 0x1000, 0, device_type)  # SDO upload
        assert answer(0x701, b"", remote=True, expect=0x701) == b"\x7f"  # node guarding: pre-operational
        assert sim.frames_in == 3 and sim.frames_out >= 3
    finally:
        sim.stop()
        bus.shutdown()
        theirs.close()
