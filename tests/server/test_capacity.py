"""A server at capacity: twice as many REALTIME sessions as its tick budget holds are opened; the
admitted ones stay on time, the surplus is refused with RESOURCE_EXHAUSTED saying why, and the
Prometheus endpoint shows it all, per process. Real `jitdyn serve`, real gRPC, a small budget so
that capacity is a handful of sessions."""

from __future__ import annotations

import asyncio
import os
import re
import secrets
import signal
import socket
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest

from jitdyn.client import AsyncClient, FrameData, Rejection, SessionOptions, TickResult
from jitdyn.errors import ResourceExhausted

# Run on its own, on a quiet machine (pytest -m timing): a loop stall just over a tick, or an open
# that went unanswered for 30 s, fails it now and then on a shared machine.
pytestmark = pytest.mark.timing

DT = 0.05
TICKS = 60  # 3 s


def _free_port() -> int:
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
                return
        raise RuntimeError("the server did not start:\n" + "".join(self.lines))

    def stop(self) -> None:
        self.process.send_signal(signal.SIGTERM)
        self.process.communicate(timeout=120)


async def _session(address: str, index: int) -> tuple[str, list[float], int]:
    """('refused', message) or ('ran', lateness of each tick's first answer, MEASURED count)."""
    async with AsyncClient(address, timeout=30) as client:
        try:
            session = await client.open_session(
                SessionOptions(model_name="pendulum_3", dt=DT, clock="REALTIME", scenario="PASSIVE")
            )
        except ResourceExhausted as error:
            return str(error), [], 0
        first: dict[int, TickResult] = {}
        async with session:

            async def produce() -> None:
                for k in range(TICKS):
                    await asyncio.sleep(max(0.0, k * DT - session.now()))
                    await session.send(
                        FrameData(seq=k, t=k * DT, qpos=[0.3, -0.2, 0.1], qvel=[0.0, 0.0, 0.0])
                    )

            async def consume() -> None:
                async for answer in session.results(timeout=5):
                    if isinstance(answer, TickResult):
                        first.setdefault(answer.seq, answer)
                    if isinstance(answer, (TickResult, Rejection)) and answer.seq >= TICKS - 1:
                        return  # the last tick answered, or its frame rejected (a skipped tick)

            await asyncio.gather(produce(), consume())
        grace = session.opened.grace
        lateness = [
            first[k].received_at - session.clock_start - (k * DT + grace) if k in first else float("inf")
            for k in range(TICKS)
        ]
        return "ran", lateness, sum(r.source == "MEASURED" for r in first.values())


@pytest.mark.parametrize("processes", [1, 2])
def test_twice_the_capacity_admitted_on_time_surplus_refused_metrics_show_it(
    tmp_path: Path, processes: int
) -> None:
    metrics_port = _free_port()
    server = Serve(
        tmp_path / "data",
        "--processes",
        str(processes),
        "--tick-budget",
        "0.12",
        "--metrics-address",
        f"127.0.0.1:{metrics_port}",
    )
    try:

        async def everyone() -> list[tuple[str, list[float], int]]:
            # Opened one after another, so each admission sees the ones before it.
            results = []
            tasks = []
            for i in range(8 * processes):
                tasks.append(asyncio.create_task(_session(server.address, i)))
                await asyncio.sleep(0.15)
            results = await asyncio.gather(*tasks)
            return results

        outcomes = asyncio.run(everyone())
        scraped = (
            urllib.request.urlopen(f"http://127.0.0.1:{metrics_port}/metrics", timeout=10).read().decode()
        )
    finally:
        server.stop()
    ran = [o for o in outcomes if o[0] == "ran"]
    refused = [o[0] for o in outcomes if o[0] != "ran"]
    assert ran and refused, outcomes
    for message in refused:
        # Refused for the process's budget, or (on a machine that other work keeps busy) for the
        # machine's idle CPU; either way the message says why.
        assert re.fullmatch(
            r"this server process is at \d+ % of a core and its tick budget is 12 % \(--tick-budget 0\.12\); "
            r"a session of pendulum_3 \(passive\) at 20 Hz is estimated at \d+ us per tick, [\d.]+ % more\. "
            r"Try again later, on another server, or at a lower rate",
            message,
        ) or re.fullmatch(
            r"this machine has [\d.]+ of its \d+ cores free \(other programs, this server's other processes or "
            r"its clients use the rest\); a session of pendulum_3 \(passive\) at 20 Hz is estimated at \d+ us "
            r"per tick, [\d.]+ of a core, and 0\.1 of a core is kept free\. Try again later, on another server, "
            r"or at a lower rate",
            message,
        ), message
    # Every tick of every admitted session answered (inf: a tick the server skipped, its frame
    # answered TOO_OLD), and none late by a tick but for at most one in the whole run: a stall of
    # the loop just over a tick still happens now and then; before the heap was frozen
    # (docs/decisions/0006) every run had one or several, skipped ones among them.
    late = [
        (i, k, round(x, 3))
        for i, (_, lateness, _) in enumerate(ran)
        for k, x in enumerate(lateness)
        if x >= DT
    ]
    assert all(x != float("inf") for _, _, x in late), late
    assert len(late) <= 1, late
    for _, _, measured in ran:
        assert measured >= 0.95 * TICKS
    # Every admitted session's ticks and every refusal, on the endpoint, by process.
    measured_total = sum(
        float(v)
        for v in re.findall(
            r'^jitdyn_ticks_total\{.*model="pendulum_3".*source="MEASURED".*\} (\S+)$', scraped, re.MULTILINE
        )
    )
    assert measured_total >= sum(m for _, _, m in ran)
    refusals = sum(
        float(v) for v in re.findall(r"^jitdyn_admission_refusals_total\{.*\} (\S+)$", scraped, re.MULTILINE)
    )
    assert refusals == len(refused)
    processes_seen = set(re.findall(r'^jitdyn_ticks_total\{.*process="(\d+)".*\}', scraped, re.MULTILINE))
    assert processes_seen <= {str(i) for i in range(processes)} and processes_seen
    assert re.search(r"^jitdyn_tick_lateness_seconds_bucket\{.*le=\"0.005\".*\} \S+$", scraped, re.MULTILINE)
    assert re.search(r"^jitdyn_durable_lag_ticks_count\{.*\} \S+$", scraped, re.MULTILINE)
    assert re.search(r'^jitdyn_gc_pause_seconds_count\{.*generation="0".*\} \S+$', scraped, re.MULTILINE)
