"""Progress bars on stderr, and only when stderr is a terminal: redirected output (a log, a pipe,
CI) stays free of carriage returns, and stdout carries results only::

    with progress_bar(total=200, desc="ticks answered", unit="tick") as bar:
        bar.update(1)

tqdm draws the bar when it is installed (jitdyn[experiments]); otherwise a one-line counter does.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator
from typing import Any, TextIO, TypeVar

from jitdyn.lifecycle import Closeable

__all__ = ["ProgressBar", "progress_bar", "track"]

_T = TypeVar("_T")


class ProgressBar(Closeable):
    """`update(n)`, `n`, `close()` (safe twice); draws nothing when `enabled` is False."""

    def __init__(self, *, total: int, desc: str, unit: str, enabled: bool, stream: TextIO) -> None:
        self.n = 0
        self._total = total
        self._desc = desc
        self._unit = unit
        self._stream = stream
        self._tqdm: Any = None
        self._enabled = enabled
        self._last_draw = 0.0
        if enabled:
            try:
                from tqdm import tqdm
            except ImportError:
                pass
            else:
                self._tqdm = tqdm(
                    total=total, desc=desc, unit=unit, file=stream, leave=False, mininterval=0.5
                )

    def update(self, n: int = 1) -> None:
        self.n += n
        if self._tqdm is not None:
            self._tqdm.update(n)
        elif self._enabled and time.monotonic() - self._last_draw >= 0.5:
            self._last_draw = time.monotonic()
            self._stream.write(f"\r{self._desc}: {self.n}/{self._total} {self._unit}s")
            self._stream.flush()

    def close(self) -> None:
        if self._tqdm is not None:
            self._tqdm.close()
            self._tqdm = None
        elif self._enabled and self._last_draw:
            self._stream.write("\r\033[K")
            self._stream.flush()
        self._enabled = False


def progress_bar(
    *, total: int, desc: str, unit: str = "it", enabled: bool = True, stream: TextIO | None = None
) -> ProgressBar:
    """A bar on `stream` (default stderr), drawn only if `enabled` and the stream is a terminal."""
    target = sys.stderr if stream is None else stream
    return ProgressBar(total=total, desc=desc, unit=unit, enabled=enabled and target.isatty(), stream=target)


def track(items: Iterable[_T], *, total: int, desc: str, enabled: bool = True) -> Iterator[_T]:
    """Iterate `items` with a bar (see `progress_bar`)."""
    with progress_bar(total=total, desc=desc, enabled=enabled) as bar:
        for item in items:
            yield item
            bar.update(1)
