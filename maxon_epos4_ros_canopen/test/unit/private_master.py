"""A ROS master for one test session, on a port the kernel picks when the
master binds it:

    python private_master.py

It prints its URI as one line on stdout, then serves until SIGINT or SIGTERM
or until its stdin closes.

Why not ``roscore -p PORT`` with a port probed free beforehand: the probe
gives the port back, and in the seconds until roscore binds it any other
process's bind(0) or connect() (the parameter server clients, nodes and
pytest workers running beside it) can take it. roscore then exits, or hangs
on a listener that does not speak XML-RPC, and the session waits in vain.
Binding port 0 in the master itself leaves no such window.

Like roscore it sets /run_id. It starts no rosout node: the tests read
each node's own output, not /rosout_agg.
"""
from __future__ import annotations

import signal
import sys
import threading
import uuid

import rosgraph
from rosmaster.master import Master


def main() -> int:
    master = Master(port=0)
    master.start()
    rosgraph.Master("/private_master", master_uri=master.uri).setParam("/run_id", str(uuid.uuid1()))
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    # stdin closing (the test process gone) ends the master as well
    threading.Thread(target=lambda: (sys.stdin.read(), stop.set()), daemon=True).start()
    print(master.uri, flush=True)
    stop.wait()
    master.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
