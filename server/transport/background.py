"""A jitdyn server on a background thread, for the demo, the experiments and tests::

    with BackgroundServer(ServerConfig(address="127.0.0.1:0", data_root=tmp)) as server:
        client = Client(server.address)

The server runs its own asyncio loop; `close()` shuts it down gracefully (open sessions are stored)
and is safe to call twice.
"""

from __future__ import annotations

import asyncio
import dataclasses
import threading
from concurrent.futures import Future

import grpc

from jitdyn.lifecycle import Closeable
from jitdyn.server.runtime.services import Services
from jitdyn.server.transport.app import ServerConfig, create_server, shutdown

__all__ = ["BackgroundServer"]


class BackgroundServer(Closeable):
    """Starts at construction; `address` is where it listens (port 0 picks a free one)."""

    def __init__(self, config: ServerConfig, *, start_timeout: float = 120.0) -> None:
        self._config = config
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="jitdyn-server", daemon=True)
        self._thread.start()
        self._server: grpc.aio.Server | None = None
        self.services: Services | None = None
        future: Future[tuple[grpc.aio.Server, int, Services]] = asyncio.run_coroutine_threadsafe(
            self._start(), self._loop
        )
        try:
            self._server, port, self.services = future.result(timeout=start_timeout)
        except BaseException:
            self._stop_loop()
            raise
        host = config.address.rsplit(":", 1)[0]
        self.port = port
        self.address = f"{host}:{port}"
        self._closed = False

    async def _start(self) -> tuple[grpc.aio.Server, int, Services]:
        server, port, services = await create_server(dataclasses.replace(self._config, shares_process=True))
        await server.start()
        return server, port, services

    def _stop_loop(self) -> None:
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=30)
        if not self._thread.is_alive():
            self._loop.close()

    def close(self, *, grace: float | None = None) -> None:
        """Stop the server; open sessions get `grace` seconds, then are stored as they are."""
        if getattr(self, "_closed", True):
            return
        self._closed = True
        if self._server is not None and self.services is not None:
            stop = shutdown(
                self._server, self.services, grace=self._config.shutdown_grace if grace is None else grace
            )
            asyncio.run_coroutine_threadsafe(stop, self._loop).result(timeout=120)
        self._stop_loop()
