"""The SDK's idempotent unary calls ride out a server restart: gRPC's service-config retry policy
retries them on UNAVAILABLE (client/_transport.py, RETRY_POLICY), without any loop of ours."""

from __future__ import annotations

import asyncio
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from jitdyn.client import AsyncClient, Client
from jitdyn.errors import Unavailable
from jitdyn.server.transport.background import BackgroundServer


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _restart_later(config: Any, delay: float, started: list[BackgroundServer]) -> threading.Thread:
    def restart() -> None:
        time.sleep(delay)
        started.append(BackgroundServer(config))

    thread = threading.Thread(target=restart, name="restart-server")
    thread.start()
    return thread


@pytest.mark.timeout(120)
def test_idempotent_calls_are_retried_across_a_restart(
    tmp_path: Path, make_config: Callable[..., Any]
) -> None:
    config = make_config(tmp_path / "data", address=f"127.0.0.1:{_free_port()}")
    restarted: list[BackgroundServer] = []
    with BackgroundServer(config) as first, Client(first.address, timeout=30) as client:
        assert client.get_model(name="pendulum_1").name == "pendulum_1"
        first.close(grace=0)
        # Down now: without the policy the next call fails at once with UNAVAILABLE.
        thread = _restart_later(config, 1.0, restarted)
        try:
            began = time.monotonic()
            assert not restarted
            model = client.get_model(name="pendulum_2")
            waited = time.monotonic() - began
            assert model.name == "pendulum_2"
            assert waited > 0.5, f"the call did not wait for the restart ({waited:.2f} s)"
            assert [m.name for m in client.list_models(name="pendulum_3")] == ["pendulum_3"]
            assert list(client.list_sessions()) == []
        finally:
            thread.join()
            for server in restarted:
                server.close(grace=0)


@pytest.mark.timeout(120)
def test_async_client_retries_too(tmp_path: Path, make_config: Callable[..., Any]) -> None:
    config = make_config(tmp_path / "data", address=f"127.0.0.1:{_free_port()}")
    restarted: list[BackgroundServer] = []
    first = BackgroundServer(config)

    async def run() -> str:
        async with AsyncClient(first.address, timeout=30) as client:
            await client.get_model(name="pendulum_1")
            first.close(grace=0)
            thread = _restart_later(config, 1.0, restarted)
            try:
                return (await client.get_model(name="pendulum_2")).name
            finally:
                await asyncio.to_thread(thread.join)

    try:
        assert asyncio.run(run()) == "pendulum_2"
    finally:
        first.close(grace=0)
        for server in restarted:
            server.close(grace=0)


def test_a_server_that_stays_away_still_fails_as_unavailable(tmp_path: Path) -> None:
    with Client(f"127.0.0.1:{_free_port()}", timeout=30) as client:
        began = time.monotonic()
        with pytest.raises(Unavailable):
            client.get_model(name="pendulum_1")
        # Five attempts with backoffs of about 0.25 + 0.5 + 1 + 2 s (randomised), then the status.
        assert time.monotonic() - began < 15
