"""The virtual EPOS4's motion, computed once per tick in one loop
(VirtualEpos4._cycles, MotorModel.cycle), against the way it was computed
before (sim_reference.py: a call per control cycle and the motor's
sub-steps): two drives, the new and the reference, take the same random
command sequences on simulated time, and must answer with the same frames
at the same moments and hold the same object dictionary, power state and
motor state after every command, bit for bit (no tolerance: the same
arithmetic in the same order gives the same floats).

A sequence mixes what a master and a test do to a drive: enabling it in
each mode, targets and profile parameters, new set-points, halt, quick
stop, disable, fault reset, small following-error windows and software
limits that trip, RxPDOs, SYNCs, NMT commands, heartbeats and the heartbeat
consumer, SDO reads, fault injection (EMCY, reboot, silence, SDO delay,
corrupted frame), hard stops for homing; time advances by ticks and SYNCs
of uneven length, including steps just over a whole number of control
cycles (where the motor splits a cycle) and beyond the longest step.
SEARCH_SHARE (search_share.py) may take every N-th sequence.

The simulator's loop pass (Simulator.step: frames as tuples straight to
the nodes, fewer clock readings) is held the same way to the pass as it
was (sim_reference.ReferenceSimulator): both serve the same random bus
traffic on a scripted clock and bus (frames readable at scripted times,
some delivered late; a wait moves the clock), and must send the same
frames at the same moments and end in the same state."""
import math
import random
import struct
from typing import Any, Callable, List, Tuple

import can
import pytest

from maxon_epos4_ros_canopen.sim import NodeConfig, Simulator
from maxon_epos4_ros_canopen.sim.drive import VirtualEpos4
from maxon_epos4_ros_canopen.sim.objects import load_od
from sim_reference import ReferenceEpos4, ReferenceSimulator
from search_share import every_nth
from sim_support import NODE1, NODE1_HM, WALL_OFFSET, ScriptedClock

SEQUENCES = 160
COMMANDS = 220
MODES = (1, 3, 6, 8, 9, 10, 0, -1)
CONTROLWORDS = (0x0006, 0x0007, 0x000F, 0x001F, 0x003F, 0x005F, 0x007F, 0x010F, 0x011F, 0x0002,
                0x000B, 0x0000, 0x0080, 0x0086, 0x000F | 0x8000)
# (index, sub, values to choose from, or (lo, hi) for a random integer)
OBJECTS: List[Tuple[int, int, Any]] = [
    (0x607A, 0, (-60000, 60000)), (0x60FF, 0, (-6000, 6000)), (0x6071, 0, (-1500, 1500)),
    (0x6081, 0, (0, 8000)), (0x6083, 0, (1, 40000)), (0x6084, 0, (1, 40000)), (0x6085, 0, (1, 60000)),
    (0x607F, 0, (100, 9000)), (0x6080, 0, (100, 9000)), (0x60B1, 0, (-500, 500)), (0x60B2, 0, (-200, 200)),
    (0x6065, 0, [5, 50, 500, 20000, 0xFFFFFFFF]), (0x6067, 0, [1, 20, 0xFFFFFFFF]), (0x6068, 0, [0, 5, 30]),
    (0x607D, 1, [-2 ** 31, -30000, 0]), (0x607D, 2, [2 ** 31 - 1, 30000, 0]),
    (0x605A, 0, [0, 1, 2, 5, 6]), (0x605E, 0, [0, 1, 2]), (0x605B, 0, [0, 1]), (0x605C, 0, [0, 1]),
    (0x6007, 0, [0, 1, 2, 3]), (0x6098, 0, [35, 37, -3, -4, 1]), (0x6099, 1, (10, 2000)),
    (0x6099, 2, (5, 500)), (0x609A, 0, (100, 20000)), (0x30B1, 0, (0, 3000)), (0x30B2, 0, (100, 2000)),
    (0x30B0, 0, (-1000, 1000)), (0x60C2, 1, [0, 5, 10, 20]), (0x1017, 0, [0, 20, 50]),
    (0x1016, 1, [0, 0x007F0064, 0x007F0032]), (0x1029, 1, [0, 1, 2]), (0x1005, 0, [0x80]),
]
READS = [(0x6064, 0), (0x6041, 0), (0x606C, 0), (0x6062, 0), (0x60F4, 0), (0x6077, 0), (0x1003, 1), (0x603F, 0)]


def _bits(x: Any) -> Any:
    """A float as its bits (-0.0 and 0.0 differ, NaN equals itself); anything else as it is."""
    return struct.pack("<d", x) if isinstance(x, float) else x


def _snapshot(node: VirtualEpos4) -> tuple:
    m, d = node.motor, node.demand
    floats = (m.position, m.velocity, m.current, node.offset, node.t, d.position, d.velocity,
              d.acceleration, d.current, node.sync_interval)
    return (tuple(_bits(x) for x in floats), m.blocked, node.state, node.stopping, node.mode,
            node.following_error, node.quick_stop_done, node.referenced, node.nmt_state,
            sorted((k, _bits(v)) for k, v in node.store.values.items()))


class Pair:
    """The new drive and the reference drive, fed the same, compared after each command."""

    def __init__(self, dcf: str, hard_stop) -> None:
        od = load_od(dcf, 1)
        self.now = 0.0
        self.logs: Tuple[List[tuple], List[tuple]] = ([], [])
        self.nodes = [cls(1, od, self._transport(log), self.now, hard_stop=hard_stop)
                      for cls, log in ((VirtualEpos4, self.logs[0]), (ReferenceEpos4, self.logs[1]))]

    def _transport(self, log: List[tuple]) -> Callable[[int, bytes, bool], None]:
        return lambda cob, data, remote: log.append((self.now, cob, bytes(data), remote))

    def each(self, action: Callable[[VirtualEpos4], Any]) -> None:
        for node in self.nodes:
            action(node)

    def check(self, history: List[str]) -> None:
        new, ref = self.nodes
        if self.logs[0] != self.logs[1] or _snapshot(new) != _snapshot(ref):
            sent = [(a, b) for a, b in zip(self.logs[0], self.logs[1]) if a != b][:3]
            pytest.fail("the new motion differs from the reference after:\n  %s\nframes (new, reference): %s%s\n"
                        "state (new): %s\nstate (reference): %s" % (
                            "\n  ".join(history[-8:]), sent,
                            "" if len(self.logs[0]) == len(self.logs[1]) else
                            " and %d against %d frames" % (len(self.logs[0]), len(self.logs[1])),
                            _snapshot(new)[:9], _snapshot(ref)[:9]))


def _sdo_write(node: VirtualEpos4, now: float, index: int, sub: int, value: int) -> None:
    var = node.store.vars.get((index, sub))
    if var is None:
        return
    try:
        raw = var.encode_raw(value)
    except Exception:  # outside the type: a master could not send it either
        return
    command = 0x23 | ((4 - len(raw)) << 2) if len(raw) <= 4 else 0x23
    node.on_frame(0x601, struct.pack("<BHB", command, index, sub) + raw[:4].ljust(4, b"\0"), False, now)


def _value(rng: random.Random, spec: Any) -> int:
    return rng.randint(*spec) if isinstance(spec, tuple) else rng.choice(spec)


def _step(rng: random.Random) -> float:
    """A time step as the runner's ticks and SYNCs make them: mostly around
    the tick and the SYNC period, sometimes tiny, sometimes just over a whole
    number of control cycles, sometimes longer than the longest step."""
    kind = rng.random()
    if kind < 0.35:
        return rng.choice((0.0025, 0.005, 0.01, 0.002, 0.001))
    if kind < 0.45:
        return rng.choice((1, 2, 3, 4)) * 0.0025 * (1.0 + rng.choice((1e-12, 4e-13, 1e-10)))
    if kind < 0.5:
        return rng.uniform(0.02, 0.05)
    if kind < 0.55:
        return rng.uniform(1e-6, 3e-4)
    return rng.uniform(0.0003, 0.012)


def _command(pair: Pair, rng: random.Random) -> str:
    """One random command, applied to both drives; returns what it was."""
    kind = rng.random()
    now = pair.now
    if kind < 0.22:
        dt = _step(rng)
        pair.now += dt
        pair.each(lambda n: n.tick(pair.now))
        return "tick +%r" % dt
    if kind < 0.40:
        dt = _step(rng)
        pair.now += dt
        pair.each(lambda n: n.on_sync(pair.now))
        return "SYNC +%r" % dt
    if kind < 0.46:
        mode = rng.choice(MODES)
        cws = [0x0006, 0x0007, 0x000F] if rng.random() < 0.8 else [0x0080, 0x0006, 0x0007, 0x000F]
        for index, value in [(0x6060, mode)] + [(0x6040, cw) for cw in cws]:
            pair.each(lambda n: _sdo_write(n, now, index, 0, value))
        return "enable in mode %d" % mode
    if kind < 0.60:
        cw = rng.choice(CONTROLWORDS)
        pair.each(lambda n: _sdo_write(n, now, 0x6040, 0, cw))
        return "controlword 0x%04X" % cw
    if kind < 0.78:
        index, sub, spec = rng.choice(OBJECTS)
        value = _value(rng, spec)
        pair.each(lambda n: _sdo_write(n, now, index, sub, value))
        return "write 0x%04X:%d = %d" % (index, sub, value)
    if kind < 0.82:
        index, sub = rng.choice(READS)
        request = struct.pack("<BHB4x", 0x40, index, sub)
        pair.each(lambda n: n.on_frame(0x601, request, False, now))
        return "read 0x%04X:%d" % (index, sub)
    if kind < 0.88:
        rpdo = rng.randrange(4)
        values = []
        for key in pair.nodes[0].pdos.rpdos[rpdo].keys:
            if key == (0x6040, 0):
                values.append(rng.choice(CONTROLWORDS))
            elif key == (0x6060, 0):
                values.append(rng.choice(MODES))
            else:
                index, sub, spec = next((o for o in OBJECTS if o[:2] == key), (0, 0, (0, 1000)))
                values.append(_value(rng, spec))
        pdo = pair.nodes[0].pdos.rpdos[rpdo]
        if not pdo.valid:
            return "RxPDO %d: not valid" % (rpdo + 1)
        try:
            data = pdo.codec.pack(*values)
        except struct.error:
            return "RxPDO %d: values outside its types" % (rpdo + 1)
        if rng.random() < 0.05:
            data = data[:-1]  # too short: a PDO length error
        pair.each(lambda n: n.on_frame(pdo.cob_id, data, False, now))
        return "RxPDO %d %s" % (rpdo + 1, data.hex())
    if kind < 0.92:
        command = rng.choice((0x01, 0x01, 0x01, 0x02, 0x80, 0x81, 0x82))
        pair.each(lambda n: n.on_nmt(command, now))
        return "NMT 0x%02X" % command
    if kind < 0.95:
        pair.each(lambda n: n.on_frame(0x77F, b"\x05", False, now))
        return "master heartbeat"
    fault = rng.choice(("emcy", "emcy", "reboot", "silent", "heartbeat_stop", "sdo_delay", "corrupt_frame", "clear"))
    code = rng.choice((0x8611, 0x3210, 0x1000))
    duration = rng.choice((0.0, 0.003, 0.02)) if fault != "silent" else rng.choice((0.004, 0.03))
    pair.each(lambda n: n.inject(fault, now, code, duration))
    return "inject %s 0x%04X %r" % (fault, code, duration)


@pytest.mark.parametrize("part", range(4))
def test_the_per_tick_motion_is_the_reference_motion_bit_for_bit(part):
    moved = 0
    seeds = every_nth(range(part * SEQUENCES // 4, (part + 1) * SEQUENCES // 4))
    for seed in seeds:
        rng = random.Random(seed)
        hard_stop = rng.choice((None, (-20000.0, 20000.0), (-3000.0, 500.0)))
        pair = Pair(NODE1_HM if rng.random() < 0.3 else NODE1, hard_stop)
        history: List[str] = ["seed %d, hard stop %s" % (seed, hard_stop)]
        for _ in range(COMMANDS):
            history.append(_command(pair, rng))
            pair.check(history)
        moved += abs(pair.nodes[0].motor.position) > 1.0
    # the sequences moved the rotors: the comparison was not between two
    # drives at rest (of all 160 sequences, 62-70 % of each part's move;
    # of every fourth, 40-60 %)
    assert moved >= len(seeds) // 3, (moved, len(seeds))


# ---------------------------------------------------------------- the loop
RUNS = 24
RUN_SECONDS = 1.5


class ScriptedBus(can.BusABC):
    """Frames readable at scripted times (in send order), stamped with their
    send time; a receive that waits moves the clock to the next readable
    frame or to its timeout's end, sometimes much later (the host stood
    still); the receive after a frame was taken first moves it on a little
    (the time handling that frame took). The simulator's frames go to
    ``sent``."""

    def __init__(self, clock: ScriptedClock, script: List[Tuple[float, float, int, bytes]],
                 rng: random.Random) -> None:
        self.clock = clock
        self.rng = rng
        self.handling = False  # a frame was taken: the next receive comes after its handling
        self.pending = []  # (readable at, frame)
        readable = -1.0
        for sent_at, delay, cob, data in sorted(script, key=lambda f: f[0]):
            readable = max(readable, sent_at + delay)
            self.pending.append((readable, can.Message(arbitration_id=cob, data=data, is_extended_id=False,
                                                       timestamp=sent_at + WALL_OFFSET)))
        self.sent: List[tuple] = []
        super().__init__(channel="scripted")

    def send(self, msg: can.Message, timeout=None) -> None:
        self.sent.append((self.clock.t, msg.arbitration_id, bytes(msg.data), msg.is_remote_frame))

    def recv(self, timeout=None):
        if self.handling:
            self.clock.t += self.rng.uniform(0.0, 0.0008)
        wake = self.clock.t + (timeout or 0.0)
        if timeout and self.rng.random() < 0.01:
            wake += self.rng.uniform(0.06, 0.2)  # a stall of the whole host
        self.handling = bool(self.pending) and self.pending[0][0] <= wake
        if self.handling:
            self.clock.t = max(self.clock.t, self.pending[0][0])
            return self.pending.pop(0)[1]
        self.clock.t = wake
        return None

    def _recv_internal(self, timeout):  # pragma: no cover - recv is overridden
        raise NotImplementedError


def _traffic(rng: random.Random, start: float) -> List[Tuple[float, float, int, bytes]]:
    """A master's frames for RUN_SECONDS: set-up over SDO (CSP on node 1,
    PVM on node 2, heartbeat consumer and producer), then every 10 ms
    (with jitter) a CSP target and a SYNC, heartbeats every 20 ms that
    sometimes stop, SDO reads; some frames are delivered late."""
    frames = []

    def frame(t: float, cob: int, data: bytes) -> None:
        kind = rng.random()
        delay = 0.0002 if kind < 0.9 else rng.uniform(0.001, 0.02) if kind < 0.99 else rng.uniform(0.03, 0.12)
        frames.append((t, delay, cob, data))

    t = start
    for node, mode in ((1, 8), (2, 3)):
        writes = [(0x1016, 1, "I", 0x7F << 16 | rng.choice((100, 150, 200))), (0x1017, 0, "H", rng.choice((20, 50))),
                  (0x6065, 0, "I", rng.choice((2000, 20000))), (0x6060, 0, "b", mode),
                  (0x6040, 0, "H", 6), (0x6040, 0, "H", 7), (0x6040, 0, "H", 15)]
        if mode == 3:
            writes.append((0x60FF, 0, "i", rng.randint(-2000, 2000)))
        for index, sub, fmt, value in writes:
            raw = struct.pack("<" + fmt, value)
            t += rng.uniform(0.0005, 0.003)
            frame(t, 0x600 + node, struct.pack("<BHB", 0x23 | ((4 - len(raw)) << 2), index, sub) + raw.ljust(4, b"\0"))
    t += 0.002
    frame(t, 0x000, bytes([0x01, 0]))
    sync, beat, silent_until = t + 0.005, t, 0.0
    end = start + RUN_SECONDS
    while sync < end:
        target = int(20000 * math.sin(sync - start))
        frame(sync - 0.0004, 0x301, struct.pack("<iI", target, 1000))
        frame(sync, 0x080, b"")
        while beat < sync:
            if beat >= silent_until:
                frame(beat, 0x77F, b"\x05")
            if rng.random() < 0.003:
                silent_until = beat + rng.uniform(0.05, 0.3)  # the master's heartbeat stops a while
            beat += 0.02
        if rng.random() < 0.05:
            frame(sync + 0.003, 0x601 + rng.randrange(2), struct.pack("<BHB4x", 0x40, 0x6064, 0))
        sync += 0.01 + rng.uniform(-0.002, 0.002)
    return frames


def _served(sim_class, seed: int) -> tuple:
    rng = random.Random(seed)
    clock = ScriptedClock()
    bus = ScriptedBus(clock, _traffic(rng, clock.t + 0.001), random.Random(seed))
    sim = sim_class(bus, [NodeConfig(1, NODE1), NodeConfig(2, NODE1)], tick=rng.choice((0.002, 0.005)),
                    clock=clock)
    end = clock.t + RUN_SECONDS + 0.3
    while clock.t < end:
        sim.run(passes=1)
    nodes = tuple(_snapshot(node) for node in sim.nodes.values())
    bus.shutdown()
    return bus.sent, nodes, sim.bus_time, sim.ticks, sim.frames_in, sim.frames_out


@pytest.mark.parametrize("seed", range(RUNS))
def test_the_loop_pass_serves_the_bus_as_the_reference_pass(seed):
    new, ref = _served(Simulator, seed), _served(ReferenceSimulator, seed)
    sent, reference_sent = new[0], ref[0]
    tpdos = sum(1 for _, cob, _, _ in sent if 0x181 <= cob <= 0x382)
    assert tpdos > 200 * RUN_SECONDS, "the drives hardly answered SYNCs: the traffic did not run"
    first = next((i for i, (a, b) in enumerate(zip(sent, reference_sent)) if a != b), None)
    assert first is None and len(sent) == len(reference_sent), (
        "frame %s differs: new %s, reference %s" % (first, sent[first:first + 3], reference_sent[first:first + 3])
        if first is not None else "%d frames against %d" % (len(sent), len(reference_sent)))
    assert new[1:] == ref[1:]
