"""bus_watch, the end-to-end tests' eyes on the bus: the polling wait, the
frame recorder and the SDO observer, over python-can's virtual bus."""
import itertools
import os
import struct

import can
import canopen
import pytest
from canopen.sdo.exceptions import SdoError

from maxon_epos4_ros_canopen.bus_watch import FrameRecorder, SdoObserver, poll

_channels = itertools.count()


@pytest.fixture
def channel():
    return "bus_watch_%d_%d" % (os.getpid(), next(_channels))


def test_poll_returns_as_soon_as_the_condition_holds():
    calls = []
    assert poll(lambda: calls.append(1) or len(calls) >= 3, timeout=30.0, step=0.0)
    assert len(calls) == 3


def test_poll_asks_once_more_at_the_deadline_and_gives_up_when_told():
    assert poll(lambda: False, timeout=0.0) is False
    assert poll(lambda: True, timeout=0.0) is True  # true at the deadline counts
    asked = []
    assert poll(lambda: asked.append(1) or False, timeout=30.0, stop=lambda: True) is False
    assert len(asked) == 1


def test_poll_counts_an_ignored_exception_as_not_yet():
    answers = iter([SdoError("no answer"), struct.error("short"), True])

    def drive_answers():
        a = next(answers)
        if isinstance(a, Exception):
            raise a
        return a

    assert poll(drive_answers, timeout=30.0, step=0.0, ignore=(SdoError, struct.error))
    with pytest.raises(ValueError):
        poll(lambda: int("x"), timeout=0.0, ignore=(SdoError,))


def test_recorder_keeps_frames_in_order_and_flush_proves_it_has_all(channel):
    sender = can.Bus(interface="virtual", channel=channel)
    sender.send(can.Message(arbitration_id=0x111, data=b"\x00", is_extended_id=False))  # before start: drained
    rec = FrameRecorder(can.Bus(interface="virtual", channel=channel), marker_id=0x7FF,
                        marker_bus=lambda: can.Bus(interface="virtual", channel=channel)).start()
    try:
        for i in range(200):
            sender.send(can.Message(arbitration_id=0x180 + (i % 3), data=bytes([i]), is_extended_id=False))
        assert rec.flush(timeout=30.0)
        frames = rec.snapshot()
        assert [f.data[0] for f in frames] == list(range(200))  # markers never show
        assert len(rec.arrivals) == 200
        assert [f.data[0] for f in rec.with_id(0x181)] == list(range(1, 200, 3))
        assert [f.data[0] for f in rec.matching(lambda f: f.arbitration_id == 0x182, 2, timeout=1.0)] == [2, 5]
        assert rec.matching(lambda f: f.arbitration_id == 0x999, 1, timeout=0.0) is None
        assert len(rec.take()) == 200 and rec.snapshot() == [] and rec.arrivals == []
        sender.send(can.Message(arbitration_id=0x222, data=b"\x01", is_extended_id=False))
        assert [f.arbitration_id for f in rec.stop()] == [0x222]
    finally:
        rec.close()
        sender.shutdown()


def test_flush_without_a_marker_is_a_clear_error(channel):
    rec = FrameRecorder(can.Bus(interface="virtual", channel=channel))
    try:
        with pytest.raises(ValueError):
            rec.flush(timeout=0.0)
    finally:
        rec.close()


def test_sdo_observer_reads_the_drive_and_names_what_did_not_answer(channel):
    server_net = canopen.Network()
    server_net.connect(interface="virtual", channel=channel)
    od = canopen.ObjectDictionary()
    var = canopen.objectdictionary.ODVariable("Velocity actual value", 0x606C, 0)
    var.data_type = canopen.objectdictionary.INTEGER32
    var.access_type = "ro"
    od.add_object(var)
    drive = canopen.LocalNode(3, od)
    server_net.add_node(drive)
    drive.sdo[0x606C].raw = -300
    client_net = canopen.Network()
    client_net.connect(interface="virtual", channel=channel)
    observer = SdoObserver(network=client_net, response_timeout=0.2)
    try:
        assert observer.read(3, 0x606C, signed=True) == -300
        assert observer.try_read(3, 0x606C, signed=False) == 2 ** 32 - 300
        assert observer.try_read(4, 0x606C) is None  # nobody answers for node 4
        with pytest.raises(AssertionError, match=r"node 4 0x606C/0 failed \(2 attempts\)"):
            observer.read(4, 0x606C, attempts=2, pause=0.0)
    finally:
        observer.close()  # not its network: the caller's to close
        client_net.disconnect()
        server_net.disconnect()
