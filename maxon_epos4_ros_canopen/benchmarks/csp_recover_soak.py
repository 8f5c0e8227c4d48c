#!/usr/bin/env python3
"""Fault, recover and move again, many times over (a soak run, not a test).

The CSP example in one process (csp_rig: the driver with the example's YAML
files, the JointTrajectoryController, two virtual EPOS4 on a python-can
virtual channel) goes through the steps of the CSP session rostest on every
round: a goal; a second goal with an EMCY fault on node 2 in the middle;
recover; a third goal, which both joints must reach. The pauses between the
steps are random, so the rounds meet the driver's and the simulator's
threads at different moments.

    .venv/bin/python maxon_epos4_ros_canopen/benchmarks/csp_recover_soak.py [--rounds 50] [--seed 1]

Prints one line per round and a summary: rounds, failures, seconds per
round. A failed round prints what each drive holds (0x6041, 0x6061, 0x607A,
0x6064, read from the simulator) and the driver's view of each joint, so a
drive that took no target can be told from one that did not follow it.
"""
from __future__ import annotations

import argparse
import random
import sys
import time
from pathlib import Path
from typing import Callable, List, Optional

PKG = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(PKG / "src"), str(PKG / "test" / "unit")]  # the core, and csp_rig shared with the tests

from csp_rig import JOINTS, CspRig, wait as rig_wait  # noqa: E402

from maxon_epos4_ros_canopen import trajectory as tj  # noqa: E402
from maxon_epos4_ros_canopen.trajectory import TrajectoryPoint  # noqa: E402

STEP_TIMEOUT = 30.0  # s for one step (a goal, recover) before the round counts as failed


def wait(condition: Callable[[], bool], timeout: float = STEP_TIMEOUT) -> bool:
    return rig_wait(condition, timeout)


def drives(rig: CspRig) -> str:
    lines = []
    for node_id, joint in zip((1, 2), JOINTS):
        values = ", ".join("0x%04X=%s" % (index, rig.sim.read(node_id, index))
                           for index in (0x6041, 0x6061, 0x607A, 0x6064))
        lines.append("  node %d: %s; driver: %s" % (node_id, values, rig.driver.joints[joint]))
    return "\n".join(lines)


def one_round(rng: random.Random) -> Optional[str]:
    """None when the round went as it should, else what went wrong."""
    rig = CspRig()
    try:
        ctrl = rig.start()
        done: List[tj.Outcome] = rig.outcomes
        ctrl.submit("a", JOINTS, [TrajectoryPoint((0.5, -0.3), (0.0, 0.0), (), 1.0)], 0.0)
        if not wait(lambda: len(done) == 1) or not done[0].succeeded:
            return "first goal: %s" % (done[:1],)
        ctrl.submit("b", JOINTS, [TrajectoryPoint((-0.4, 0.3), (0.0, 0.0), (), 3.0)], 0.0)
        time.sleep(rng.uniform(0.2, 1.0))
        rig.sim.inject_fault(2, "emcy", 0x8611)
        if not wait(lambda: len(done) == 2) or done[1].code != tj.PATH_TOLERANCE_VIOLATED:
            return "faulted goal: %s" % (done[1:2],)
        time.sleep(rng.uniform(0.0, 1.0))
        recovered = rig.driver.recover()
        if not recovered.success:
            return "recover: %s" % recovered.message
        time.sleep(rng.uniform(0.0, 2.0))
        ctrl.submit("c", JOINTS, [TrajectoryPoint((0.5, -0.5), (0.0, 0.0), (), 1.0)], 0.0)
        if not wait(lambda: len(done) == 3) or not done[2].succeeded:
            return "goal after recover: %s\n%s" % (done[2:3], drives(rig))
        return None
    except Exception as exc:  # a round that cannot even start is a failed round, not the end of the soak
        return "%s: %s" % (type(exc).__name__, exc)
    finally:
        rig.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=50)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    rng = random.Random(args.seed)
    failures = 0
    start = time.monotonic()
    for n in range(1, args.rounds + 1):
        problem = one_round(rng)
        failures += problem is not None
        print("round %d: %s" % (n, "ok" if problem is None else "FAILED: " + problem), flush=True)
    elapsed = time.monotonic() - start
    print("rounds %d, failed %d, %.1f s per round" % (args.rounds, failures, elapsed / max(args.rounds, 1)))
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
