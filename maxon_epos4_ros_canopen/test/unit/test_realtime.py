"""The cycle thread's SCHED_FIFO request and its fallback, with the
permission present and absent: the OS functions are injected, so no test
needs (or uses) the permission it checks."""
import errno
import logging
import os
import threading

import pytest

from maxon_epos4_ros_canopen.config import ConfigError, load_config
from maxon_epos4_ros_canopen.config_schema import RealtimeConfig
from maxon_epos4_ros_canopen.driver import realtime

HERE = os.path.dirname(os.path.abspath(__file__))
DCF1 = os.path.normpath(os.path.join(HERE, "..", "..", "config", "epos4_node1.dcf"))


class FakeOs:
    """sched_setscheduler as the kernel answers it: granted up to ``allowed``
    (CAP_SYS_NICE: 99; RLIMIT_RTPRIO n: n; none: 0), PermissionError above."""
    SCHED_FIFO = 1

    def __init__(self, allowed):
        self.allowed = allowed
        self.calls = []

    @staticmethod
    def sched_param(priority):
        return ("param", priority)

    def sched_setscheduler(self, pid, policy, param):
        self.calls.append((pid, policy, param[1]))
        if param[1] > self.allowed:
            raise PermissionError(errno.EPERM, "Operation not permitted")


@pytest.fixture(autouse=True)
def fresh_warnings(monkeypatch):
    monkeypatch.setattr(realtime, "_warned", set())


def run(cfg, fake_os, rtprio=0, mlock=lambda: 0):
    logger = logging.getLogger("test_realtime")
    return realtime.apply(cfg, os_module=fake_os, rtprio_limit=lambda: rtprio, mlockall=mlock, logger=logger)


def test_permitted_the_thread_itself_runs_fifo(caplog):
    fake = FakeOs(allowed=99)  # CAP_SYS_NICE
    out = run(RealtimeConfig(priority=70), fake)
    assert (out.fifo, out.priority, out.memory_locked, out.warning) == (True, 70, False, "")
    assert fake.calls == [(0, FakeOs.SCHED_FIFO, 70)]  # pid 0: the calling thread
    assert not caplog.records


def test_rtprio_limit_below_the_priority_takes_the_limit_and_says_so(caplog):
    fake = FakeOs(allowed=20)
    out = run(RealtimeConfig(priority=70), fake, rtprio=20)
    assert (out.fifo, out.priority) == (True, 20)
    assert [c[2] for c in fake.calls] == [70, 20]
    assert "SCHED_FIFO 20 instead of 70" in out.warning and "rtprio 70" in out.warning
    assert len([r for r in caplog.records if r.levelno == logging.WARNING]) == 1


def test_not_permitted_one_warning_says_what_to_set(caplog):
    fake = FakeOs(allowed=0)
    out = run(RealtimeConfig(priority=50), fake)
    assert (out.fifo, out.priority) == (False, 0)
    assert fake.calls == [(0, FakeOs.SCHED_FIFO, 50)]
    for text in ("not permitted to run SCHED_FIFO 50", "/etc/security/limits.conf", "rtprio 50", "ulimit -r 50",
                 "CAP_SYS_NICE", "realtime: enabled: false"):
        assert text in caplog.text
    # the cycle thread starts again at each init and recover: still one warning
    run(RealtimeConfig(priority=50), fake)
    assert len([r for r in caplog.records if r.levelno == logging.WARNING]) == 1


def test_turned_off_asks_nothing(caplog):
    fake = FakeOs(allowed=99)
    locks = []
    out = run(RealtimeConfig(enabled=False, lock_memory=True), fake, mlock=lambda: locks.append(1) or 0)
    assert out == realtime.Outcome(False, 0, False) and fake.calls == [] and locks == []
    assert not caplog.records


def test_no_fifo_on_the_platform():
    out = run(RealtimeConfig(), object())
    assert not out.fifo and "not available" in out.warning


def test_memory_locked_when_asked_and_refusal_named(caplog):
    out = run(RealtimeConfig(lock_memory=True), FakeOs(allowed=99), mlock=lambda: 0)
    assert out.memory_locked and out.warning == ""
    out = run(RealtimeConfig(lock_memory=True), FakeOs(allowed=99), mlock=lambda: errno.ENOMEM)
    assert out.fifo and not out.memory_locked
    assert "memory not locked" in out.warning and "memlock" in out.warning


def test_other_errors_are_reported_not_raised():
    class Broken(FakeOs):
        def sched_setscheduler(self, pid, policy, param):
            raise OSError(errno.EINVAL, "Invalid argument")
    out = run(RealtimeConfig(), Broken(99))
    assert not out.fifo and "refused" in out.warning


def test_the_real_request_from_a_thread_leaves_the_process_alone():
    """On this host, whichever way the kernel answers: the calling thread
    alone changes class, and nothing raises."""
    if not hasattr(os, "sched_getscheduler"):
        pytest.skip("no sched_getscheduler on this platform")
    before = os.sched_getscheduler(0)
    seen = {}

    def thread():
        out = realtime.apply(RealtimeConfig(priority=1), logger=logging.getLogger("test_realtime"))
        seen["out"], seen["policy"] = out, os.sched_getscheduler(0)
    t = threading.Thread(target=thread)
    t.start()
    t.join()
    assert seen["policy"] == (os.SCHED_FIFO if seen["out"].fifo else before)
    assert os.sched_getscheduler(0) == before


def test_config_key():
    base = {"sync": {"interval_ms": 10}, "nodes": {"n1": {"id": 1, "eds_file": DCF1}}}
    assert load_config(base, "t").realtime == RealtimeConfig(True, 50, False)
    cfg = load_config(dict(base, realtime={"enabled": False, "priority": 80, "lock_memory": True}), "t")
    assert cfg.realtime == RealtimeConfig(False, 80, True)
    for bad, key in (({"priority": 0}, "realtime/priority"), ({"priority": 100}, "realtime/priority"),
                     ({"enabled": "yes"}, "realtime/enabled")):
        with pytest.raises(ConfigError) as e:
            load_config(dict(base, realtime=bad), "t")
        assert e.value.key == key
    assert "unknown option realtime/policy" in " ".join(load_config(dict(base, realtime={"policy": 1}), "t").warnings)


def test_the_driver_cycle_thread_asks_at_its_start():
    """The CSP example with realtime priority 1: the driver's cycle thread
    is SCHED_FIFO 1 exactly when the driver says the kernel granted it;
    with realtime enabled: false it keeps the process's class."""
    from csp_rig import CspRig
    main_policy = os.sched_getscheduler(0)
    for enabled in (True, False):
        rig = CspRig(adjust=lambda p: p.update(realtime={"enabled": enabled, "priority": 1}))
        try:
            rig.start()
            out = rig.driver.realtime
            cycle = [t for t in threading.enumerate() if t.name == "epos4_driver_cycle"]
            assert len(cycle) == 1
            policy = os.sched_getscheduler(cycle[0].native_id)
            assert policy == (os.SCHED_FIFO if out.fifo else main_policy)
            if out.fifo:
                assert os.sched_getparam(cycle[0].native_id).sched_priority == 1
            assert out.fifo is False or enabled
            assert os.sched_getscheduler(0) == main_policy
        finally:
            rig.close()
