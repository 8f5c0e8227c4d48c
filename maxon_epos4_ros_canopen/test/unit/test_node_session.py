"""The node tests' session (node_session.py) runs on a master of its own:
the process answering at its ROS_MASTER_URI is the one the session started,
not whatever took a port probed free beforehand."""
from __future__ import annotations

from pathlib import Path

import rosgraph

from node_session import Session


def test_the_session_master_is_its_own(tmp_path: Path) -> None:
    sessions = [Session(tmp_path / name) for name in ("a", "b")]
    try:
        for s in sessions:
            s.tmp.mkdir()
            s.start_master()
        uris = [s.env["ROS_MASTER_URI"] for s in sessions]
        assert uris[0] != uris[1]
        for s, uri in zip(sessions, uris):
            master = rosgraph.Master("/test_node_session", master_uri=uri)
            assert master.getPid() == s.procs[0].pid, "another process answers at %s" % uri
            assert master.getParam("/run_id")
    finally:
        for s in sessions:
            s.close()
    for s in sessions:
        assert s.procs[0].returncode == 0, s.log("master.log")
