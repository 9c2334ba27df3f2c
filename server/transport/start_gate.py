"""When an admitted REALTIME session's clock starts: its `opened` waits while the process is still
opening or refusing others, so that its first ticks are not answered late by that work
(docs/decisions/0225-a-session-starts-after-the-burst.md).

    gate = StartGate()
    with gate.opening():            # around each open, while the slow steps' thread runs it
        ...
    gate.refused()                  # each open refused for want of capacity
    held = await gate.wait()        # before an admitted session's `opened` is written

A burst of opens costs the process CPU for a second or two: each admitted open runs tens of
milliseconds of Python (the model, the estimator, the log), and each refused one a millisecond or
more of gRPC's. Ticks answered meanwhile go late. A session held here has not started: its client
waits for `opened` and its clock starts when it comes. The sessions held are let go one at a time,
SPACING apart, so that their ticks do not all fall due at once, and none waits more than HOLD.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections import deque
from collections.abc import Iterator
from typing import Final

__all__ = ["HOLD", "QUIET", "SPACING", "StartGate"]

HOLD: Final = 2.0  # s: the longest a session's start is held
QUIET: Final = 0.1  # s with no open refused before the held sessions start
SPACING: Final = 2e-3  # s between the starts of two held sessions
_LOOK: Final = 0.01  # s between two looks at whether the process is still busy


class StartGate:
    """The starts held while the process opens or refuses sessions. On the event loop only."""

    def __init__(self, *, hold: float = HOLD, quiet: float = QUIET, spacing: float = SPACING) -> None:
        self._hold, self._quiet, self._spacing = hold, quiet, spacing
        self._opening = 0
        self._refused_at = -math.inf
        self._waiting: deque[tuple[asyncio.Future[None], float]] = deque()
        self._releasing: asyncio.Task[None] | None = None

    @contextlib.contextmanager
    def opening(self) -> Iterator[None]:
        """Around one open: the process is busy while any is under way."""
        self._opening += 1
        try:
            yield
        finally:
            self._opening -= 1

    def refused(self) -> None:
        """An open was refused now for want of capacity (RESOURCE_EXHAUSTED)."""
        self._refused_at = time.monotonic()

    def busy(self) -> bool:
        """Whether an open is under way or one was refused in the last QUIET s."""
        return self._opening > 0 or time.monotonic() - self._refused_at < self._quiet

    async def wait(self) -> float:
        """Wait until the process is no longer busy, or HOLD has passed, and the sessions held
        before this one have started; the seconds held."""
        if not self._waiting and not self.busy():
            return 0.0
        began = time.monotonic()
        started = asyncio.get_running_loop().create_future()
        self._waiting.append((started, began + self._hold))
        if self._releasing is None or self._releasing.done():
            self._releasing = asyncio.ensure_future(self._release())
        await started
        return time.monotonic() - began

    async def _release(self) -> None:
        while self._waiting:
            started, until = self._waiting[0]
            if started.done():  # its stream was cancelled while it waited
                self._waiting.popleft()
                continue
            if self.busy() and time.monotonic() < until:
                await asyncio.sleep(_LOOK)
                continue
            self._waiting.popleft()
            started.set_result(None)
            if self._waiting:
                await asyncio.sleep(self._spacing)
