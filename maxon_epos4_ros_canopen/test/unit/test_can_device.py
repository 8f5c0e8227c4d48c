"""bus/device names any adapter python-can supports: SocketCAN names, and
INTERFACE:CHANNEL forms with a bit rate where the adapter takes one."""
from __future__ import annotations

import time
import uuid
from pathlib import Path

import can
import pytest

from maxon_epos4_ros_canopen import can_device
from maxon_epos4_ros_canopen.can_device import ArrivalClock, CanDeviceError, open_device, parse_device
from maxon_epos4_ros_canopen.config import ConfigError, load_config
from maxon_epos4_ros_canopen.driver.bus import open_bus


@pytest.mark.parametrize("device, expected", [
    ("can0", ("socketcan", "can0")),
    ("vcan0", ("socketcan", "vcan0")),
    ("socketcan:can1", ("socketcan", "can1")),
    ("pcan:PCAN_USBBUS1", ("pcan", "PCAN_USBBUS1")),
    ("ixxat:0", ("ixxat", "0")),
    ("kvaser:0", ("kvaser", "0")),
    ("slcan:/dev/ttyACM0", ("slcan", "/dev/ttyACM0")),
    ("slcan:/dev/ttyACM0@115200", ("slcan", "/dev/ttyACM0@115200")),
    ("virtual:bench", ("virtual", "bench")),
])
def test_device_forms(device, expected):
    assert parse_device(device) == expected


@pytest.mark.parametrize("device, message", [
    ("", "empty name"),
    ("foo:0", "unknown interface 'foo'"),
    ("pcan:", "no channel after 'pcan:'"),
])
def test_bad_device_names_are_named_in_the_error(device, message):
    with pytest.raises(CanDeviceError, match=message) as info:
        parse_device(device)
    assert repr(device) in str(info.value)


def test_virtual_form_carries_frames_between_two_opened_buses():
    channel = "can_device_" + uuid.uuid4().hex[:8]
    a, b = open_device("virtual:" + channel), open_device("virtual:" + channel)
    try:
        a.send(can.Message(arbitration_id=0x701, data=b"\x05", is_extended_id=False))
        got = b.recv(timeout=5.0)
        assert got is not None and got.arbitration_id == 0x701 and bytes(got.data) == b"\x05"
    finally:
        a.shutdown()
        b.shutdown()


PKG = Path(__file__).resolve().parents[2]


def layers(bus):
    return {"bus": bus, "sync": {"interval_ms": 10},
            "nodes": {"node1": {"id": 1, "eds_file": str(PKG / "config" / "epos4_node1.dcf")}}}


def test_bus_layer_with_bitrate_opens_through_open_bus():
    channel = "can_device_" + uuid.uuid4().hex[:8]
    cfg = load_config(layers({"device": "virtual:" + channel, "bitrate": 500000}), "test", lambda p: "/")
    assert cfg.bus.bitrate == 500000 and cfg.bus.device == "virtual:" + channel
    bus = open_bus(cfg.bus)
    try:
        assert bus.channel_info  # an opened python-can bus
    finally:
        bus.shutdown()


@pytest.mark.parametrize("device", ["pcan:PCAN_USBBUS1", "ixxat:0", "kvaser:0", "slcan:/dev/ttyACM0"])
def test_missing_adapter_is_a_clear_error_naming_the_device(device):
    # None of these adapters (nor their vendor libraries) exist on the test machines.
    with pytest.raises(CanDeviceError) as info:
        open_device(device, 1000000)
    assert str(info.value).startswith("CAN device %r (python-can interface %s" % (device, device.split(":")[0]))


def test_missing_socketcan_interface_names_it():
    with pytest.raises(CanDeviceError, match="'vcan9'"):
        open_device("vcan9")


def test_config_rejects_unknown_interface_and_odd_bitrate():
    with pytest.raises(ConfigError, match="bus/device.*unknown interface 'usb'"):
        load_config(layers({"device": "usb:0"}), "test", lambda p: "/")
    with pytest.raises(ConfigError, match="bus/bitrate.*not a CANopen bit rate"):
        load_config(layers({"device": "pcan:PCAN_USBBUS1", "bitrate": 300000}), "test", lambda p: "/")


def test_bitrate_on_socketcan_is_reported_as_ignored():
    cfg = load_config(layers({"device": "can0", "bitrate": 1000000}), "test", lambda p: "/")
    assert any("bus/bitrate ignored for can0" in w for w in cfg.warnings)


def test_a_receive_buffer_is_enlarged_to_hold_a_second_of_a_full_bus():
    """The kernel's default socket receive buffer holds a few hundred CAN
    frames: a process the host leaves unscheduled longer loses the rest.
    Where the process may (root, CAP_NET_ADMIN) the buffer goes beyond
    net.core.rmem_max; elsewhere up to it, never smaller than it was."""
    import os
    import socket
    from maxon_epos4_ros_canopen.can_device import RECEIVE_BUFFER_BYTES, enlarge_receive_buffer
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:  # the same option on any socket
        before = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        granted = enlarge_receive_buffer(sock)
        assert granted == sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        assert granted >= before
        if os.geteuid() == 0:
            assert granted >= RECEIVE_BUFFER_BYTES


def test_arrival_clock_counts_the_time_a_frame_waited_in_the_socket():
    clock = ArrivalClock()
    read_at = time.monotonic()
    assert clock.arrival(time.time() - 0.2, read_at) == pytest.approx(read_at - 0.2, abs=0.01)
    # a stamp of another clock (an adapter's own) says nothing: read on arrival
    assert clock.arrival(12.0, read_at) == read_at
    assert clock.arrival(time.time() + 3.0, read_at) == read_at


def test_arrival_clock_reads_the_wall_clock_once_a_second_and_follows_a_step(monkeypatch):
    """A clock read is a system call on some hosts (user-mode Linux): not
    one per frame. A wall clock stepped meanwhile is followed at the next
    refresh."""
    wall = [1000.0]
    mono = [50.0]
    wall_reads = []

    def read_wall():
        wall_reads.append(wall[0])
        return wall[0]
    monkeypatch.setattr(can_device.time, "time", read_wall)
    clock = ArrivalClock(clock=lambda: mono[0])
    for i in range(1000):  # frames 0.5 ms apart, each stamped 0.1 s before it is read
        mono[0] = 50.0 + i * 0.0005
        wall[0] = 1000.0 + i * 0.0005
        assert clock.arrival(wall[0] - 0.1, mono[0]) == pytest.approx(mono[0] - 0.1)
    assert len(wall_reads) == 1
    wall[0] += 3600.0  # the wall clock stepped an hour ahead; its stamps with it
    mono[0] += ArrivalClock.REFRESH_S + 0.1
    assert clock.arrival(wall[0] - 0.1, mono[0]) == pytest.approx(mono[0] - 0.1)
    assert len(wall_reads) == 2


def test_a_host_stamped_bus_tells_a_backlog_of_many_seconds():
    """SocketCAN and the virtual bus stamp frames with this host's wall clock:
    a frame 20 s late is a backlog (a host far behind), not another clock;
    elsewhere more than 5 s is taken for an adapter's own clock."""
    bus = can.Bus(interface="virtual", channel="lag_" + uuid.uuid4().hex)
    try:
        assert can_device.max_receive_lag(bus) == can_device.HOST_STAMPED_MAX_LAG
    finally:
        bus.shutdown()
    read_at = time.monotonic()
    host = ArrivalClock(max_lag=can_device.HOST_STAMPED_MAX_LAG)
    assert host.arrival(time.time() - 20.0, read_at) == pytest.approx(read_at - 20.0, abs=0.01)
    assert ArrivalClock().arrival(time.time() - 20.0, read_at) == read_at


def test_arrival_clock_does_not_take_a_wall_clock_stepped_back_for_a_long_wait(monkeypatch):
    """A wall clock stepped back (NTP) between two reads of the offset would
    make every frame look seconds late, and a heartbeat watchdog trip: a
    frame that seems to have waited long has the offset read again first."""
    wall, mono = [1000.0], [50.0]
    monkeypatch.setattr(can_device.time, "time", lambda: wall[0])
    clock = ArrivalClock(clock=lambda: mono[0], max_lag=can_device.HOST_STAMPED_MAX_LAG)
    assert clock.arrival(wall[0] - 0.01, mono[0]) == pytest.approx(mono[0] - 0.01)
    mono[0] += 0.3
    wall[0] += 0.3 - 3.0  # stepped 3 s back; the kernel stamps by the new wall clock
    assert clock.arrival(wall[0] - 0.01, mono[0]) == pytest.approx(mono[0] - 0.01)

