"""canopen_motor_node and virtual EPOS4 drives in one process, on python-can's
in-process `virtual` bus: the node's ROS interface can then be tested where
no vcan0 exists. Used by test_canopen_motor_node.py as a subprocess:

    python node_with_sim.py CHANNEL ID:DCF [ID:DCF ...] -- NODE_ARGS...

The node reads its parameters from the master as usual; its bus/device must
be `virtual:CHANNEL`. Lines on stdin inject simulator faults:
`NODE_ID FAULT [ERROR_CODE] [DURATION]`, e.g. `1 emcy 0x8611`; the line
`sync TOKEN` is answered with `synced TOKEN` on stderr once two SYNC frames
were sent after it (see answer_sync).
"""
from __future__ import annotations

import importlib.machinery
import importlib.util
import sys
import threading
import time
from pathlib import Path

import can

from maxon_epos4_ros_canopen.sim.runner import Simulator, parse_node_spec

NODE_SCRIPT = Path(__file__).resolve().parents[2] / "nodes" / "canopen_motor_node"
SYNC_COB_ID = 0x080
SYNC_WAIT = 60.0  # generous: a loaded host may starve the driver's cycle for seconds


def answer_sync(channel: str, token: str) -> None:
    """Print `synced TOKEN` once two SYNCs were sent after this call.

    The driver's cycle sends SYNC last, after the RxPDOs of the commands it
    took from its inbox (the shipped bus layer: SYNC and cycle share the
    period). The first SYNC may end a cycle that began before this call;
    the second ends one that began after it. So whatever the driver had
    queued before this call has been sent by then, ahead of any SDO
    request a test sends afterwards, and the simulated drives handle frames
    in the order they were sent."""
    # A new reader of the channel gets only frames sent after it was opened.
    tap = can.Bus(interface="virtual", channel=channel)
    try:
        syncs = 0
        deadline = time.monotonic() + SYNC_WAIT
        while syncs < 2 and time.monotonic() < deadline:
            msg = tap.recv(timeout=0.5)
            if msg is not None and msg.arbitration_id == SYNC_COB_ID and not msg.is_extended_id:
                syncs += 1
    finally:
        tap.shutdown()
    print("synced %s" % token if syncs >= 2 else "sync %s: no SYNC for %.0f s" % (token, SYNC_WAIT),
          file=sys.stderr, flush=True)


def inject_from_stdin(sim: Simulator, channel: str) -> None:
    for line in sys.stdin:
        words = line.split()
        if not words:
            continue
        if words[0] == "sync" and len(words) == 2:
            # its own thread: the wait must not hold up a fault injection
            threading.Thread(target=answer_sync, args=(channel, words[1]), daemon=True).start()
            continue
        try:
            code = int(words[2], 0) if len(words) > 2 else 0
            duration = float(words[3]) if len(words) > 3 else 0.0
            print("inject: %s" % sim.inject_fault(int(words[0]), words[1], code, duration), file=sys.stderr)
        except (ValueError, IndexError) as exc:
            print("inject: %r refused: %s" % (line, exc), file=sys.stderr)


def main() -> int:
    split = sys.argv.index("--")
    channel, specs = sys.argv[1], sys.argv[2:split]
    sim_bus = can.Bus(interface="virtual", channel=channel)
    sim = Simulator(sim_bus, [parse_node_spec(s) for s in specs]).start()
    threading.Thread(target=inject_from_stdin, args=(sim, channel), daemon=True).start()
    loader = importlib.machinery.SourceFileLoader("canopen_motor_node", str(NODE_SCRIPT))
    spec = importlib.util.spec_from_loader("canopen_motor_node", loader)
    node = importlib.util.module_from_spec(spec)
    loader.exec_module(node)
    sys.argv = [str(NODE_SCRIPT)] + sys.argv[split + 1:]
    try:
        return node.main()
    finally:
        sim.stop()
        sim_bus.shutdown()


if __name__ == "__main__":
    sys.exit(main())
