"""The event loop watched: how late it runs what falls due (its lag), and what it was doing when it
stalled.

A beat is due on the loop every BEAT; how late it runs is the loop's lag, and the lag of every
deadline timer of the REALTIME sessions in that moment (an answer sent at its deadline leaves that
late). Admission takes the lag as evidence (server/runtime/admission.py), and so does the
`jitdyn_loop_lag_seconds` metric. A watchdog thread looks every READ while the loop beats, and as
the loop could have been silent for `stall` seconds: when it has, it samples the loop thread's
stack every LOOK until the loop beats again, and `report`
gets the stall, its stacks by how often they were seen, and what the other threads were doing when
it began (a loop waiting for the GIL shows in the call that gave it away, and the thread that has
it shows among the others). It also gets the kernel's account of the stall (Linux's schedstat):
how much of it the loop's thread ran, how much it was runnable but waiting for a CPU, the rest
(waiting for the GIL, a lock or I/O), what the process's other threads ran, and how idle the
machine's CPUs were meanwhile.

    watch = LoopWatch(loop, on_lag=admission.observe_loop_lag, stall=0.1, report=log_stall)
    watch.start()               # on the loop's thread
    watch.stop()

What it found, and why it is built so: docs/decisions/0009-the-loop-watched.md.
"""

from __future__ import annotations

import asyncio
import math
import os
import sys
import threading
import time
import traceback
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

__all__ = ["BEAT", "LOOK", "READ", "LoopWatch", "Stall"]

BEAT: Final = 5e-3  # s between two beats of the loop
LOOK: Final = 10e-3  # s between two samples of a stall's stacks
# s between two readings of the kernel's counts while the loop beats (a stall's account starts at
# the last one before it); the watchdog sleeps in between, and until the loop could have stalled.
READ: Final = 20e-3
_OURS: Final = str(Path(__file__).resolve().parents[2])  # frames of jitdyn's own code
_SHOWN: Final = 14  # innermost frames of a stack shown


@dataclass(frozen=True)
class Account:
    """The kernel's account of a stretch of a stall (s): the loop thread on a CPU, the loop thread
    runnable and waiting for one, the process's other threads on a CPU, and the machine's CPUs
    idle (summed over CPUs) out of `wall`."""

    wall: float
    ran: float
    waited_for_cpu: float
    others_ran: float
    idle: float

    def describe(self) -> str:
        neither = max(0.0, self.wall - self.ran - self.waited_for_cpu)
        cpus = os.cpu_count() or 1
        return (
            f"  of its last {1e3 * self.wall:.0f} ms the loop's thread ran {1e3 * self.ran:.0f}, waited "
            f"{1e3 * self.waited_for_cpu:.0f} for a CPU and {1e3 * neither:.0f} for the GIL, a lock or I/O; "
            f"the process's other threads ran {1e3 * self.others_ran:.0f}; the machine's {cpus} CPUs were "
            f"{100 * self.idle / (self.wall * cpus) if self.wall > 0 else 0:.0f} % idle"
        )


@dataclass
class Stall:
    """A stall: `seconds` without a beat; the loop thread's stacks sampled meanwhile, with how
    often; every other thread's stack when it was first seen; the kernel's account of it, from
    the last look before it was seen to its end (None where Linux's schedstat is not there)."""

    seconds: float
    loop_stacks: Counter[str] = field(default_factory=Counter)
    others: dict[str, str] = field(default_factory=dict)
    account: Account | None = None

    def describe(self) -> str:
        samples = sum(self.loop_stacks.values())
        lines = [f"the event loop stalled {1e3 * self.seconds:.0f} ms; what it ran ({samples} samples):"]
        if self.account is not None:
            lines.append(self.account.describe())
        for stack, count in self.loop_stacks.most_common(3):
            lines.append(f"  {count} of {samples}:\n{stack}")
        busy = {name: stack for name, stack in self.others.items() if stack}
        for name, stack in busy.items():
            lines.append(f"  thread {name}, when it began:\n{stack}")
        return "\n".join(lines)


def _stack(frame: object, *, ours_only: bool = False) -> str:
    """The frames of jitdyn's own code and the innermost frame (what it called last), one per line;
    with no frame of jitdyn's, the innermost three, or "" when `ours_only`."""
    entries = traceback.extract_stack(frame)  # type: ignore[arg-type]
    kept = [e for e in entries if e.filename.startswith(_OURS)]
    if not kept and ours_only:
        return ""
    kept = kept or entries[-3:]
    if entries and entries[-1] is not kept[-1]:
        kept.append(entries[-1])
    return "".join(f"    {Path(e.filename).name}:{e.lineno} {e.name}\n" for e in kept[-_SHOWN:])


@dataclass(frozen=True)
class _Reading:
    """What the kernel had counted at one moment (s): the loop thread's time on a CPU and waiting
    for one, every thread's of the process on a CPU, the machine's idle time summed over CPUs."""

    at: float
    ran: float
    waited: float
    all_ran: float
    idle: float

    def until(self, later: _Reading) -> Account:
        ran = later.ran - self.ran
        return Account(
            wall=later.at - self.at,
            ran=ran,
            waited_for_cpu=later.waited - self.waited,
            others_ran=max(0.0, later.all_ran - self.all_ran - ran),
            idle=later.idle - self.idle,
        )


class _Kernel:
    """Reads the kernel's counts for `_Reading`s through files kept open (a look costs ~10 us);
    `read` gives None where /proc has no schedstat (not Linux, or a kernel without
    CONFIG_SCHEDSTATS)."""

    def __init__(self, loop_tid: int) -> None:
        self._thread: int | None = None
        self._machine: int | None = None
        try:
            self._tick = os.sysconf("SC_CLK_TCK")
            self._thread = os.open(f"/proc/self/task/{loop_tid}/schedstat", os.O_RDONLY)
            self._machine = os.open("/proc/stat", os.O_RDONLY)
        except (AttributeError, ValueError, OSError):  # no sysconf (Windows), no /proc
            self.close()

    def read(self) -> _Reading | None:
        if self._thread is None or self._machine is None:
            return None
        try:
            at = time.monotonic()
            ran, waited, _ = os.pread(self._thread, 128, 0).split()
            all_ran = time.process_time()
            fields = os.pread(self._machine, 256, 0).split(b"\n", 1)[0].split()
            idle = (int(fields[4]) + int(fields[5])) / self._tick  # idle and iowait, summed over CPUs
            return _Reading(at=at, ran=int(ran) / 1e9, waited=int(waited) / 1e9, all_ran=all_ran, idle=idle)
        except (OSError, ValueError, IndexError):
            return None

    def close(self) -> None:
        for fd in (self._thread, self._machine):
            if fd is not None:
                os.close(fd)
        self._thread = self._machine = None


class LoopWatch:
    """Beats on `loop` every BEAT, handing each beat's lag (s) to `on_lag`; with `stall` (s), a
    thread reports through `report` every stall longer than it."""

    def __init__(
        self,
        loop: asyncio.AbstractEventLoop,
        *,
        on_lag: Callable[[float], None],
        stall: float | None = None,
        report: Callable[[Stall], None] | None = None,
    ) -> None:
        self._loop = loop
        self._on_lag = on_lag
        self._stall = stall
        self._report = report
        self._due = 0.0
        self._beat = time.monotonic()  # when the loop last beat, on the watchdog's clock
        self._loop_thread = 0
        self._loop_tid = 0  # the loop thread's id for the kernel
        self._stopped = threading.Event()
        self._handle: asyncio.TimerHandle | None = None
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Call on the loop's thread."""
        self._loop_thread = threading.get_ident()
        self._loop_tid = threading.get_native_id()
        self._due = self._loop.time() + BEAT
        self._handle = self._loop.call_at(self._due, self._on_beat)
        if self._stall is not None and self._report is not None:
            self._thread = threading.Thread(target=self._watch, name="jitdyn-loop-watch", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        self._stopped.set()
        if self._handle is not None:
            self._handle.cancel()

    def silent(self) -> float:
        """Seconds since the loop last beat; safe from any thread (the kubelet's liveness probe asks
        it from the probes' own threads, server/transport/probes.py)."""
        return max(0.0, time.monotonic() - self._beat)

    def _on_beat(self) -> None:
        now = self._loop.time()
        self._beat = time.monotonic()
        self._on_lag(max(0.0, now - self._due))
        # The next beat from now, not from when this one was due: a stall is one late beat.
        self._due = now + BEAT
        self._handle = self._loop.call_at(self._due, self._on_beat)

    def _watch(self) -> None:
        assert self._stall is not None and self._report is not None
        stall: Stall | None = None
        began = 0.0
        kernel = _Kernel(self._loop_tid)
        readings: deque[_Reading] = deque(maxlen=int(self._stall / READ) + 4)  # the last readings
        before: _Reading | None = None  # the kernel's counts at the last reading before the stall began
        read_at = -math.inf
        wait = LOOK
        # A look every READ while the loop beats, or when it could have been silent for `stall`
        # if that is sooner; every LOOK while a stall lasts. A look every LOOK throughout cost
        # 9-11 ms of CPU a second (docs/decisions/0213-the-tick-around-the-engine.md).
        while not self._stopped.wait(wait):
            beat = self._beat
            now = time.monotonic()
            silent = now - beat
            if stall is not None and beat != began:  # the loop beat again: the stall is over
                stall.seconds = beat - began
                after = kernel.read()
                if before is not None and after is not None:
                    stall.account = before.until(after)
                self._report(stall)
                stall = None
            if silent <= self._stall:
                if now >= read_at:
                    read_at = now + READ
                    if (reading := kernel.read()) is not None:
                        readings.append(reading)
                wait = max(1e-3, min(read_at, beat + self._stall + LOOK / 2) - now)
                continue
            wait = LOOK
            frames = sys._current_frames()
            if stall is None:
                stall, began = Stall(seconds=silent), beat
                before = next(
                    (r for r in reversed(readings) if r.at <= began), readings[0] if readings else None
                )
                names = {t.ident: t.name for t in threading.enumerate()}
                stall.others = {
                    names.get(ident, str(ident)): _stack(frame, ours_only=True)
                    for ident, frame in frames.items()
                    if ident not in (self._loop_thread, threading.get_ident())
                }
            frame = frames.get(self._loop_thread)
            if frame is not None:
                stall.loop_stacks[_stack(frame)] += 1
        kernel.close()
