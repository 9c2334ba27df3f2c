"""A real `jitdyn serve` in its own process for the server-level tests: started on port 0, its
address read from what it prints, stopped with SIGTERM."""

from __future__ import annotations

import asyncio
import os
import re
import secrets
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

from jitdyn.client import AsyncClient, FrameData, Rejection, SessionOptions, TickResult
from jitdyn.errors import ResourceExhausted


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class Serve:
    def __init__(self, data: Path, *args: str) -> None:
        env = dict(os.environ, JITDYN_SECRET=secrets.token_hex(32))
        env.pop("JITDYN_INDEX_URL", None)
        self.process = subprocess.Popen(
            [
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
