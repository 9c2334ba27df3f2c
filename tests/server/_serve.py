"""A real `jitdyn serve` in its own process for the server-level tests: started on port 0, its
address read from what it prints, stopped with SIGTERM."""

from __future__ import annotations

import asyncio
import contextlib
import gc
import os
import re
import secrets
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

from jitdyn.client import AsyncClient, FrameData, Rejection, SessionOptions, TickResult
from jitdyn.errors import ResourceExhausted
from jitdyn.server.runtime.priority import set_priority

# Why a pendulum_3 PASSIVE session at 20 Hz is refused: the process's budget, the machine's idle
# CPU, or answers (or the loop) already late; priced, or at the door when no session would fit.
REFUSALS = (
    (
        r"this server process is at \d+ % of a core and its tick budget is \d+ % \(--tick-budget [\d.]+\); "
        r"a session of pendulum_3 \(passive\) at 20 Hz is estimated at \d+ us per tick, [\d.]+ % more\. "
        r"Try again later, on another server, or at a lower rate"
    ),
    (
        r"this machine has [\d.]+ of its \d+ cores free \(other programs, this server's other processes or "
        r"its clients use the rest\); a session of pendulum_3 \(passive\) at 20 Hz is estimated at \d+ us "
        r"per tick, [\d.]+ of a core, and 0\.1 of a core is kept free\. Try again later, on another server, "
        r"or at a lower rate"
    ),
    (
        r"this server process (answered [\d.]+ % of its ticks more than 5 ms past their deadlines in|ran its "
        r"deadlines more than 5 ms late for [\d.]+ % of) the last 2 s \(at \d+ % of a core, tick budget \d+ %\): "
        r"the CPU its sessions get is short, so a session of pendulum_3 \(passive\) at 20 Hz is not "
        r"admitted\. Try again later, on another server, or at a lower rate"
    ),
    # The same three, asked at the door before the model is priced (Admission.full): no session fits.
    (
        r"this server process is at \d+ % of a core and its tick budget is \d+ % \(--tick-budget [\d.]+\): "
        r"no session fits, so a session of pendulum_3 at 20 Hz is not admitted\. Try again later, on another "
        r"server, or at a lower rate"
    ),
    (
        r"this machine has [\d.]+ of its \d+ cores free \(other programs, this server's other processes or "
        r"its clients use the rest\) and 0\.1 of a core is kept free: no session fits, so a session of "
        r"pendulum_3 at 20 Hz is not admitted\. Try again later, on another server, or at a lower rate"
    ),
    (
        r"this server process (answered [\d.]+ % of its ticks more than 5 ms past their deadlines in|ran its "
        r"deadlines more than 5 ms late for [\d.]+ % of) the last 2 s \(at \d+ % of a core, tick budget \d+ %\): "
        r"the CPU its sessions get is short, so a session of pendulum_3 at 20 Hz is not admitted\. Try again "
        r"later, on another server, or at a lower rate"
    ),
)


@contextlib.contextmanager
def heap_frozen() -> Iterator[None]:
    """This test process as a client program is while it measures an answer's lateness: what the
    suite left on its heap frozen (benchmarks/load.py freezes its load generator the same way). A
    full collection of it took 127-270 ms in a pytest process that had run tests/server, and
    stalled the clients' loop: their frames went out late and their answers were read late, which
    counted as the server's lateness."""
    gc.collect()
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


@contextlib.contextmanager
def client_first() -> Iterator[None]:
    """This test process as a client program on another machine would be: not behind the CPU hogs
    of the machine it shares with the server. Its threads run at the server's own priority (nice
    -10, server/runtime/priority.py) while it measures, where that is permitted; else as they
    were. A frame this client sent late, or an answer it read late, is not the server's."""
    before = os.getpriority(os.PRIO_PROCESS, 0)
    set_priority(-10)
    try:
        yield
    finally:
        set_priority(before)


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class Serve:
    """`jitdyn serve ARGS` on a free loopback port, started under `prefix` (a command that runs
    another, such as setpriv) if given."""

    def __init__(self, data: Path, *args: str, prefix: tuple[str, ...] = ()) -> None:
        env = dict(os.environ, JITDYN_SECRET=secrets.token_hex(32))
        env.pop("JITDYN_INDEX_URL", None)
        self.process = subprocess.Popen(
            [
                *prefix,
                sys.executable,
                "-m",
                "jitdyn.cli",
                "serve",
                "--address",
                "127.0.0.1:0",
                "--data",
                str(data),
                "--workers",
                "1",
                *args,
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env=env,
        )
        assert self.process.stdout is not None
        self.lines: list[str] = []
        for line in self.process.stdout:
            self.lines.append(line)
            match = re.search(r"listening on (127\.0\.0\.1:\d+)", line)
            if match:
                self.address = match.group(1)
                # Read the rest as it comes: a full pipe would block the server's next log line,
                # and with it the event loop that wrote it.
                self._reader = threading.Thread(target=self._read, daemon=True)
                self._reader.start()
                return
        raise RuntimeError("the server did not start:\n" + "".join(self.lines))

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            self.lines.append(line)

    def stop(self) -> None:
        self.process.send_signal(signal.SIGTERM)
        self.process.wait(timeout=120)
        self._reader.join(timeout=10)
        assert self.process.stdout is not None
        self.process.stdout.close()


async def realtime_session(address: str, *, dt: float, ticks: int) -> tuple[str, list[float], int]:
    """A pendulum_3 PASSIVE REALTIME session sending every frame on time: (the refusal's message, [], 0), or
    ('ran', the lateness of each tick's first answer past its deadline (inf: none came), MEASURED
    count)."""
    async with AsyncClient(address, timeout=30) as client:
        try:
            session = await client.open_session(
                SessionOptions(model_name="pendulum_3", dt=dt, clock="REALTIME", scenario="PASSIVE")
            )
        except ResourceExhausted as error:
            return str(error), [], 0
        first: dict[int, TickResult] = {}
        async with session:

            async def produce() -> None:
                for k in range(ticks):
                    await asyncio.sleep(max(0.0, k * dt - session.now()))
                    await session.send(
                        FrameData(seq=k, t=k * dt, qpos=[0.3, -0.2, 0.1], qvel=[0.0, 0.0, 0.0])
                    )

            async def consume() -> None:
                async for answer in session.results(timeout=5):
                    if isinstance(answer, TickResult):
                        first.setdefault(answer.seq, answer)
                    if isinstance(answer, (TickResult, Rejection)) and answer.seq >= ticks - 1:
                        return  # the last tick answered, or its frame rejected (a skipped tick)

            await asyncio.gather(produce(), consume())
        grace = session.opened.grace
        lateness = [
            first[k].received_at - session.clock_start - (k * dt + grace) if k in first else float("inf")
            for k in range(ticks)
        ]
        return "ran", lateness, sum(r.source == "MEASURED" for r in first.values())
