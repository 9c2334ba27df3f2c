"""The context-manager half of anything with a lifecycle: a subclass writes `close()`, safe to
call twice, and gets `with` for free::

    class Recorder(Closeable):
        def close(self) -> None: ...

    with Recorder() as recorder:   # recorder.close() on the way out, whatever happened
        ...
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from types import TracebackType
from typing import Self

__all__ = ["Closeable"]


class Closeable(ABC):
    """`with obj:` closes `obj` on exit; `close()` must be safe to call twice."""

    @abstractmethod
    def close(self) -> None:
        """Release what the object holds; a second call does nothing."""

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
