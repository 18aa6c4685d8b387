"""Real-time scheduling of the acquisition processes (Linux ``SCHED_FIFO``).

Why: on a machine short of CPU the device → subscriber latency tail is mostly time spent
runnable but not running, behind the other threads of the cell; under ``SCHED_FIFO`` a
woken acquisition thread takes a core from any normal task and runs its short burst to the
end (docs/daq.md, "Real-time scheduling", for the measured effect and the price: a
normal-priority subscriber on the same machine is then starved first).

The policy is set on every thread of the process; threads and processes started after
that inherit it (zenoh's runtime threads, the device workers). Threads that do long CPU work off the
acquisition path (the MCAP writer compresses whole chunks) go back to normal scheduling
with :func:`normal_for_this_thread`, so an acquisition thread of the same priority never
waits for them.
"""

from __future__ import annotations

import contextlib
import os
import threading

from daq.config import DaqConfig
from daq.errors import ConfigError

#: SCHED_FIFO priorities Linux accepts
MIN_PRIORITY, MAX_PRIORITY = 1, 99


def set_realtime(priority: int, where: str) -> None:
    """Put every thread of this process (and what they start later) under ``SCHED_FIFO``
    at ``priority`` (1-99); 0 leaves scheduling alone. ``where`` names the setting (config
    key or flag) in the error raised when the system refuses it."""
    if priority == 0:
        return
    if not MIN_PRIORITY <= priority <= MAX_PRIORITY:
        raise ConfigError(
            f"{where}: must be 0 (off) or {MIN_PRIORITY}-{MAX_PRIORITY}, got {priority}"
        )
    if not hasattr(os, "sched_setscheduler"):
        raise ConfigError(f"{where}: real-time scheduling needs Linux (SCHED_FIFO)")
    param = os.sched_param(priority)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, param)
        # threads started before us, at import (numpy's BLAS pool): the whole process
        for tid in _other_threads():
            with contextlib.suppress(ProcessLookupError):  # it ended meanwhile
                os.sched_setscheduler(tid, os.SCHED_FIFO, param)
    except PermissionError as exc:
        raise ConfigError(
            f"{where}: SCHED_FIFO priority {priority} refused ({exc.strerror}): needs root, "
            f"CAP_SYS_NICE, or an RLIMIT_RTPRIO of at least {priority} (`ulimit -r`, "
            "limits.conf 'rtprio'); set it to 0 to run with normal scheduling"
        ) from None


def _other_threads() -> list[int]:
    try:
        tids = [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return []
    return [t for t in tids if t != threading.get_native_id()]


def set_realtime_of(cfg: DaqConfig) -> None:
    """:func:`set_realtime` with ``[publish] realtime_priority`` of ``cfg``."""
    set_realtime(cfg.publish.realtime_priority, f"{cfg.source}: [publish]: key 'realtime_priority'")


def normal_for_this_thread() -> None:
    """Normal scheduling for the calling thread only (no privilege needed to lower)."""
    if hasattr(os, "sched_setscheduler") and os.sched_getscheduler(0) != os.SCHED_OTHER:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


def describe() -> str:
    """The calling thread's policy, as health reports it: ``"fifo:10"`` or ``"normal"``."""
    if not hasattr(os, "sched_getscheduler"):
        return "normal"
    policy = os.sched_getscheduler(0)
    if policy == os.SCHED_FIFO:
        return f"fifo:{os.sched_getparam(0).sched_priority}"
    if policy == os.SCHED_RR:
        return f"rr:{os.sched_getparam(0).sched_priority}"
    return "normal"
