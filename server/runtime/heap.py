"""The serving process's heap, kept out of the ticks' way.

After its imports a server holds ~150 000 objects (grpc, numpy, scipy, SQLAlchemy, alembic,
pyarrow, MuJoCo); a full (generation 2) garbage collection walks all of them and took 68 ms here,
more than a 20 Hz tick, with the event loop stopped. Ticks answered after such a pause are a tick
late or skipped. Freezing the heap once the server is up moves those objects out of the
collector's reach (gc.freeze), so later full collections walk only what sessions made since.
docs/decisions/0006-freeze-the-startup-heap.md.

    freeze_startup_heap()                 # once, when the server is up
    pauses = watch_collections()          # every collection's pause, kept
    pauses.drain(observe)                 # observe(generation, seconds) each, from the loop
"""

from __future__ import annotations

import gc
import time
from collections import deque
from collections.abc import Callable
from typing import Any, Final

__all__ = ["CollectionPauses", "freeze_startup_heap", "watch_collections"]

_KEPT: Final = 4096  # pauses kept between two drains; older ones are dropped


def freeze_startup_heap() -> int:
    """Collect what startup left as garbage, then freeze every object alive: the collector never
    walks them again. Returns how many are frozen."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


class CollectionPauses:
    """The garbage collector's pauses, (generation, seconds), kept until `drain`.

    A collection starts wherever an allocation crosses a threshold: in any thread, inside any code,
    also code that holds a lock. prometheus-client holds its (non-reentrant) lock while it makes a
    labelled series, which allocates; a callback that observed a metric there waited for that lock
    forever, and the process with it (a server hung with its sessions opening). So the callback
    only appends to a deque (atomic, lock-free), and the pauses reach the metrics from the loop.
    """

    def __init__(self) -> None:
        self._pauses: deque[tuple[int, float]] = deque(maxlen=_KEPT)
        self._started = 0.0

    def callback(self, phase: str, info: dict[str, Any]) -> None:
        if phase == "start":
            self._started = time.perf_counter()
        else:
            self._pauses.append((int(info["generation"]), time.perf_counter() - self._started))

    def drain(self, observe: Callable[[int, float], None]) -> int:
        """Call `observe(generation, seconds)` for every pause kept before this call; how many.
        (Observing allocates, and so may collect: those pauses wait for the next drain.)"""
        count = len(self._pauses)
        for _ in range(count):
            observe(*self._pauses.popleft())
        return count


def watch_collections() -> CollectionPauses:
    """Keep the pause of every garbage collection of this process from now on."""
    pauses = CollectionPauses()
    gc.callbacks.append(pauses.callback)
    return pauses
