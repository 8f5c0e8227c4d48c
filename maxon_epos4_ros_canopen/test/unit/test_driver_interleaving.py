"""Every interleaving of a command with the cycle, line by line.

The cycle thread is traced (sys.settrace through threading.settrace): at the
k-th line of driver code it runs in a chosen cycle it stops, the test thread
sends a command, and the cycle goes on. k walks over every line a cycle runs,
in each cycle of a profile position set-point handshake. After each
interleaving the drive's own 0x607A (read from the simulator) must become
the command: a command that arrives while the cycle is anywhere in its work
is never lost, the last one wins."""
import os
import threading

import pytest

from maxon_epos4_ros_canopen.driver import core
from test_driver import J1, Rig, ppm_ready, until

DRIVER_DIR = os.path.dirname(os.path.abspath(core.__file__))

CYCLE_THREAD = "epos4_driver_cycle"
HANDSHAKE_CYCLES = 4  # profile position: target, edge, acknowledge, edge cleared


class CycleStepper:
    """Stops the cycle thread at one line of one cycle until released."""

    def __init__(self):
        self.cycle_code = core.Driver.cycle.__code__
        self.armed = None          # [cycles to go, line number in that cycle]
        self.lines_in_cycle = 0
        self.paused = threading.Event()
        self.resume = threading.Event()
        self.max_lines = 0

    def arm(self, cycle_offset, line):
        self.paused.clear()
        self.resume.clear()
        self.missed = False
        self.armed = [cycle_offset, line]

    def global_trace(self, frame, event, arg):
        # threading.settrace reaches every thread init starts: the CAN
        # notifier's lines must neither count nor be stopped at
        if threading.current_thread().name != CYCLE_THREAD:
            return None
        code = frame.f_code
        if code is self.cycle_code:
            # a new cycle begins
            self.max_lines = max(self.max_lines, self.lines_in_cycle)
            self.lines_in_cycle = 0
            armed = self.armed
            if armed is not None:
                if armed[0] == 0:
                    # the aimed-at cycle ended before that line
                    self.armed = None
                    self.missed = True
                    self.paused.set()
                else:
                    armed[0] -= 1
            return self.local_trace
        if code.co_filename.startswith(DRIVER_DIR):
            return self.local_trace
        return None

    def local_trace(self, frame, event, arg):
        if event != "line":
            return self.local_trace
        self.lines_in_cycle += 1
        armed = self.armed
        if armed is not None and armed[0] == 0 and self.lines_in_cycle == armed[1]:
            self.armed = None
            self.paused.set()
            self.resume.wait(30.0)
        return self.local_trace


@pytest.fixture
def stepped(request):
    stepper = CycleStepper()
    threading.settrace(stepper.global_trace)   # the cycle thread starts at init
    rig = Rig("interleave_" + request.node.name)
    try:
        # a short cycle: the handshake after each interleaving takes a few
        d = ppm_ready(rig, sync={"interval_ms": 5, "overflow": 0})
    finally:
        threading.settrace(None)
    yield rig, d, stepper
    rig.close()


def test_a_command_at_any_line_of_any_handshake_cycle_is_never_lost(stepped):
    rig, d, stepper = stepped
    start = rig.read(0x6064)
    assert until(lambda: stepper.max_lines > 0)
    value = start
    results = []
    cycles_before = d.cycles
    assert until(lambda: d.cycles > cycles_before + 2)
    lines = stepper.max_lines
    assert lines > 50  # the whole cycle is traced, not just its head
    for offset in range(1, HANDSHAKE_CYCLES + 1):
        for line in range(1, lines + 1):
            first, second = value + 7, value + 11
            value = second
            # one command starts a handshake; the second one arrives while
            # the cycle `offset` cycles later is stopped at `line`
            assert d.set_command(J1, "position", first).success
            stepper.arm(offset, line)
            assert stepper.paused.wait(10.0)
            paused = not stepper.missed   # False: that cycle had fewer lines
            answer = d.set_command(J1, "position", second)
            stepper.resume.set()
            assert answer.success, answer.message
            reached = until(lambda: rig.read(0x607A) == second, 10.0)
            results.append((offset, line, paused))
            a = d.joints[J1]
            assert reached, ("command lost", offset, line, rig.read(0x607A), second, a.command_value,
                             a.last_refusal, dict(a.counters), hex(a.statusword))
    # the later cycles of a handshake run fewer lines: most interleavings
    # still happened inside the cycle they aimed at
    assert sum(1 for r in results if r[2]) >= 0.5 * len(results)
