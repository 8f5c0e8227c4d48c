"""100,000 random and malformed frames (a share of them under SEARCH_SHARE,
search_share.py) into the virtual EPOS4 (two nodes, one moving): no
exception in any thread, no error logged by the simulator's loop, and every
node still answers SDO afterwards."""
import logging
import struct
import threading

import can
import pytest
from canopen.sdo.exceptions import SdoCommunicationError

from search_share import share
from sim_support import NODE1, NODE2, NodeConfig, spin_up
from maxon_epos4_ros_canopen import fuzz

FRAMES = 100_000 // share()  # SEARCH_SHARE (search_share.py): a share of the storm
# How long a node may keep failing SDO after the storm (forged answers still
# queued in the client) before the test fails: generous, it only bounds how
# long a failure takes on a loaded host. Between tries the client pauses
# ASK_PAUSE: a poll interval, not a wait for anything.
ASK_TIMEOUT = 30.0
ASK_PAUSE = 0.2


class _Errors(logging.Handler):
    def __init__(self):
        super().__init__(logging.ERROR)
        self.records = []

    def emit(self, record):
        self.records.append(self.format(record))


@pytest.fixture
def thread_exceptions():
    caught = []
    previous = threading.excepthook
    threading.excepthook = lambda args: caught.append("%s in %s: %s" % (
        args.exc_type.__name__, args.thread.name if args.thread else "?", args.exc_value))
    yield caught
    threading.excepthook = previous


def test_simulator_survives_a_storm_and_still_answers_sdo(thread_exceptions, sim_rig):
    errors = _Errors()
    sim_log = logging.getLogger("maxon_epos4_ros_canopen.sim")
    sim_log.addHandler(errors)
    rig = sim_rig([NodeConfig(1, NODE1), NodeConfig(2, NODE2)])
    try:
        node1, node2 = rig.remote(1), rig.remote(2, NODE2)
        spin_up(node1, rig, 500)
        fuzzer = fuzz.FrameFuzzer(2024, node_ids=[1, 2])
        report = fuzz.send(rig.raw, fuzzer.frames(FRAMES))
        print("simulator fuzz: %s" % report.summary())
        assert report.sent == FRAMES
        standard = FRAMES - fuzzer.counts["extended"]
        assert rig.wait(lambda: rig.sim.frames_in >= standard)  # the simulator took every frame
        # The storm may have stopped or reset the nodes: bring them to
        # pre-operational, where SDO works, and ask each of them. The storm's
        # forged SDO responses may still sit in a client's queue on a loaded
        # host: a client that took one for its answer asks again.
        rig.send(0x000, bytes([0x80, 0]))

        def ask(node, index):
            # the client's own receive queue may still hold the storm's
            # backlog of forged responses for a while on a loaded host; a
            # forged answer shorter than 8 bytes makes canopen's client fail
            # to unpack it (struct.error) rather than raise an SDO error
            deadline = rig.clock.now() + ASK_TIMEOUT
            while rig.clock.now() < deadline:
                try:
                    return node.sdo[index].raw
                except (SdoCommunicationError, struct.error):
                    rig.clock.sleep(ASK_PAUSE)
            return node.sdo[index].raw
        for node in (node1, node2):
            node.sdo.RESPONSE_TIMEOUT = 5.0
            assert ask(node, 0x1000) == 0x00020192
            assert ask(node, 0x6041) & 0x0200  # a statusword, remote bit set
        ticks = rig.sim.ticks  # the simulator still runs: its tick goes on
        assert rig.wait(lambda: rig.sim.ticks > ticks + 2)
    finally:
        rig.close()
        sim_log.removeHandler(errors)
    assert thread_exceptions == []
    assert errors.records == []
