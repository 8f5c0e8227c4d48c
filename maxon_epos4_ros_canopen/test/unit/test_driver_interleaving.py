"""Every interleaving of a command with the cycle, line by line.

The cycle is traced (sys.settrace on the thread that runs it: the stepped
clock's, which is the test's): at the k-th line of driver code it runs in a
chosen cycle, the cycle stops while another thread sends a command, and
goes on once that call returned. k walks over every line a cycle runs, in
each cycle of a profile position set-point handshake. After each
interleaving the drive's own 0x607A (read from the simulator) must become
the command: a command that arrives while the cycle is anywhere in its work
is never lost, the last one wins.

On virtual time each interleaving is the same on every run; the threads of
a real host against the cycle are test_driver_adversary.py's
(docs/testing.md). SEARCH_SHARE (search_share.py) may take every N-th line
of each cycle, a different one in each."""
import os
import sys
import threading

import pytest

from driver_support import J1, ppm_ready
from search_share import every_nth
from maxon_epos4_ros_canopen.driver import cycle

DRIVER_DIR = os.path.dirname(os.path.abspath(cycle.__file__))

HANDSHAKE_CYCLES = 4  # profile position: target, edge, acknowledge, edge cleared
CALL_TIMEOUT = 30.0  # a command that blocks on the stopped cycle: a defect, reported


def from_another_thread(fn):
    """fn() on a thread of its own, as a ROS callback calls the driver; its
    answer. The cycle's own thread would apply a command at once."""
    out = []
    caller = threading.Thread(target=lambda: out.append(fn()), name="command_caller")
    caller.start()
    caller.join(CALL_TIMEOUT)
    assert not caller.is_alive(), "a command blocked while the cycle stood still"
    return out[0]


class CycleStepper:
    """At one line of one cycle, runs ``action`` on another thread while the
    cycle stands still."""

    def __init__(self):
        self.run_code = cycle.ControlCycle._run_once.__code__
        self.armed = None          # [cycles to go, line number in that cycle]
        self.action = None
        self.answer = None
        self.fired = False
        self.missed = False
        self.in_cycle = False
        self.lines_in_cycle = 0
        self.max_lines = 0
        self.measuring = True      # every cycle is traced until the first arm()

    def arm(self, cycle_offset, line, action):
        self.measuring = False
        self.fired = self.missed = False
        self.answer = None
        self.action = action
        self.armed = [cycle_offset, line]

    def _fire(self, missed):
        self.armed = None
        self.missed = missed
        self.answer = from_another_thread(self.action)
        self.fired = True

    def global_trace(self, frame, event, arg):
        code = frame.f_code
        if code is self.run_code:
            # a new cycle begins
            self.max_lines = max(self.max_lines, self.lines_in_cycle)
            self.lines_in_cycle = 0
            armed = self.armed
            if armed is not None:
                if armed[0] == 0:
                    # the aimed-at cycle ended before that line: the
                    # command comes between the two cycles
                    self._fire(missed=True)
                else:
                    armed[0] -= 1
            # only the aimed-at cycle needs its lines counted: tracing the
            # others would only slow the run down
            armed = self.armed
            self.in_cycle = self.measuring or (armed is not None and armed[0] == 0)
            return self.local_trace if self.in_cycle else None
        if self.in_cycle and code.co_filename.startswith(DRIVER_DIR):
            return self.local_trace
        return None

    def local_trace(self, frame, event, arg):
        if event == "return" and frame.f_code is self.run_code:
            self.in_cycle = False
        if event != "line":
            return self.local_trace
        self.lines_in_cycle += 1
        armed = self.armed
        if armed is not None and armed[0] == 0 and self.lines_in_cycle == armed[1]:
            self._fire(missed=False)
        return self.local_trace


@pytest.fixture
def stepped(driver_rig):
    rig = driver_rig
    # a short cycle: the handshake after each interleaving takes a few
    d = ppm_ready(rig, sync={"interval_ms": 5, "overflow": 0})
    stepper = CycleStepper()
    sys.settrace(stepper.global_trace)   # the cycle runs on this thread, in the clock's waits
    try:
        yield rig, d, stepper
    finally:
        sys.settrace(None)


def test_a_command_at_any_line_of_any_handshake_cycle_is_never_lost(stepped):
    rig, d, stepper = stepped
    start = rig.read(0x6064)
    value = start
    results = []
    cycles_before = d.cycles
    assert rig.until(lambda: d.cycles > cycles_before + 2)
    lines = stepper.max_lines
    assert lines > 50  # the whole cycle is traced, not just its head
    for offset in range(1, HANDSHAKE_CYCLES + 1):
        for line in every_nth(range(1, lines + 1), phase=offset):
            first, second = value + 7, value + 11
            value = second
            # one command starts a handshake; the second one arrives while
            # the cycle `offset` cycles later is stopped at `line`
            assert from_another_thread(lambda: d.set_command(J1, "position", first)).success
            stepper.arm(offset, line, lambda: d.set_command(J1, "position", second))
            assert rig.until(lambda: stepper.fired, 10.0)
            paused = not stepper.missed   # False: that cycle had fewer lines
            answer = stepper.answer
            assert answer.success, answer.message
            reached = rig.until(lambda: rig.read(0x607A) == second, 10.0)
            results.append((offset, line, paused))
            a = d.joints[J1]
            assert reached, ("command lost", offset, line, rig.read(0x607A), second, a.command_value,
                             a.last_refusal, dict(a.counters), hex(a.statusword))
    # the later cycles of a handshake run fewer lines: most interleavings
    # still happened inside the cycle they aimed at
    assert sum(1 for r in results if r[2]) >= 0.5 * len(results)
