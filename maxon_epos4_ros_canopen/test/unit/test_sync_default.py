"""SYNC from the kernel by default, a clean fallback elsewhere: with the
shipped bus layer (kernel_timer by default) on python-can's virtual bus,
which has no kernel timer, the cycle sends every SYNC itself right after
its RxPDOs, and no sender thread sends one of its own, not even once."""
import os

from csp_rig import CspRig, wait
from maxon_epos4_ros_canopen.config import load_config
from maxon_epos4_ros_canopen.config_schema import SyncConfig

HERE = os.path.dirname(os.path.abspath(__file__))
DCF1 = os.path.normpath(os.path.join(HERE, "..", "..", "config", "epos4_node1.dcf"))


def test_kernel_timer_is_the_default():
    cfg = load_config({"sync": {"interval_ms": 10}, "nodes": {"n1": {"id": 1, "eds_file": DCF1}}}, "t")
    assert cfg.sync.kernel_timer is True and SyncConfig().kernel_timer is True
    cfg = load_config({"sync": {"interval_ms": 10, "kernel_timer": False},
                       "nodes": {"n1": {"id": 1, "eds_file": DCF1}}}, "t")
    assert cfg.sync.kernel_timer is False


def test_virtual_bus_falls_back_to_the_cycle_sending_sync():
    rig = CspRig()
    try:
        assert rig.params["sync"].get("kernel_timer", True) is True  # the shipped layer leaves it on
        rig.start()
        assert rig.driver.sync is not None and not rig.driver.sync.kernel_timed
        assert wait(lambda: sum(f.arbitration_id == 0x80 for f in rig.listener.frames) >= 20, 30.0)
        frames = list(rig.listener.frames)
        ids = [f.arbitration_id for f in frames]
        # every SYNC follows the RxPDOs of both drives sent since the SYNC before it
        # (a thread's SYNC would come first, before the cycle's first RxPDOs, or between them)
        previous = -1
        for i in [i for i, cob in enumerate(ids) if cob == 0x80][:20]:
            between = ids[previous + 1:i]
            assert 0x201 in between and 0x202 in between, between
            previous = i
    finally:
        rig.close()
