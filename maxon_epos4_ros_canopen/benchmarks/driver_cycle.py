#!/usr/bin/env python3
"""Cost of the driver's per-SYNC cycle, per axis, against the virtual EPOS4.

Runs N simulated EPOS4 nodes and the driver in one process on python-can's
virtual bus, CSP mode with a moving target set by a cycle callback (the
trajectory path), and prints what one cycle costs. The simulator shares the
process and the CPU, so the figures are an upper bound for the driver.

    PYTHONPATH=maxon_epos4_ros_canopen/src .venv/bin/python \
        maxon_epos4_ros_canopen/benchmarks/driver_cycle.py [AXES ...]
"""
import os
import statistics
import sys
import time

import can

from maxon_epos4_ros_canopen.config import load_config
from maxon_epos4_ros_canopen.driver import Driver
from maxon_epos4_ros_canopen.sim.runner import NodeConfig, Simulator

DCF = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "config", "epos4_node1.dcf")
SECONDS = 3.0


def run(axes: int) -> None:
    channel = "bench_cycle_%d" % axes
    sim_bus = can.Bus(interface="virtual", channel=channel)
    count_bus = can.Bus(interface="virtual", channel=channel)
    sim = Simulator(sim_bus, [NodeConfig(i, DCF) for i in range(1, axes + 1)]).start()
    params = {"bus": {"device": "virtual:" + channel}, "sync": {"interval_ms": 10},
              "nodes": [{"id": i, "name": "j%d" % i, "eds_file": DCF} for i in range(1, axes + 1)],
              "defaults": {"pos_to_device": "rint(pos*3200/(2*pi))", "pos_from_device": "obj6064*2*pi/3200",
                           "vel_to_device": "rint(vel)", "vel_from_device": "obj606C",
                           "eff_to_device": "rint(eff)", "eff_from_device": "0"}}
    driver = Driver(load_config(params, "benchmark"))
    times = []
    inner = driver.cycle

    def timed() -> None:
        t0 = time.perf_counter()
        inner()
        times.append(time.perf_counter() - t0)
    driver.cycle = timed
    try:
        r = driver.init()
        assert r.success, r.message
        r = driver.switch_mode(list(driver.joints), 8)
        assert r.success, r.message
        t_start = time.monotonic()

        def trajectory(d: Driver) -> None:
            t = time.monotonic() - t_start
            for j in d.joints.values():
                j.set_command("position", 0.5 * t)
        driver.add_cycle_callback(trajectory)
        while count_bus.recv(0) is not None:
            pass
        del times[:]
        time.sleep(SECONDS)
        frames = 0
        while count_bus.recv(0) is not None:
            frames += 1
        samples = sorted(times)
        mean = statistics.mean(samples)
        p99 = samples[int(0.99 * (len(samples) - 1))]
        print("axes %2d: %4d cycles, cycle mean %6.0f us (%5.0f us/axis), p99 %6.0f us, "
              "overruns %d, bus %5.0f frames/s" % (
                  axes, len(samples), mean * 1e6, mean * 1e6 / axes, p99 * 1e6,
                  driver.overruns, frames / SECONDS))
    finally:
        driver.close()
        sim.stop()
        sim_bus.shutdown()
        count_bus.shutdown()


if __name__ == "__main__":
    for n in [int(a) for a in sys.argv[1:]] or [1, 4, 8]:
        run(n)
