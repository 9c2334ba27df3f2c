"""The serving process's heap, kept out of the ticks' way.

After its imports a server holds ~150 000 objects (grpc, numpy, scipy, SQLAlchemy, alembic,
pyarrow, MuJoCo); a full (generation 2) garbage collection walks all of them and took 68 ms here,
more than a 20 Hz tick, with the event loop stopped. Ticks answered after such a pause are a tick
late or skipped. Freezing the heap once the server is up moves those objects out of the
collector's reach (gc.freeze), so later full collections walk only what sessions made since.
docs/decisions/0006-freeze-the-startup-heap.md.

    freeze_startup_heap()                 # once, when the server is up
    watch_collections(observe)            # observe(generation, seconds) after every collection
"""

from __future__ import annotations

import gc
import time
from collections.abc import Callable
from typing import Any

__all__ = ["freeze_startup_heap", "watch_collections"]


def freeze_startup_heap() -> int:
    """Collect what startup left as garbage, then freeze every object alive: the collector never
    walks them again. Returns how many are frozen."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


def watch_collections(observe: Callable[[int, float], None]) -> None:
    """Call `observe(generation, seconds)` after every garbage collection of this process."""
    started = [0.0]

    def callback(phase: str, info: dict[str, Any]) -> None:
        if phase == "start":
            started[0] = time.perf_counter()
        else:
            observe(int(info["generation"]), time.perf_counter() - started[0])

    gc.callbacks.append(callback)
