"""How often the interpreter hands the GIL to another thread, following the REALTIME sessions open
in the process: a fifth of the tightest grace, between SWITCH_FLOOR and CPython's default
(docs/decisions/0003-gil-switch-interval.md says what was measured).

    switch = SwitchInterval()
    switch.add(2.5e-3)          # a 200 Hz session opens: the GIL changes hands every 0.5 ms
    switch.remove(2.5e-3)       # it ends: back to the default

A frame is read on the event loop only once gRPC's poller thread has had the GIL, and CPython makes
a waiting thread wait up to the switch interval while the loop runs Python; for slow sessions a
short interval only adds switches, so it is as short as the tightest grace needs and no shorter.
"""

from __future__ import annotations

import sys
import threading
from collections import Counter
from typing import Final

__all__ = ["PROCESS_SWITCH_INTERVAL", "SWITCH_DEFAULT", "SWITCH_FLOOR", "SWITCH_SHARE", "SwitchInterval"]

SWITCH_DEFAULT: Final = sys.getswitchinterval()  # s, CPython's (5 ms unless changed)
SWITCH_SHARE: Final = 0.2  # of the tightest grace
SWITCH_FLOOR: Final = 2e-4  # s


class SwitchInterval:
    """The graces of the REALTIME sessions open, and the switch interval they call for. Setting it
    is process-wide: one instance per process (`PROCESS_SWITCH_INTERVAL`), whatever admitted the
    sessions. Thread-safe."""

    def __init__(self) -> None:
        self._graces: Counter[float] = Counter()
        self._lock = threading.Lock()

    def add(self, grace: float) -> None:
        """A session with this grace (s) opened."""
        self._count(grace, +1)

    def remove(self, grace: float) -> None:
        """A session with this grace (s) ended."""
        self._count(grace, -1)

    def _count(self, grace: float, change: int) -> None:
        with self._lock:
            self._graces[grace] += change
            if self._graces[grace] <= 0:
                del self._graces[grace]
            interval = SWITCH_DEFAULT
            if self._graces:
                interval = min(SWITCH_DEFAULT, max(SWITCH_FLOOR, SWITCH_SHARE * min(self._graces)))
            sys.setswitchinterval(interval)


PROCESS_SWITCH_INTERVAL: Final = SwitchInterval()
