"""Wake-ups on the event loop to within tens of microseconds, for REALTIME deadlines.

asyncio's timers wake through the selector, and Linux's epoll_wait takes its timeout in whole
milliseconds, which Python rounds up: `asyncio.sleep` came back 0.65 ms late at the median and
1.04 ms at p90 here. That is the whole grace of a 500 Hz session (dt/2 = 1 ms) and 40 % of a
200 Hz one's, spent before any work starts. A timerfd armed for the earliest wake-up, watched by
the loop like any socket, makes epoll return when it expires: a wake-up then costs one read and
one re-arm, and nothing spins.

    alarm = Alarm.of(asyncio.get_running_loop())
    await alarm.sleep_until(time.monotonic() + 0.002)

    wakeup = alarm.wakeup()               # one sleeper whose wake-up can be moved while it sleeps
    await wakeup.until(deadline)          # in one task
    wakeup.move(later)                    # in another: the sleeper wakes at `later` instead

Where there is no timerfd (not Linux, or a libc without it), `sleep_until` is asyncio.sleep.
"""

from __future__ import annotations

import asyncio
import ctypes
import ctypes.util
import heapq
import itertools
import os
import time
import weakref
from typing import ClassVar, Final

__all__ = ["Alarm", "Wakeup"]

_CLOCK_MONOTONIC: Final = 1  # the clock of time.monotonic() on Linux
_TFD_NONBLOCK: Final = os.O_NONBLOCK
_TFD_CLOEXEC: Final = os.O_CLOEXEC
_TFD_TIMER_ABSTIME: Final = 1


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


class _Itimerspec(ctypes.Structure):
    _fields_ = [("it_interval", _Timespec), ("it_value", _Timespec)]


def _libc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name, use_errno=True)
        create, settime = libc.timerfd_create, libc.timerfd_settime
    except (OSError, AttributeError, TypeError):
        return None
    create.argtypes, create.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    settime.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.POINTER(_Itimerspec), ctypes.c_void_p]
    settime.restype = ctypes.c_int
    return libc


_LIBC: Final = _libc() if os.name == "posix" else None


def _close_quietly(fd: int) -> None:
    try:
        os.close(fd)
    except OSError:
        pass  # closed already


class _Entry:
    """A pending wake-up in the heap; a moved one is left there dead, and dropped at the top."""

    __slots__ = ("future", "live", "when")

    def __init__(self, when: float, future: asyncio.Future[None]) -> None:
        self.when = when
        self.future = future
        self.live = True


class Alarm:
    """One timerfd per event loop, armed for the earliest pending wake-up."""

    _by_loop: ClassVar[weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, Alarm]] = (
        weakref.WeakKeyDictionary()
    )

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        # Weakly: the registry's values must not keep their keys (the loops) alive.
        self._loop_ref = weakref.ref(loop)
        self._heap: list[tuple[float, int, _Entry]] = []
        self._order = itertools.count()
        self._armed = float("inf")  # the expiry the timer is set to
        self._spec = _Itimerspec()
        self._fd = -1
        if _LIBC is not None:
            fd = _LIBC.timerfd_create(_CLOCK_MONOTONIC, _TFD_NONBLOCK | _TFD_CLOEXEC)
            if fd >= 0:
                try:
                    loop.add_reader(fd, self._fire)
                except (NotImplementedError, RuntimeError):  # a loop that cannot watch descriptors
                    os.close(fd)
                else:
                    self._fd = fd
                    weakref.finalize(loop, self._release)

    @classmethod
    def of(cls, loop: asyncio.AbstractEventLoop) -> Alarm:
        """The loop's alarm, made on first use."""
        alarm = cls._by_loop.get(loop)
        if alarm is None:
            alarm = cls._by_loop[loop] = cls(loop)
        return alarm

    @property
    def precise(self) -> bool:
        """Whether wake-ups come from a timerfd (else from asyncio's millisecond timers)."""
        return self._fd >= 0

    async def sleep_until(self, when: float) -> None:
        """Return at time.monotonic() `when` (at once when it has passed)."""
        if when <= time.monotonic():
            return
        if self._fd < 0:
            await asyncio.sleep(when - time.monotonic())
            return
        future: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._push(when, future)
        await future  # a cancelled sleeper's entry is dropped when it reaches the top

    def wakeup(self) -> Wakeup:
        """A sleeper of this loop whose wake-up can be moved while it sleeps."""
        return Wakeup(self)

    def _push(self, when: float, future: asyncio.Future[None]) -> _Entry:
        entry = _Entry(when, future)
        heapq.heappush(self._heap, (when, next(self._order), entry))
        if when < self._armed:
            self._arm(when)
        return entry

    def _drop(self, entry: _Entry) -> None:
        """Forget a moved wake-up; when it was the one the timer is armed for, re-arm for the next,
        so that the loop is not woken for nothing."""
        entry.live = False
        heap = self._heap
        if heap and heap[0][2] is entry:
            while heap and not heap[0][2].live:
                heapq.heappop(heap)
            if heap:
                self._arm(heap[0][0])

    def close(self) -> None:
        """Stop watching the timer and cancel every sleeper (the loop's end does it too)."""
        loop = self._loop_ref()
        if self._fd >= 0 and loop is not None and not loop.is_closed():
            loop.remove_reader(self._fd)
        self._release()
        for _, _, entry in self._heap:
            if entry.live and not entry.future.done():
                entry.future.cancel()
        self._heap.clear()
        if loop is not None:
            Alarm._by_loop.pop(loop, None)

    def _release(self) -> None:
        """Close the timer once (at close, or when the loop is collected)."""
        fd, self._fd = self._fd, -1
        if fd >= 0:
            _close_quietly(fd)

    def _arm(self, when: float) -> None:
        seconds = int(when)
        self._spec.it_value.tv_sec = seconds
        self._spec.it_value.tv_nsec = max(1, int((when - seconds) * 1e9))  # 0 would disarm it
        if _LIBC is None or _LIBC.timerfd_settime(self._fd, _TFD_TIMER_ABSTIME, self._spec, None) != 0:
            raise OSError(ctypes.get_errno(), "timerfd_settime failed")
        self._armed = when

    def _fire(self) -> None:
        try:
            os.read(self._fd, 8)
        except BlockingIOError:
            pass  # re-armed for later since it fired: nothing is due yet
        self._armed = float("inf")
        now = time.monotonic()
        heap = self._heap
        while heap and (heap[0][0] <= now or not heap[0][2].live or heap[0][2].future.done()):
            _, _, entry = heapq.heappop(heap)
            if entry.live and not entry.future.done():
                entry.future.set_result(None)
        if heap:
            self._arm(heap[0][0])


class Wakeup:
    """One sleeper's wake-up, which another task can move without waking it.

    A REALTIME session sleeps until its next tick's deadline; when the tick's frame arrives and is
    answered first, the wake-up moves to the next deadline. Waking the sleeper only for it to find
    its tick answered and sleep again cost a loop wake-up per tick (52 us of CPU here).
    """

    __slots__ = ("_alarm", "_entry")

    def __init__(self, alarm: Alarm) -> None:
        self._alarm = alarm
        self._entry: _Entry | None = None

    @property
    def when(self) -> float | None:
        """When the sleeper wakes (time.monotonic()), or None when nobody sleeps."""
        entry = self._entry
        return None if entry is None else entry.when

    async def until(self, when: float) -> None:
        """Sleep until `when`, or until the time a `move` sets meanwhile (one sleeper at a time)."""
        if self._entry is not None:
            raise RuntimeError("this wake-up has a sleeper already")
        alarm = self._alarm
        if when <= time.monotonic():
            return
        if not alarm.precise:
            await asyncio.sleep(when - time.monotonic())  # `move` cannot reach asyncio's timers
            return
        future: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._entry = alarm._push(when, future)
        try:
            await future
        finally:
            entry, self._entry = self._entry, None
            if entry is not None and entry.live and not future.done():
                alarm._drop(entry)  # cancelled: its place in the heap goes too

    def move(self, when: float) -> None:
        """Wake the sleeper at `when` instead (at once when it has passed); nothing when nobody
        sleeps or the time is the same."""
        entry = self._entry
        if entry is None or entry.when == when or entry.future.done():
            return
        alarm = self._alarm
        replacement = alarm._push(when, entry.future)
        alarm._drop(entry)
        self._entry = replacement
