#!/usr/bin/env python3
"""How many virtual EPOS4 nodes one simulator serves in real time at a 10 ms SYNC.

Runs over python-can's ``virtual`` bus in ONE process pinned to ONE core
(simulator thread + a master thread that sends, every cycle, one RxPDO2 with
a CSP target per node and a SYNC, and counts the TxPDOs 1-3 of every node).
A cycle is "complete" when all 3 x N TxPDOs of a SYNC arrive before the next
SYNC.  Prints, per node count: complete cycles, SYNC->last TxPDO latency,
and the simulator thread's CPU share.  N "sustained" = >= 99 % complete.
python-can's virtual bus deep-copies every frame for every receiver and the
master shares the core, so this part measures the whole process.

Part 2 measures the simulator's own work: the same traffic fed straight into
the simulator (a bus that discards sends, simulated clock), CPU time per
10 ms cycle for each node count; N is sustainable when that stays below 10 ms.

    .venv/bin/python maxon_epos4_ros_canopen/benchmarks/sim_many_nodes.py [--seconds 5] [--counts 8,16,32,48,64]
"""
import argparse
import os
import statistics
import struct
import sys
import time

import can

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "src"))
from maxon_epos4_ros_canopen.sim import NodeConfig, Simulator  # noqa: E402

DCF = os.path.join(HERE, "..", "config", "epos4_node1.dcf")
PERIOD = 0.010


def sdo_write(bus, node_id, index, sub, fmt, value):
    data = struct.pack("<" + fmt, value)
    command = 0x23 | ((4 - len(data)) << 2)
    bus.send(can.Message(arbitration_id=0x600 + node_id, is_extended_id=False,
                         data=struct.pack("<BHB", command, index, sub) + data.ljust(4, b"\0")))
    end = time.monotonic() + 2.0
    while time.monotonic() < end:
        msg = bus.recv(0.1)
        if msg is not None and msg.arbitration_id == 0x580 + node_id:
            if msg.data[0] != 0x60:
                raise RuntimeError("node %d refused 0x%04X: %s" % (node_id, index, bytes(msg.data).hex()))
            return
    raise RuntimeError("node %d: no SDO answer" % node_id)


def run(count: int, seconds: float) -> dict:
    channel = "sim_bench_%d_%d" % (os.getpid(), count)
    sim_bus = can.Bus(interface="virtual", channel=channel)
    master = can.Bus(interface="virtual", channel=channel)
    ids = list(range(1, count + 1))
    sim = Simulator(sim_bus, [NodeConfig(i, DCF) for i in ids], tick=0.005, statistics=True).start()
    try:
        for i in ids:  # CSP, RxPDO2 asynchronous so the target lands at once
            sdo_write(master, i, 0x1401, 1, "I", 0x80000300 + i)
            sdo_write(master, i, 0x1401, 2, "B", 255)
            sdo_write(master, i, 0x1401, 1, "I", 0x00000300 + i)
            sdo_write(master, i, 0x6060, 0, "b", 8)
            for cw in (6, 7, 15):
                sdo_write(master, i, 0x6040, 0, "H", cw)
        master.send(can.Message(arbitration_id=0, is_extended_id=False, data=[1, 0]))
        tpdo_ids = {base + i for i in ids for base in (0x180, 0x280, 0x380)}
        expected = len(tpdo_ids)
        cycles = complete = 0
        latencies = []
        cpu0, wall0 = sim.cpu_seconds, time.monotonic()
        next_sync = time.monotonic()
        end = next_sync + seconds
        target = 0
        while next_sync < end:
            target += 10
            for i in ids:
                master.send(can.Message(arbitration_id=0x300 + i, is_extended_id=False,
                                        data=struct.pack("<iI", target, 1000)))
            sync_time = time.monotonic()
            master.send(can.Message(arbitration_id=0x80, is_extended_id=False, data=b""))
            next_sync += PERIOD
            seen, last = 0, None
            while True:
                timeout = next_sync - time.monotonic()
                if timeout <= 0:
                    break
                msg = master.recv(timeout)
                if msg is None:
                    break
                if msg.arbitration_id in tpdo_ids:
                    seen += 1
                    last = time.monotonic()
                    if seen == expected:
                        break
            cycles += 1
            if seen >= expected:
                complete += 1
                latencies.append((last - sync_time) * 1000.0)
            while time.monotonic() < next_sync:  # idle until the next SYNC, draining
                msg = master.recv(max(0.0, next_sync - time.monotonic()))
        wall = time.monotonic() - wall0
        return {"nodes": count, "cycles": cycles, "complete": complete,
                "lat_median_ms": statistics.median(latencies) if latencies else float("nan"),
                "lat_max_ms": max(latencies) if latencies else float("nan"),
                "sim_cpu": (sim.cpu_seconds - cpu0) / wall,
                "frames_per_s": 3 * count / PERIOD + count / PERIOD + 1 / PERIOD}
    finally:
        sim.stop()
        master.shutdown()
        sim_bus.shutdown()


class _DiscardBus(can.BusABC):
    """Counts sends, receives nothing: isolates the simulator's own work."""

    def __init__(self) -> None:
        super().__init__(channel="discard")
        self.sent = 0

    def send(self, msg, timeout=None) -> None:
        self.sent += 1

    def _recv_internal(self, timeout):
        return None, False


def simulator_work(count: int, cycles: int = 300) -> float:
    """CPU milliseconds the simulator spends per 10 ms cycle for ``count`` CSP nodes."""
    clock = [1000.0]
    bus = _DiscardBus()
    sim = Simulator(bus, [NodeConfig(i, DCF) for i in range(1, count + 1)], tick=0.005,
                    clock=lambda: clock[0])
    sim._rebuild_routes()
    sim._next_tick = clock[0]
    for node in sim.nodes.values():
        node.on_nmt(0x01, clock[0])
        node.store.download(0x6060, 0, struct.pack("<b", 8))
        for cw in (6, 7, 15):
            node.store.download(0x6040, 0, struct.pack("<H", cw))
    rpdo = [can.Message(arbitration_id=0x300 + i, is_extended_id=False, data=bytes(8))
            for i in range(1, count + 1)]
    sync = can.Message(arbitration_id=0x80, is_extended_id=False, data=b"")
    start = time.process_time()
    for k in range(cycles):
        for msg in rpdo:
            msg.data[0:4] = struct.pack("<i", 10 * k)
            sim.handle(msg, clock[0])
        sim.handle(sync, clock[0])
        clock[0] += PERIOD / 2  # the runner's periodic tick between SYNCs (tick 5 ms)
        for node in sim.nodes.values():
            node.tick(clock[0])
        clock[0] += PERIOD / 2
    elapsed = time.process_time() - start
    bus.shutdown()
    return elapsed / cycles * 1000.0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--counts", default="8,16,32,48,64")
    args = parser.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    print("python-can virtual bus, one process on one core, SYNC %.0f ms, %.0f s per count"
          % (PERIOD * 1000, args.seconds))
    print("%5s %8s %9s %11s %9s %9s %10s" % ("nodes", "cycles", "complete", "lat med ms",
                                             "lat max", "sim CPU", "frames/s"))
    sustained = 0
    for count in [int(c) for c in args.counts.split(",")]:
        r = run(count, args.seconds)
        share = r["complete"] / max(1, r["cycles"])
        print("%5d %8d %8.1f%% %11.2f %9.2f %8.0f%% %10.0f" % (
            r["nodes"], r["cycles"], 100 * share, r["lat_median_ms"], r["lat_max_ms"],
            100 * r["sim_cpu"], r["frames_per_s"]))
        if share >= 0.99:
            sustained = max(sustained, count)
    print("sustained (>= 99%% of cycles complete): %d nodes" % sustained)
    print()
    print("simulator work only (frames discarded, simulated clock), CPU ms per 10 ms cycle:")
    best = 0
    for count in (8, 16, 32, 64, 127):
        ms = simulator_work(count)
        print("%5d nodes %8.2f ms  (%3.0f%% of one core)" % (count, ms, ms / (PERIOD * 10)))
        if ms < PERIOD * 1000:
            best = count
    print("simulator work fits in a 10 ms SYNC cycle for up to %d nodes (of the counts tried)" % best)
    return 0


if __name__ == "__main__":
    sys.exit(main())
