"""The event loop watched: how late it runs what falls due (its lag), and what it was doing when it
stalled.

A beat is due on the loop every BEAT; how late it runs is the loop's lag, and the lag of every
deadline timer of the REALTIME sessions in that moment (an answer sent at its deadline leaves that
late). Admission takes the lag as evidence (server/runtime/admission.py), and so does the
`jitdyn_loop_lag_seconds` metric. A watchdog thread looks every LOOK: when the loop has not beaten
for `stall` seconds, it samples the loop thread's stack until the loop beats again, and `report`
gets the stall, its stacks by how often they were seen, and what the other threads were doing when
it began (a loop waiting for the GIL shows in the call that gave it away, and the thread that has
it shows among the others).

    watch = LoopWatch(loop, on_lag=admission.observe_loop_lag, stall=0.1, report=log_stall)
    watch.start()               # on the loop's thread
    watch.stop()

What it found, and why it is built so: docs/decisions/0009-the-loop-watched.md.
"""

from __future__ import annotations

import asyncio
import sys
import threading
import time
import traceback
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

__all__ = ["BEAT", "LOOK", "LoopWatch", "Stall"]

BEAT: Final = 5e-3  # s between two beats of the loop
LOOK: Final = 10e-3  # s between two looks of the watchdog (and two samples of a stall)
_OURS: Final = str(Path(__file__).resolve().parents[2])  # frames of jitdyn's own code
_SHOWN: Final = 14  # innermost frames of a stack shown


@dataclass
class Stall:
    """A stall: `seconds` without a beat; the loop thread's stacks sampled meanwhile, with how
    often; every other thread's stack when it was first seen."""

    seconds: float
    loop_stacks: Counter[str] = field(default_factory=Counter)
    others: dict[str, str] = field(default_factory=dict)

    def describe(self) -> str:
        samples = sum(self.loop_stacks.values())
        lines = [f"the event loop stalled {1e3 * self.seconds:.0f} ms; what it ran ({samples} samples):"]
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
        self._stopped = threading.Event()
        self._handle: asyncio.TimerHandle | None = None
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Call on the loop's thread."""
        self._loop_thread = threading.get_ident()
        self._due = self._loop.time() + BEAT
        self._handle = self._loop.call_at(self._due, self._on_beat)
        if self._stall is not None and self._report is not None:
            self._thread = threading.Thread(target=self._watch, name="jitdyn-loop-watch", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        self._stopped.set()
        if self._handle is not None:
            self._handle.cancel()

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
        while not self._stopped.wait(LOOK):
            beat = self._beat
            silent = time.monotonic() - beat
            if stall is not None and beat != began:  # the loop beat again: the stall is over
                stall.seconds = beat - began
                self._report(stall)
                stall = None
            if silent <= self._stall:
                continue
            frames = sys._current_frames()
            if stall is None:
                stall, began = Stall(seconds=silent), beat
                names = {t.ident: t.name for t in threading.enumerate()}
                stall.others = {
                    names.get(ident, str(ident)): _stack(frame, ours_only=True)
                    for ident, frame in frames.items()
                    if ident not in (self._loop_thread, threading.get_ident())
                }
            frame = frames.get(self._loop_thread)
            if frame is not None:
                stall.loop_stacks[_stack(frame)] += 1
