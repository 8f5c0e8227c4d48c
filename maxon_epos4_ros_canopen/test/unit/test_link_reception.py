"""The notifier's one listener (link._Reception): what ReceiveClock,
canopen's MessageListener and _ReceiveErrors did as three listeners, in
their order, in one call."""
import logging

import can
import canopen

from maxon_epos4_ros_canopen.clock import SteppedClock
from maxon_epos4_ros_canopen.driver.bus import ReceiveClock
from maxon_epos4_ros_canopen.driver.link import _Reception


class FakeNotifier:
    exception = None


def reception():
    clock = SteppedClock(100.0)
    network = canopen.Network()
    stamps = ReceiveClock(clock=clock)
    r = _Reception(stamps, network, clock)
    r._notifier = FakeNotifier()
    return r, network, stamps, clock


def frame(can_id, data=b"\x01\x02", **kw):
    return can.Message(arbitration_id=can_id, data=data, is_extended_id=False, timestamp=0.0, **kw)


def test_subscribers_get_each_frame_after_it_was_stamped_and_the_scanner_sees_it():
    r, network, stamps, _ = reception()
    got = []
    network.subscribe(0x181, lambda can_id, data, ts: got.append((can_id, bytes(data), stamps.progress)))
    network.subscribe(0x181, lambda can_id, data, ts: got.append("second"))
    r(frame(0x181))
    assert got[0][:2] == (0x181, b"\x01\x02") and got[0][2] == stamps.progress and got[1] == "second"
    r.on_message_received(frame(0x281))  # nobody subscribed: nothing, no error
    assert 1 in network.scanner.nodes


def test_a_later_subscription_counts():
    r, network, _, _ = reception()
    got = []
    r(frame(0x701, b"\x05"))
    network.subscribe(0x701, lambda can_id, data, ts: got.append(bytes(data)))
    r(frame(0x701, b"\x05"))
    assert got == [b"\x05"]


def test_error_and_remote_frames_reach_no_subscriber_but_are_stamped():
    r, network, stamps, _ = reception()
    got = []
    network.subscribe(0x181, lambda *a: got.append(a))
    stamps.progress = (-1.0, -1.0)
    r(frame(0x181, is_error_frame=True))
    assert stamps.progress != (-1.0, -1.0)  # stamped all the same, as ReceiveClock was before
    r(frame(0x181, data=b"", is_remote_frame=True))
    assert got == []


def test_a_failing_subscriber_is_logged_and_the_next_frame_handled(caplog):
    r, network, _, _ = reception()
    got = []

    def bad(*_):
        raise ValueError("subscriber broke")
    network.subscribe(0x181, bad)
    network.subscribe(0x281, lambda can_id, data, ts: got.append(can_id))
    with caplog.at_level(logging.ERROR, logger="canopen.network"):
        r(frame(0x181))
    assert "subscriber broke" in caplog.text
    r(frame(0x281))
    assert got == [0x281]


def test_a_receive_error_is_handled_and_cleared_for_canopen():
    r, _, _, _ = reception()
    r._notifier.exception = OSError("interface down")
    r.on_error(OSError("interface down"))
    assert r._notifier.exception is None


def test_the_receive_lag_is_the_latest_frames_wait_while_frames_still_wait_and_none_once_all_are_read():
    """receive_lag_ms in diagnostics: a notifier that read a frame 0.5 s
    after it arrived is 0.5 s behind while frames still wait unread; once
    it has read everything that came, it is behind by nothing, whatever the
    last frame's wait was (a bus that went quiet after a storm must not
    show the storm's backlog for ever). Where the adapter cannot tell what
    waits, the latest frame's wait is all there is."""
    clock = SteppedClock(100.0)
    waiting = [True]
    stamps = ReceiveClock(lambda: waiting[0], clock=clock)
    clock.advance(1.0)
    stamps.on_message_received(frame_at(clock.wall() - 0.5))
    assert abs(stamps.lag() - 0.5) < 1e-6
    waiting[0] = False
    assert stamps.lag() == 0.0
    blind = ReceiveClock(None, clock=clock)
    blind.on_message_received(frame_at(clock.wall() - 0.5))
    assert abs(blind.lag() - 0.5) < 1e-6
    assert not blind.unread_before(clock.now() + 1.0)  # nothing known to wait: an SDO timeout counts as read


def frame_at(stamp):
    return can.Message(arbitration_id=0x581, data=b"\x01", is_extended_id=False, timestamp=stamp)
