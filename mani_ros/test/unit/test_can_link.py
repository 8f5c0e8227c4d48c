"""A node's CAN connection (CanLink) over python-can's virtual bus: valid
messages reach the node, garbage and failing handlers never stop it."""
import itertools
import queue
import random

import can
import pytest

from mani_ros import protocol as p
from mani_ros.can_link import CanLink

_channels = itertools.count()


@pytest.fixture
def link_and_peer(request):
    channel = "mani_link_%s_%d" % (request.node.name, next(_channels))
    peer = can.Bus(interface="virtual", channel=channel)
    messages, problems = queue.Queue(), queue.Queue()
    handler = {"fn": messages.put}
    link = CanLink(channel, "virtual", on_message=lambda m: handler["fn"](m),
                   on_problem=problems.put,
                   bus=can.Bus(interface="virtual", channel=channel))
    yield link, peer, messages, problems, handler
    link.shutdown()
    peer.shutdown()


def send(peer, message):
    peer.send(p.to_can_message(message))


def test_valid_messages_reach_the_node_and_sent_ones_reach_the_bus(link_and_peer):
    link, peer, messages, _, _ = link_and_peer
    send(peer, p.LocomotionFb(p.REAR_LEFT, True))
    assert messages.get(timeout=5) == p.LocomotionFb(p.REAR_LEFT, True)
    link.send(p.VelocityCmd(p.FRONT_RIGHT, -300))
    frame = peer.recv(timeout=5)
    assert (frame.arbitration_id, bytes(frame.data)) == (0x0C4, bytes.fromhex("d4fe"))  # one int16, data length 2


def test_garbage_is_counted_and_reported_not_raised(link_and_peer):
    link, peer, messages, problems, _ = link_and_peer
    rng = random.Random(7)
    sent_valid = 0
    for _ in range(3000):
        can_id = rng.randrange(0x0F0)
        data = bytes(rng.randrange(256) for _ in range(rng.randrange(9)))
        try:
            p.decode(can_id, data)
            sent_valid += 1
        except p.ProtocolError:
            pass
        peer.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))
    send(peer, p.PowerFb(True))
    received = []
    while True:
        message = messages.get(timeout=10)
        received.append(message)
        if message == p.PowerFb(True) and len(received) == sent_valid + 1:
            break
    assert link.rejected == 3000 - sent_valid and link.received == sent_valid + 1
    assert "ignored frame" in problems.get(timeout=1)


def test_a_failing_handler_does_not_stop_reception(link_and_peer):
    link, peer, messages, problems, handler = link_and_peer

    def broken(message):
        raise RuntimeError("node bug")

    handler["fn"] = broken
    send(peer, p.PowerFb(False))
    assert "handling powerFb motor_power=False failed: node bug" in problems.get(timeout=5)
    handler["fn"] = messages.put
    send(peer, p.PowerFb(True))
    assert messages.get(timeout=5) == p.PowerFb(True)
    assert link.handler_errors == 1
