"""MuJoCo's warnings routed to Python logging (logger `jitdyn.mujoco`), instead of MuJoCo's default
of printing them and appending them to MUJOCO_LOG.TXT in whatever folder the process runs from::

    route_mujoco_messages()          # once per process; the server and the `jitdyn` command do it
    warning_counts()                 # {"Nan, Inf or huge value in QACC at DOF #. ...": 754}

MuJoCo calls the handler from whichever thread warned, mujoco.rollout's C++ threads included. A
warning repeated in a loop (an unstable simulation warns at every step) is logged at its 1st, 2nd,
4th, 8th, ... occurrence with the count so far, so a log stays readable. MuJoCo's errors need no
handler here: the Python bindings raise them as exceptions (mujoco.FatalError) and log nothing.
Per session: a session's work runs under `counting(counter)` (the runtime does it around each tick,
the worker pool carries it into its threads), and each warning raised meanwhile also counts there.

    counter = WarningCounter()
    with counting(counter):
        mujoco.mj_step(model, data)  # a warning here adds to counter.count
"""

from __future__ import annotations

import logging
import re
import threading
from collections import Counter
from collections.abc import Iterable
from typing import Any

import mujoco

__all__ = [
    "WarningCounter",
    "counting",
    "current_counter",
    "data_warnings",
    "route_mujoco_messages",
    "warning_counts",
]

_log = logging.getLogger("jitdyn.mujoco")
_lock = threading.Lock()
_counts: Counter[str] = Counter()
_NUMBERS = re.compile(r"[-+]?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")


def _kind(message: str) -> str:
    """The message without its numbers (DOF index, time): one kind per repeated warning."""
    return _NUMBERS.sub("#", message.strip())


class WarningCounter:
    """MuJoCo warnings raised while one session's work ran (thread-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._count = 0

    def add(self) -> None:
        with self._lock:
            self._count += 1

    @property
    def count(self) -> int:
        with self._lock:
            return self._count


_local = threading.local()


def current_counter() -> WarningCounter | None:
    """The counter of the session whose work this thread runs now, if any."""
    counter: WarningCounter | None = getattr(_local, "counter", None)
    return counter


class counting:  # lower case: it is used as the function it replaced, `with counting(counter):`
    """Count the warnings this thread raises meanwhile in `counter` too (None: none).

    A class rather than a generator under contextlib.contextmanager: every REALTIME tick enters
    it, and the generator's machinery cost 3x the two assignments it guards."""

    __slots__ = ("_counter", "_previous")

    def __init__(self, counter: WarningCounter | None) -> None:
        self._counter = counter
        self._previous: WarningCounter | None = None

    def __enter__(self) -> None:
        self._previous = getattr(_local, "counter", None)
        _local.counter = self._counter

    def __exit__(self, *exc: object) -> None:
        _local.counter = self._previous


def _on_warning(message: str) -> None:
    kind = _kind(message)
    session = current_counter()
    if session is not None:
        session.add()
    with _lock:
        _counts[kind] += 1
        count = _counts[kind]
    if count & (count - 1) == 0:  # 1, 2, 4, 8, ...
        _log.warning("MuJoCo: %s%s", message.strip(), f" ({count} such warnings so far)" if count > 1 else "")


def route_mujoco_messages() -> None:
    """Send MuJoCo's warnings to the `jitdyn.mujoco` logger from now on; safe to call again."""
    mujoco.set_mju_user_warning(_on_warning)


def warning_counts() -> dict[str, int]:
    """The warnings MuJoCo raised in this process since routing, by kind (numbers as '#')."""
    with _lock:
        return dict(_counts)


def data_warnings(datas: Iterable[Any]) -> int:
    """How many warnings MuJoCo counted in these MjData (every kind of mjtWarning)."""
    return sum(
        int(d.warning[kind].number) for d in datas for kind in range(int(mujoco.mjtWarning.mjNWARNING))
    )
