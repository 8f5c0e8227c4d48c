#!/usr/bin/env python3
"""CPU of one control cycle per axis: the driver against a minimal loop on
python-canopen alone, both against the virtual EPOS4 (a benchmark).

    .venv/bin/python maxon_epos4_ros_canopen/benchmarks/cycle_cpu.py --impl driver --axes 8 [--layout compact]
    .venv/bin/python maxon_epos4_ros_canopen/benchmarks/cycle_cpu.py --impl baseline --axes 8
    .venv/bin/python maxon_epos4_ros_canopen/benchmarks/cycle_cpu.py --impl lean --axes 8 [--layout compact]
    .venv/bin/python maxon_epos4_ros_canopen/benchmarks/cycle_cpu.py --ratio --axes 32 [--rounds 3] [--plot F.png]
    .venv/bin/python maxon_epos4_ros_canopen/benchmarks/cycle_cpu.py --impl driver --axes 127 --init-only

One process per run (run_all starts them), printing one JSON line: init
time, CPU per cycle and per axis, PDO frames per axis per SYNC, peak RSS.
With --init-only: the init time alone (init, then close; no cycle is
measured: at 10 ms, 127 axes' cycles are more than this process's CPU).

What is charged: the master process's CPU time. The virtual EPOS4 runs in
a process of its own (forked at start), joined to the master by a
socketpair that carries CAN frames (PipeBus): sharing the master's GIL, 32
DCF drives and the driver need more than 10 ms of CPU per 10 ms SYNC, and
the simulated drives would fall ever further behind. After init the
master's bus is a sink for PDOs: they are counted and dropped (only SYNC
reaches the simulator); TxPDOs still arrive and are decoded by the master.
The driver gets the TxPDOs on a second socketpair as SocketCAN frames
(``struct can_frame``, stamped by the kernel) and reads them with its own
SocketCAN receiver, as it reads a CAN_RAW socket on a real bus; the loops
written here read theirs through python-can, as their users do.
CSP at 10 ms SYNC, a new target position every cycle for every axis.
The driver is used through its public API only (Driver(config, bus=...,
pdo_bus=...), init, switch_mode, add_cycle_callback, set_command, close).

Two baselines: ``baseline``, python-canopen's PDO maps (DCF layout);
``lean``, what a competent user writes on python-can alone: each cycle
drains the socket into a dict of latest frames, unpacks the TxPDOs and
packs the RxPDOs with prepared ``struct``s, sends them and SYNC; no PDO
maps, no unit expressions, no state machine (the drives are enabled over
SDO at setup, which is not measured). ``--layout`` picks the PDO layout of
the driver and of the lean loop alike, so each ratio is at equal frames.

``--ratio`` runs driver and lean loop for both layouts in alternating
rounds (a process each) and prints the CPU per axis (median, min-max over
the rounds) and the ratios: at equal frames (driver / lean, same layout)
and across layouts (driver compact / lean DCF).
"""
from __future__ import annotations

import argparse
import collections
import json
import math
import multiprocessing
import os
import resource
import select
import socket
import struct
import sys
import threading
import time
from typing import Callable, Optional, Tuple

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


class PipeBus(can.BusABC):
    """One end of a socketpair carrying CAN frames to the other process.

    Written here because python-can's in-process virtual bus does not reach
    another process, and vcan is absent on hosts like this one: a local
    socketpair joins the two and never leaves the machine.

    A frame is stamped with the sender's wall clock, as python-can's virtual
    bus stamps it, so a frame left waiting in the socket shows how long it
    waited. Sending blocks while the peer's buffer is full (it is reading:
    each process has a thread that receives), for at most ``timeout``; a
    frame that still finds no room is lost, as on a full SocketCAN queue."""

    FRAME = struct.Struct("<dIBB8s")  # stamp, COB-ID, DLC, flags, data
    EXTENDED, REMOTE, ERROR = 1, 2, 4

    def __init__(self, sock: socket.socket, channel: str = "pipe") -> None:
        self.sock = sock
        self.channel_info = channel
        for opt in (socket.SO_SNDBUF, socket.SO_RCVBUF):  # a SYNC's burst of TxPDOs fits
            try:
                sock.setsockopt(socket.SOL_SOCKET, opt, 1 << 22)
            except OSError:
                pass
        # non-blocking: a receive finds no frame at once or waits in poll,
        # a send waits only for the peer to make room
        sock.setblocking(False)
        self._poll = select.poll()
        self._poll.register(sock, select.POLLIN)
        super().__init__(channel=channel)

    def send(self, msg: can.Message, timeout: Optional[float] = None) -> None:
        flags = ((self.EXTENDED if msg.is_extended_id else 0) | (self.REMOTE if msg.is_remote_frame else 0)
                 | (self.ERROR if msg.is_error_frame else 0))
        frame = self.FRAME.pack(time.time(), msg.arbitration_id, msg.dlc, flags, bytes(msg.data))
        try:
            self.sock.send(frame)
            return
        except BlockingIOError:
            pass
        except OSError as e:
            raise can.CanOperationError("pipe send: %s" % e) from None
        # the peer's buffer is full: wait for room (select: the receiving
        # thread owns the poll object)
        wait = 1.0 if timeout is None else timeout
        _, room, _ = select.select([], [self.sock], [], wait)
        try:
            if room:
                self.sock.send(frame)
                return
        except OSError as e:
            raise can.CanOperationError("pipe send: %s" % e) from None
        raise can.CanOperationError("pipe send: no room for %g s" % wait)

    def _recv_internal(self, timeout: Optional[float]) -> Tuple[Optional[can.Message], bool]:
        # a frame already waiting is read at once: one system call, not two
        try:
            frame = self.sock.recv(self.FRAME.size, socket.MSG_DONTWAIT)
        except BlockingIOError:
            if not self._poll.poll(None if timeout is None else max(0.0, timeout) * 1000.0):
                return None, False
            try:
                frame = self.sock.recv(self.FRAME.size, socket.MSG_DONTWAIT)
            except BlockingIOError:
                return None, False
            except OSError as e:
                raise can.CanOperationError("pipe receive: %s" % e) from None
        except OSError as e:
            raise can.CanOperationError("pipe receive: %s" % e) from None
        if len(frame) != self.FRAME.size:
            raise can.CanOperationError("pipe closed")
        stamp, cob, dlc, flags, data = self.FRAME.unpack(frame)
        return can.Message(timestamp=stamp, arbitration_id=cob, is_extended_id=bool(flags & self.EXTENDED),
                           is_remote_frame=bool(flags & self.REMOTE), is_error_frame=bool(flags & self.ERROR),
                           dlc=dlc, data=data[:dlc] if not flags & self.REMOTE else None, check=False), False

    def shutdown(self) -> None:
        self.sock.close()
        super().shutdown()


class CanFramePipe:
    """The simulator's end of the pipe that carries its TxPDOs to the
    driver as a CAN_RAW socket hands them over: one ``struct can_frame``
    per datagram, stamped by the kernel on receipt (SO_TIMESTAMPNS works on
    a local socketpair too). The driver reads it with its own SocketCAN
    receiver (driver/cycle_reception.RawCanReceiver), as on a real bus."""

    FRAME = struct.Struct("=IB3x8s")  # struct can_frame

    def __init__(self, sock: socket.socket, sent) -> None:
        """``sent``: a shared counter of the frames sent (multiprocessing.Value)."""
        self.sock = sock
        self.sent = sent
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 22)
        sock.settimeout(1.0)  # a master that stopped reading: the frame is lost, as on a full queue

    def send(self, msg: can.Message, timeout: Optional[float] = None) -> None:
        try:
            self.sock.send(self.FRAME.pack(msg.arbitration_id, msg.dlc, bytes(msg.data)))
        except OSError as e:
            raise can.CanOperationError("pipe send: %s" % e) from None
        self.sent.value += 1

    def shutdown(self) -> None:
        self.sock.close()


class SplitBus(can.BusABC):
    """The simulator's end when the driver reads its TxPDOs from a pipe of
    their own (Driver's ``pdo_bus``), as the driver's kernel filter splits
    them from the rest on SocketCAN: TxPDOs go out on ``pdo``, everything
    else on ``main``, which alone carries frames from the master."""

    def __init__(self, main: PipeBus, pdo: CanFramePipe) -> None:
        self.main, self.pdo = main, pdo
        super().__init__(channel=main.channel_info)

    def send(self, msg: can.Message, timeout: Optional[float] = None) -> None:
        (self.pdo if 0x180 <= msg.arbitration_id < 0x500 else self.main).send(msg, timeout)

    def _recv_internal(self, timeout: Optional[float]) -> Tuple[Optional[can.Message], bool]:
        return self.main.recv(timeout), False

    def shutdown(self) -> None:
        self.main.shutdown()
        self.pdo.shutdown()
        super().shutdown()


def _serve_simulator(sock: socket.socket, pdo_sock: Optional[socket.socket], pdo_sent, axes: int, ready,
                     stop) -> None:
    """The simulator process: ``axes`` virtual EPOS4 on ``sock`` (TxPDOs on
    ``pdo_sock`` when given, counted in ``pdo_sent``) until ``stop`` is set."""
    bus: can.BusABC = PipeBus(sock, "simulator")
    if pdo_sock is not None:
        bus = SplitBus(bus, CanFramePipe(pdo_sock, pdo_sent))
    sim = Simulator(bus, [NodeConfig(i, DCF) for i in range(1, axes + 1)], tick=0.005).start()
    ready.set()
    stop.wait()
    sim.stop()
    bus.shutdown()


class SimulatorProcess:
    """The virtual EPOS4 in a process of its own (its own GIL: see the
    module text), forked before this process starts any thread."""

    def __init__(self, axes: int, pdo_pipe: bool = False) -> None:
        """``pdo_pipe``: the TxPDOs come on a pipe of their own (``pdo_sock``,
        SocketCAN frames; ``pdo_sent`` counts them)."""
        ctx = multiprocessing.get_context("fork")
        self.pdo_sent = ctx.Value("Q", 0)
        mine, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        pdo_mine, pdo_theirs = (socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET) if pdo_pipe
                                else (None, None))
        self.stop_event = ctx.Event()
        ready = ctx.Event()
        self.process = ctx.Process(target=_serve_simulator,
                                   args=(theirs, pdo_theirs, self.pdo_sent, axes, ready, self.stop_event),
                                   name="virtual_epos4", daemon=True)
        self.process.start()
        theirs.close()
        if pdo_theirs is not None:
            pdo_theirs.close()
        self.sock = mine
        self.pdo_sock = pdo_mine
        # the drives answer from the start, as they did in this process:
        # loading 32 dictionaries takes longer than an SDO timeout
        if not ready.wait(60.0):
            self.stop()
            raise RuntimeError("the simulator process did not start")

    def cpu_seconds(self) -> float:
        """CPU time the simulator process used so far (Linux /proc)."""
        with open("/proc/%d/stat" % self.process.pid) as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def stop(self) -> None:
        self.stop_event.set()
        self.process.join(5.0)
        if self.process.is_alive():
            self.process.kill()


class SinkBus(can.BusABC):
    """The master's end of the simulator's pipe. ``sinking``: PDOs the
    master sends are counted and dropped (SYNC and everything else still go
    out); received PDOs are counted."""

    def __init__(self, inner: can.BusABC) -> None:
        self.inner = inner
        self.sinking = False
        self.sent = collections.Counter()
        self.received = collections.Counter()
        super().__init__(channel=inner.channel_info)

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


def thread_cpu() -> dict:
    """CPU seconds of each live thread of this process, by thread name
    (the kernel's per-thread clock: the notifier, the cycle, the simulator)."""
    out = {}
    for t in threading.enumerate():
        try:
            out[t.name] = time.clock_gettime(time.pthread_getcpuclockid(t.ident))
        except (OSError, TypeError, AttributeError):  # ended meanwhile, or no per-thread clock
            pass
    return out


def thread_label(name: str) -> str:
    """A short name for a thread of the run (python-can's notifier names
    itself after the bus)."""
    if name.startswith("Notifier"):
        return "notifier"
    return {"epos4_driver_cycle": "cycle", "virtual_epos4": "simulator", "MainThread": "main"}.get(name, name)


def run_driver(bus: SinkBus, axes: int, layout: str, switch: bool = True, pdo_bus: Optional[socket.socket] = None
               ) -> dict:
    from maxon_epos4_ros_canopen.config import load_config
    from maxon_epos4_ros_canopen.driver import Driver

    defaults = dict(UNITS, eds_file=DCF)
    if layout != "dcf":
        defaults.update(pdo_layout=layout, modes=["CSP"])
    params = {"bus": {"device": "virtual:unused"}, "sync": {"interval_ms": PERIOD * 1000},
              "nodes": [{"id": i, "name": "j%d" % i} for i in range(1, axes + 1)], "defaults": defaults}
    # generous waits: they only bound how long a failure takes on a loaded host
    driver = Driver(load_config(params, "benchmark"), bus=bus, pdo_bus=pdo_bus, state_timeout=20.0,
                    sdo_timeout=5.0)
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
    driver.add_cycle_callback(sine_targets(names))
    return {"init_s": init_s, "stop": driver.close}


def sine_targets(names) -> Callable:
    """A cycle callback: a new position target for every joint every cycle,
    a slow sine from the moment it is made."""
    t_start = time.monotonic()

    def trajectory(d) -> None:
        target = 0.2 * math.sin(time.monotonic() - t_start)
        for name in names:
            d.set_command(name, "position", target)
    return trajectory


def run_every_period(cycle: Callable[[], None], on_close: Callable[[], None] = lambda: None) -> Callable[[], None]:
    """A baseline's loop: ``cycle`` every PERIOD on a thread of its own
    (as the driver's cycle runs); returns the function that stops it."""
    stop = threading.Event()

    def loop() -> None:
        next_t = time.monotonic()
        while not stop.is_set():
            cycle()
            next_t += PERIOD
            stop.wait(max(0.0, next_t - time.monotonic()))
    thread = threading.Thread(target=loop, daemon=True)
    thread.start()

    def close() -> None:
        stop.set()
        thread.join(2.0)
        on_close()
    return close


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
    t_start = time.monotonic()

    def cycle() -> None:
        target = int(3200 * 0.2 * math.sin(time.monotonic() - t_start) / (2 * math.pi))
        for sw, pos, vel, rpdo1, rpdo2, tp, cw in nodes:
            _ = (sw.raw, pos.raw * 2 * math.pi / 3200, vel.raw)
            cw.raw = 15
            tp.raw = target
            rpdo1.transmit()
            rpdo2.transmit()
        network.send_message(SYNC_ID, b"")
    return {"init_s": init_s, "stop": run_every_period(cycle, network.disconnect)}


# The lean loop's frames per layout: (COB-ID base, struct format) of the
# RxPDOs it sends each cycle and of the TxPDOs it reads. DCF: the
# project's EPOS4 DCF mapping (RxPDO1 6040+60FF, RxPDO2 607A+6081; TxPDO1
# 6041+6061, TxPDO2 606B+606C, TxPDO3 6064+30D3.1). Compact: the driver's
# compact CSP layout (RxPDO1 6040+607A; TxPDO1 6041+6064, TxPDO2 606C).
LEAN_FRAMES = {
    "dcf": {"rx": ((0x200, "<Hi"), (0x300, "<iI")), "tx": ((0x180, "<Hb"), (0x280, "<ii"), (0x380, "<ii"))},
    "compact": {"rx": ((0x200, "<Hi"),), "tx": ((0x180, "<Hi"), (0x280, "<i"))},
}


def _lean_setup(bus: can.BusABC, axes: int, layout: str) -> None:
    """The drives in CSP, Operation Enabled, OPERATIONAL, with the layout's
    PDO mapping (written through canopen on the loop's bus; setup is not
    measured)."""
    from maxon_epos4_ros_canopen.config import load_config
    from maxon_epos4_ros_canopen.driver.plan import plan_node

    network = canopen.Network(bus)
    network.connect()
    try:
        for i in range(1, axes + 1):
            node = canopen.RemoteNode(i, DCF)
            network.add_node(node)
            if layout == "compact":
                cfg = load_config({"sync": {"interval_ms": PERIOD * 1000}, "nodes": {"n": dict(
                    UNITS, id=i, eds_file=DCF, pdo_layout="compact", modes=["CSP"])}}, "lean")
                plan_node(cfg.nodes[0], node.object_dictionary, cfg.sync, "lean").write_with_canopen(node)
            node.sdo["Modes of operation"].raw = 8
            for cw in (6, 7, 15):
                node.sdo["Controlword"].raw = cw
            node.nmt.state = "OPERATIONAL"
    finally:
        # not disconnect(): that shuts the bus the loop goes on with
        network.notifier.stop()


def run_lean(bus: SinkBus, axes: int, layout: str) -> dict:
    """The lean loop on python-can alone (see the module text)."""
    import struct
    t0 = time.perf_counter()
    _lean_setup(bus, axes, layout)
    init_s = time.perf_counter() - t0
    frames = LEAN_FRAMES[layout]
    rx = [[can.Message(arbitration_id=base + i, is_extended_id=False, data=bytes(struct.calcsize(fmt)))
           for base, fmt in frames["rx"]] for i in range(1, axes + 1)]
    rx_pack = [struct.Struct(fmt).pack for _, fmt in frames["rx"]]
    tx = [(base, struct.Struct(fmt).unpack) for base, fmt in frames["tx"]]
    sync = can.Message(arbitration_id=SYNC_ID, is_extended_id=False, data=b"")
    latest: dict = {}
    t_start = time.monotonic()
    inc_per_rad = 3200 / (2 * math.pi)
    recv = bus.recv

    def cycle() -> None:
        msg = recv(0.0)
        while msg is not None:
            latest[msg.arbitration_id] = msg.data
            msg = recv(0.0)
        target = int(round(0.2 * math.sin(time.monotonic() - t_start) * inc_per_rad))
        for i in range(axes):
            node_id = i + 1
            values = [unpack(latest[base + node_id]) for base, unpack in tx if base + node_id in latest]
            _ = values and values[0][0] & 0x6F == 0x27  # operation enabled?
            msgs = rx[i]
            msgs[0].data[:] = rx_pack[0](15, target if layout == "compact" else 0)
            if len(msgs) > 1:
                msgs[1].data[:] = rx_pack[1](target, 0)
            for m in msgs:
                bus.send(m)
        bus.send(sync)
    return {"init_s": init_s, "stop": run_every_period(cycle)}


def ratio(axes: int, rounds: int, seconds: float, plot: str = "") -> int:
    """Driver against the lean loop, both layouts, alternating rounds."""
    import statistics
    import subprocess
    runs = [("driver", "dcf"), ("lean", "dcf"), ("driver", "compact"), ("lean", "compact")]
    got: dict = {r: [] for r in runs}
    for k in range(rounds):
        for impl, layout in runs:
            p = subprocess.run([sys.executable, os.path.abspath(__file__), "--impl", impl, "--layout", layout,
                                "--axes", str(axes), "--seconds", str(seconds)], capture_output=True, text=True)
            lines = [ln for ln in p.stdout.splitlines() if ln.startswith("{")]
            out = json.loads(lines[-1]) if lines else {"ok": False, "error": p.stderr.strip()[-300:]}
            if not out.get("ok"):
                print("round %d %s %s: %s" % (k + 1, impl, layout, out.get("error")))
                continue
            got[(impl, layout)].append(out)
            print("round %d %-6s %-7s %6.1f us/axis  %.2f PDO frames/axis" % (
                k + 1, impl, layout, out["cpu_per_axis_us"], out["pdos_per_axis"]), flush=True)
    cpu = {r: [o["cpu_per_axis_us"] for o in v] for r, v in got.items()}
    if not all(cpu.values()):
        print("some runs failed: no ratio")
        return 1
    med = {r: statistics.median(v) for r, v in cpu.items()}
    print("\nCPU per axis at %d axes, %d round(s) of %.0f s, median (min-max):" % (axes, rounds, seconds))
    for r in runs:
        print("  %-6s %-7s %6.1f us (%.1f-%.1f), %.2f PDO frames/axis/SYNC" % (
            r[0], r[1], med[r], min(cpu[r]), max(cpu[r]), statistics.median(o["pdos_per_axis"] for o in got[r])))
    print("per thread, us per axis, median of the rounds (the simulator's is not charged):")
    for r in runs:
        names = sorted({n for o in got[r] for n in o.get("threads_per_axis_us", {})})
        print("  %-6s %-7s %s" % (r[0], r[1], ", ".join(
            "%s %.1f" % (n, statistics.median(o["threads_per_axis_us"].get(n, 0.0) for o in got[r])) for n in names)))
    print("ratios, median of the rounds' (min-max) (target: driver <= 1.0 x lean loop):")
    for d, b, what in ((("driver", "dcf"), ("lean", "dcf"), "equal frames, DCF layout"),
                       (("driver", "compact"), ("lean", "compact"), "equal frames, compact layout"),
                       (("driver", "compact"), ("lean", "dcf"), "across layouts: driver compact / lean DCF")):
        ratios = [a / c for a, c in zip(cpu[d], cpu[b])]  # round by round: the same moment's load
        print("  %.2f (%.2f-%.2f)  %s" % (statistics.median(ratios), min(ratios), max(ratios), what))
    if plot:
        _plot_ratio(plot, runs, cpu, axes)
    return 0


def _plot_ratio(path: str, runs, cpu, axes: int) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    colours = {"driver": "tab:blue", "lean": "tab:orange"}
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    for n, layout in enumerate(("dcf", "compact")):
        for m, impl in enumerate(("driver", "lean")):
            v = cpu[(impl, layout)]
            mid = sorted(v)[len(v) // 2]
            ax1.bar(n + 0.4 * m, mid, width=0.38, color=colours[impl], label=impl if n == 0 else None,
                    yerr=[[mid - min(v)], [max(v) - mid]], capsize=4)
    ax1.set_xticks([0.2, 1.2])
    ax1.set_xticklabels(["DCF layout", "compact layout"])
    ax1.set_ylabel("CPU per axis per cycle (us), median, bar: min-max")
    ax1.set_ylim(bottom=0)
    ax1.set_title("%d axes" % axes)
    ax1.legend()
    pairs = [(("driver", "dcf"), ("lean", "dcf"), "DCF / DCF"), (("driver", "compact"), ("lean", "compact"),
             "compact / compact"), (("driver", "compact"), ("lean", "dcf"), "compact / lean DCF")]
    for n, (d, b, label) in enumerate(pairs):
        r = [a / c for a, c in zip(cpu[d], cpu[b])]
        mid = sorted(r)[len(r) // 2]
        ax2.bar(n, mid, color="tab:blue", yerr=[[mid - min(r)], [max(r) - mid]], capsize=4,
                label="driver / lean loop" if n == 0 else None)
    ax2.axhline(1.0, color="tab:red", linestyle="--", label="target 1.0")
    ax2.set_xticks(range(3))
    ax2.set_xticklabels(["equal frames\nDCF", "equal frames\ncompact", "across layouts"])
    ax2.set_ylim(bottom=0)
    ax2.set_ylabel("ratio, median, bar: min-max over rounds")
    ax2.legend()
    fig.tight_layout()
    fig.savefig(path)
    print("plot: %s" % path)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--impl", choices=("driver", "baseline", "lean"), default="driver")
    ap.add_argument("--axes", type=int, default=8)
    ap.add_argument("--layout", default="dcf", help="driver and lean: the PDO layout (dcf, compact)")
    ap.add_argument("--ratio", action="store_true", help="driver against lean loop, both layouts")
    ap.add_argument("--rounds", type=int, default=3, help="--ratio: alternating rounds")
    ap.add_argument("--plot", default="", help="--ratio: write a PNG here")
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--init-only", action="store_true", help="driver only: measure init, then close")
    args = ap.parse_args()
    if args.ratio:
        return ratio(args.axes, args.rounds, args.seconds, args.plot)
    # the driver reads its TxPDOs on a pipe of their own with its SocketCAN
    # receiver, as on SocketCAN (driver/cycle_reception.py); the loops
    # written here read one socket through python-can, as their users do
    sim = SimulatorProcess(args.axes, pdo_pipe=args.impl == "driver")
    bus = SinkBus(PipeBus(sim.sock, "master"))
    pdo_bus = sim.pdo_sock
    out = {"impl": args.impl, "axes": args.axes, "layout": args.layout if args.impl != "baseline" else "dcf"}
    run = None
    try:
        if args.init_only:
            run = run_driver(bus, args.axes, args.layout, switch=False, pdo_bus=pdo_bus)
            out.update({"ok": True, "init_s": run["init_s"]})
            # The figure is taken: the process ends here. Shutting down 127
            # axes through a 10 ms cycle is more than this process's CPU
            # (that is what --init-only is for), and would hang the run.
            out["rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
            print(json.dumps(out), flush=True)
            sim.process.kill()  # os._exit skips multiprocessing's clean-up
            os._exit(0)
        else:
            if args.impl == "driver":
                run = run_driver(bus, args.axes, args.layout, pdo_bus=pdo_bus)
            elif args.impl == "lean":
                run = run_lean(bus, args.axes, args.layout)
            else:
                run = run_baseline(bus, args.axes)
            time.sleep(0.5)  # settle: mode switch done, targets moving
            bus.sinking = True
            pdo_sent0 = sim.pdo_sent.value
            threads0 = thread_cpu()
            cpu0, sim0, wall0 = time.process_time(), sim.cpu_seconds(), time.monotonic()
            sync0 = bus.sent[SYNC_ID]
            time.sleep(args.seconds)
            cpu, sim_cpu, wall = time.process_time() - cpu0, sim.cpu_seconds() - sim0, time.monotonic() - wall0
            threads1 = thread_cpu()
            pdo_sent = sim.pdo_sent.value - pdo_sent0
            syncs = bus.sent[SYNC_ID] - sync0
            cycles = max(1, syncs)
            master_cpu = cpu  # the simulator's CPU is its own process's
            out.update({
                "ok": True, "init_s": run["init_s"], "cycles": syncs, "wall_s": wall,
                "cpu_per_cycle_us": master_cpu / cycles * 1e6,
                "cpu_per_axis_us": master_cpu / cycles / args.axes * 1e6,
                "sim_cpu_share": sim_cpu / wall,
                "rx_pdos_per_axis": sum(n for k, n in bus.sent.items() if 0x200 <= k < 0x580) / cycles / args.axes,
                "tx_pdos_per_axis": (sum(bus.received.values()) + pdo_sent) / cycles / args.axes,
            })
            out["pdos_per_axis"] = out["rx_pdos_per_axis"] + out["tx_pdos_per_axis"]
            # per thread of the master, us per axis per cycle (the simulator runs in its own process)
            out["threads_per_axis_us"] = {thread_label(name): (threads1[name] - t0) / cycles / args.axes * 1e6
                                          for name, t0 in threads0.items() if name in threads1}
    except Exception as e:  # a run that cannot start is a row in the table, not a crash
        out.update({"ok": False, "error": str(e)})
    finally:
        if run is not None:
            run["stop"]()
        sim.stop()
        bus.shutdown()
        if pdo_bus is not None:
            pdo_bus.close()
    out["rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(json.dumps(out))
    return 0 if out["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
