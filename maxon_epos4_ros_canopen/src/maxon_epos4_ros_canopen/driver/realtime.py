"""The cycle thread's scheduling: SCHED_FIFO where the process may have it.

As ros2_control's controller manager does for its update thread, the
driver's cycle thread asks the kernel for the real-time FIFO class at a
configured priority, from the thread itself (``sched_setscheduler(0, ...)``
acts on the calling thread on Linux), so the notifier, ROS and the rest of
the process keep their normal scheduling. Where the process may not
(neither CAP_SYS_NICE nor an RLIMIT_RTPRIO as high as asked), the thread
takes the highest priority the limit allows, or stays as it is, and one
warning says what to set. Memory is locked (mlockall) when asked, so no
page fault stalls a cycle.

The OS functions come in as arguments for the tests: no test needs the
permission it checks.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
from dataclasses import dataclass
from typing import Any, Callable, Optional

from ..config_schema import RealtimeConfig

log = logging.getLogger(__name__)

# <sys/mman.h>: lock what is mapped now and what will be
MCL_CURRENT, MCL_FUTURE = 1, 2
_LIMITS_HINT = ("allow it with a line '<user> - rtprio %d' in /etc/security/limits.conf (log in again), "
                "'ulimit -r %d' in the shell that starts the node, LimitRTPRIO=%d in a systemd unit, or "
                "CAP_SYS_NICE (setcap cap_sys_nice+ep on the python interpreter)")


@dataclass(frozen=True)
class Outcome:
    """What the cycle thread got: its policy and priority, whether memory
    is locked, and the warning logged (empty when everything asked was had)."""
    fifo: bool
    priority: int
    memory_locked: bool
    warning: str = ""


def _mlockall() -> int:
    """mlockall(MCL_CURRENT | MCL_FUTURE) through libc: Python's os module
    has no mlockall, and no maintained library wraps it alone. Returns 0 or
    an errno value."""
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    if libc.mlockall(MCL_CURRENT | MCL_FUTURE) == 0:
        return 0
    return ctypes.get_errno()


def _rtprio_soft_limit() -> int:
    import resource
    return resource.getrlimit(resource.RLIMIT_RTPRIO)[0]


# warnings already logged in this process: a cycle thread restarted by each
# init or recover says the same once, not every time
_warned = set()


def apply(cfg: RealtimeConfig, os_module: Any = os, rtprio_limit: Callable[[], int] = _rtprio_soft_limit,
          mlockall: Callable[[], int] = _mlockall, logger: logging.Logger = log) -> Outcome:
    """Ask for SCHED_FIFO at ``cfg.priority`` for the calling thread (and
    mlockall when ``cfg.lock_memory``); never raises. Call it from the
    thread to be scheduled."""
    if not cfg.enabled:
        return Outcome(False, 0, False)
    problems = []
    fifo, priority = False, 0
    hint = _LIMITS_HINT % ((cfg.priority,) * 3)
    if not hasattr(os_module, "sched_setscheduler") or not hasattr(os_module, "SCHED_FIFO"):
        problems.append("SCHED_FIFO is not available on this platform")
    else:
        tries = [cfg.priority]
        try:
            soft: Optional[int] = int(rtprio_limit())
        except (OSError, ValueError, AttributeError):
            soft = None
        if soft is not None and 0 < soft < cfg.priority:
            tries.append(soft)  # the most the limit allows without CAP_SYS_NICE
        for p in tries:
            try:
                os_module.sched_setscheduler(0, os_module.SCHED_FIFO, os_module.sched_param(p))
            except PermissionError:
                continue
            except OSError as e:
                problems.append("SCHED_FIFO %d refused: %s" % (p, e))
                break
            fifo, priority = True, p
            break
        if fifo and priority < cfg.priority:
            problems.append("SCHED_FIFO %d instead of %d (RLIMIT_RTPRIO %d): %s"
                            % (priority, cfg.priority, priority, hint))
        elif not fifo and not problems:
            problems.append("not permitted to run SCHED_FIFO %d (RLIMIT_RTPRIO %s, no CAP_SYS_NICE), the cycle "
                            "thread keeps normal scheduling: %s" % (cfg.priority, soft, hint))
    locked = False
    if cfg.lock_memory:
        err = mlockall()
        if err == 0:
            locked = True
        else:
            problems.append("memory not locked (mlockall: %s): raise the locked-memory limit ('<user> - memlock "
                            "unlimited' in /etc/security/limits.conf, LimitMEMLOCK=infinity in a systemd unit)"
                            % os.strerror(err))
    warning = "; ".join(problems)
    if warning and warning not in _warned:
        _warned.add(warning)
        logger.warning("driver cycle thread: %s (realtime: enabled: false turns the request off)", warning)
    return Outcome(fifo, priority, locked, warning)
