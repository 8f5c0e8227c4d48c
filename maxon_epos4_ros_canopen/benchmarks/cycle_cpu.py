#!/usr/bin/env python3
"""CPU of one control cycle per axis: the driver against a minimal loop on
python-canopen alone, both against the virtual EPOS4 (a benchmark).

    .venv/bin/python maxon_epos4_ros_canopen/benchmarks/cycle_cpu.py --impl driver --axes 8 [--layout compact]
    .venv/bin/python maxon_epos4_ros_canopen/benchmarks/cycle_cpu.py --impl baseline --axes 8
    .venv/bin/python maxon_epos4_ros_canopen/benchmarks/cycle_cpu.py --impl driver --axes 127 --init-only

One process per run (run_all starts them), printing one JSON line: init
time, CPU per cycle and per axis, PDO frames per axis per SYNC, peak RSS.
With --init-only: the init time alone (init, then close; no cycle is
measured: at 10 ms, 127 axes' cycles are more than this process's CPU).

What is charged: the process's CPU time minus the simulator thread's (which
also pays python-can's virtual-bus copies of the frames it sends). After
init the master's bus is a sink for PDOs: they are counted and dropped
(only SYNC reaches the simulator), so the copies of the master's frames are
not charged either; TxPDOs still arrive and are decoded by the master.
CSP at 10 ms SYNC, a new target position every cycle for every axis.
The driver is used through its public API only (Driver(config, bus=...),
init, switch_mode, add_cycle_callback, set_command, close).
"""
from __future__ import annotations

import argparse
import collections
import json
import math
import os
import resource
import sys
import threading
import time

import can
import canopen

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "src"))
from maxon_epos4_ros_canopen.sim.runner import NodeConfig, Simulator  # noqa: E402

DCF = os.path.join(HERE, "..", "config", "epos4_node1.dcf")
PERIOD = 0.010
SYNC_ID = 0x080
UNITS = {"pos_to_device": "rint(pos*3200/(2*pi))", "pos_from_device": "obj6064*2*pi/3200",
         "vel_to_device": "rint(vel)", "vel_from_device": "obj606C",
         "eff_to_device": "rint(eff)", "eff_from_device": "0"}


class SinkBus(can.BusABC):
    """The master's view of a virtual channel. ``sinking``: PDOs the master
    sends are counted and dropped (SYNC and everything else still go out);
    received PDOs are counted."""

    def __init__(self, channel: str) -> None:
        self.inner = can.Bus(interface="virtual", channel=channel)
        self.sinking = False
        self.sent = collections.Counter()
        self.received = collections.Counter()
        super().__init__(channel=channel)

    def send(self, msg: can.Message, timeout=None) -> None:
        if self.sinking:
            self.sent[msg.arbitration_id] += 1
            if 0x180 <= msg.arbitration_id < 0x580:
                return
        self.inner.send(msg, timeout)

    def _recv_internal(self, timeout):
        msg = self.inner.recv(timeout)
        if msg is not None and self.sinking and 0x180 <= msg.arbitration_id < 0x580:
            self.received[msg.arbitration_id] += 1
        return msg, False

    def shutdown(self) -> None:
        self.inner.shutdown()
        super().shutdown()


def run_driver(bus: SinkBus, axes: int, layout: str, switch: bool = True) -> dict:
    from maxon_epos4_ros_canopen.config import load_config
    from maxon_epos4_ros_canopen.driver import Driver

    defaults = dict(UNITS, eds_file=DCF)
    if layout != "dcf":
        defaults.update(pdo_layout=layout, modes=["CSP"])
    params = {"bus": {"device": "virtual:unused"}, "sync": {"interval_ms": PERIOD * 1000},
              "nodes": [{"id": i, "name": "j%d" % i} for i in range(1, axes + 1)], "defaults": defaults}
    driver = Driver(load_config(params, "benchmark"), bus=bus)
    names = list(driver.joints)
    t0 = time.perf_counter()
    r = driver.init()
    init_s = time.perf_counter() - t0
    if not r.success:
        driver.close()
        raise RuntimeError("init: %s" % r.message)
    if not switch:
        return {"init_s": init_s, "stop": driver.close}
    r = driver.switch_mode(names, 8)
    if not r.success:
        driver.close()
        raise RuntimeError("switch to CSP: %s" % r.message)
    t_start = time.monotonic()

    def trajectory(d) -> None:
        target = 0.2 * math.sin(time.monotonic() - t_start)
        for name in names:
            d.set_command(name, "position", target)
    driver.add_cycle_callback(trajectory)
    return {"init_s": init_s, "stop": driver.close}


def run_baseline(bus: SinkBus, axes: int) -> dict:
    """What a user writes on python-canopen alone: RemoteNodes with the
    DCF's PDO maps, CiA 402 enable over SDO, then every 10 ms read the
    TxPDO values, write a target into RxPDO2, transmit RxPDO1+2 and SYNC."""
    network = canopen.Network(bus)
    network.connect()
    nodes = []
    t0 = time.perf_counter()
    for i in range(1, axes + 1):
        node = canopen.RemoteNode(i, DCF)
        network.add_node(node)
        node.tpdo.read(from_od=True)
        node.rpdo.read(from_od=True)
        node.sdo["Modes of operation"].raw = 8
        for cw in (6, 7, 15):
            node.sdo["Controlword"].raw = cw
        node.nmt.state = "OPERATIONAL"
        nodes.append((node.tpdo[1]["Statusword"], node.tpdo[3]["Position actual value"],
                      node.tpdo[2]["Velocity actual value"], node.rpdo[1], node.rpdo[2],
                      node.rpdo[2]["Target position"], node.rpdo[1]["Controlword"]))
    init_s = time.perf_counter() - t0
    stop = threading.Event()
    t_start = time.monotonic()

    def loop() -> None:
        next_t = time.monotonic()
        while not stop.is_set():
            target = int(3200 * 0.2 * math.sin(time.monotonic() - t_start) / (2 * math.pi))
            for sw, pos, vel, rpdo1, rpdo2, tp, cw in nodes:
                _ = (sw.raw, pos.raw * 2 * math.pi / 3200, vel.raw)
                cw.raw = 15
                tp.raw = target
                rpdo1.transmit()
                rpdo2.transmit()
            network.send_message(SYNC_ID, b"")
            next_t += PERIOD
            stop.wait(max(0.0, next_t - time.monotonic()))
    thread = threading.Thread(target=loop, daemon=True)
    thread.start()

    def close() -> None:
        stop.set()
        thread.join(2.0)
        network.disconnect()
    return {"init_s": init_s, "stop": close}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--impl", choices=("driver", "baseline"), default="driver")
    ap.add_argument("--axes", type=int, default=8)
    ap.add_argument("--layout", default="dcf", help="driver only: the node layer's pdo_layout")
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--init-only", action="store_true", help="driver only: measure init, then close")
    args = ap.parse_args()
    channel = "cycle_cpu_%d" % os.getpid()
    sim_bus = can.Bus(interface="virtual", channel=channel)
    sim = Simulator(sim_bus, [NodeConfig(i, DCF) for i in range(1, args.axes + 1)], tick=0.005).start()
    bus = SinkBus(channel)
    out = {"impl": args.impl, "axes": args.axes, "layout": args.layout if args.impl == "driver" else "dcf"}
    run = None
    try:
        if args.init_only:
            run = run_driver(bus, args.axes, args.layout, switch=False)
            out.update({"ok": True, "init_s": run["init_s"]})
            # The figure is taken: the process ends here. Shutting down 127
            # axes through a 10 ms cycle is more than this process's CPU
            # (that is what --init-only is for), and would hang the run.
            out["rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
            print(json.dumps(out), flush=True)
            os._exit(0)
        else:
            run = run_driver(bus, args.axes, args.layout) if args.impl == "driver" else run_baseline(bus, args.axes)
            time.sleep(0.5)  # settle: mode switch done, targets moving
            bus.sinking = True
            cpu0, sim0, wall0 = time.process_time(), sim.cpu_seconds, time.monotonic()
            sync0 = bus.sent[SYNC_ID]
            time.sleep(args.seconds)
            cpu, sim_cpu, wall = time.process_time() - cpu0, sim.cpu_seconds - sim0, time.monotonic() - wall0
            syncs = bus.sent[SYNC_ID] - sync0
            cycles = max(1, syncs)
            master_cpu = max(0.0, cpu - sim_cpu)
            out.update({
                "ok": True, "init_s": run["init_s"], "cycles": syncs, "wall_s": wall,
                "cpu_per_cycle_us": master_cpu / cycles * 1e6,
                "cpu_per_axis_us": master_cpu / cycles / args.axes * 1e6,
                "sim_cpu_share": sim_cpu / wall,
                "rx_pdos_per_axis": sum(n for k, n in bus.sent.items() if 0x200 <= k < 0x580) / cycles / args.axes,
                "tx_pdos_per_axis": sum(bus.received.values()) / cycles / args.axes,
            })
            out["pdos_per_axis"] = out["rx_pdos_per_axis"] + out["tx_pdos_per_axis"]
    except Exception as e:  # a run that cannot start is a row in the table, not a crash
        out.update({"ok": False, "error": str(e)})
    finally:
        if run is not None:
            run["stop"]()
        sim.stop()
        bus.shutdown()
        sim_bus.shutdown()
    out["rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(json.dumps(out))
    return 0 if out["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
