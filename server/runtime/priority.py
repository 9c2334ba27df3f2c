"""The serving processes' CPU priority: real-time ticks ahead of the batch work beside them.

    problem = set_priority(-10)     # every thread of this process, and the processes it starts
    if problem: print(problem)      # not permitted (no CAP_SYS_NICE): runs at the priority it had
    prioritise(-10)                 # the same, the problem logged as a warning

Linux counts nice per thread: each thread of the process is set, and threads and processes started
afterwards inherit it. All of a process's threads get the same priority: a thread of lower
priority holding the GIL would keep the loop waiting for it whenever the machine is busy (priority
inversion). Why a server raises it, and what it does and does not protect from:
docs/decisions/0011-serving-priority.md.
"""

from __future__ import annotations

import logging
import os

__all__ = ["prioritise", "set_priority"]

_log = logging.getLogger(__name__)


def _threads() -> list[int]:
    """The native ids of this process's threads (Linux), or [0]: the process, elsewhere."""
    try:
        return [int(tid) for tid in os.listdir("/proc/self/task")]
    except OSError:
        return [0]


def set_priority(nice: int) -> str | None:
    """Set this process's threads to `nice`; None when done (or already so), else a line saying why
    not and how to allow it."""
    if not hasattr(os, "setpriority"):
        return (
            f"the serving processes' CPU priority (--nice {nice}) is not settable on this system; left as is"
        )
    current = os.getpriority(os.PRIO_PROCESS, 0)
    if current == nice:
        return None
    try:
        for tid in _threads():
            try:
                os.setpriority(os.PRIO_PROCESS, tid, nice)
            except ProcessLookupError:  # a thread that ended meanwhile
                pass
    except PermissionError:
        for tid in _threads():  # back as it was, all threads alike
            try:
                os.setpriority(os.PRIO_PROCESS, tid, current)
            except (PermissionError, ProcessLookupError):
                pass
        return (
            f"the serving processes run at nice {current}, not --nice {nice}: lowering it needs "
            "CAP_SYS_NICE (run as root, `setcap cap_sys_nice+ep` on the Python binary, or --nice "
            f"{current} to keep it); batch work started beside the server at the same priority can "
            "make admitted sessions late"
        )
    return None


def prioritise(nice: int) -> None:
    """`set_priority(nice)`, a problem logged as a warning."""
    problem = set_priority(nice)
    if problem is not None:
        _log.warning("%s", problem)
