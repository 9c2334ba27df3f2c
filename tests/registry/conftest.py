"""Fixtures of the registry tests: an index on SQLite and on PostgreSQL (each test in its own schema,
dropped afterwards), a registry on it, and a live grpc.aio server with only the ModelRegistryServicer
on a loopback port 0 with a synchronous stub to it."""

from __future__ import annotations

import asyncio
import threading
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import grpc
import pytest
import sqlalchemy as sa

from jitdyn.registry import ModelRegistry, RegistryLimits
from jitdyn.storage.db import open_index

POSTGRES_URL = "postgresql+psycopg://root@127.0.0.1:5432/test"
# The test server's limits: small enough to go over cheaply, big enough for myoHand.
SERVER_LIMITS = RegistryLimits(max_mjcf_bytes=1 << 20, compile_timeout=60.0)
MESSAGE_BYTES = 64 << 20


@pytest.fixture()
def data_root(tmp_path: Path) -> Path:
    root = tmp_path / "data"
    root.mkdir()
    return root


@pytest.fixture(params=["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def engine(request: pytest.FixtureRequest, data_root: Path) -> Iterator[sa.Engine]:
    """A migrated index: a SQLite file in the data root, or a fresh PostgreSQL schema."""
    if request.param == "sqlite":
        engine = open_index(f"sqlite:///{data_root / 'index.sqlite'}")
        yield engine
        engine.dispose()
        return
    schema = f"jitdyn_registry_test_{uuid.uuid4().hex[:12]}"
    engine = open_index(POSTGRES_URL, schema=schema)
    try:
        yield engine
    finally:
        engine.dispose()
        admin = sa.create_engine(POSTGRES_URL)
        with admin.begin() as connection:
            connection.execute(sa.text(f'DROP SCHEMA IF EXISTS "{schema}" CASCADE'))
        admin.dispose()


@pytest.fixture()
def registry(engine: sa.Engine, data_root: Path) -> Iterator[ModelRegistry]:
    with ModelRegistry(engine=engine, data_root=data_root) as opened:
        yield opened


@pytest.fixture(scope="module")
def served_registry(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ModelRegistry]:
    """The registry behind the module's server: SQLite, built-ins registered, SERVER_LIMITS."""
    root = tmp_path_factory.mktemp("served")
    engine = open_index(f"sqlite:///{root / 'index.sqlite'}")
    with ModelRegistry(engine=engine, data_root=root, limits=SERVER_LIMITS) as opened:
        opened.register_builtins()
        yield opened
    engine.dispose()


@pytest.fixture(scope="module")
def registry_stub(
    served_registry: ModelRegistry, tenant_interceptor: grpc.aio.ServerInterceptor
) -> Iterator[Any]:
    """A synchronous ModelRegistryService stub to a grpc.aio server on 127.0.0.1:0, in its own
    event-loop thread, serving `served_registry`."""
    from jitdyn.server.transport.registry_service import ModelRegistryServicer
    from jitdyn.v1 import model_registry_pb2_grpc

    options = [
        ("grpc.max_receive_message_length", MESSAGE_BYTES),
        ("grpc.max_send_message_length", MESSAGE_BYTES),
    ]
    loop = asyncio.new_event_loop()
    started = threading.Event()
    state: dict[str, Any] = {}

    async def start() -> None:
        server = grpc.aio.server(interceptors=[tenant_interceptor], options=options)
        model_registry_pb2_grpc.add_ModelRegistryServiceServicer_to_server(
            ModelRegistryServicer(served_registry), server
        )
        state["port"] = server.add_insecure_port("127.0.0.1:0")
        await server.start()
        state["server"] = server

    def run() -> None:
        asyncio.set_event_loop(loop)
        loop.run_until_complete(start())
        started.set()
        loop.run_forever()

    thread = threading.Thread(target=run, name="registry-server", daemon=True)
    thread.start()
    if not started.wait(30):
        raise RuntimeError("the test gRPC server did not start within 30 s")
    channel = grpc.insecure_channel(f"127.0.0.1:{state['port']}", options=options)
    try:
        yield model_registry_pb2_grpc.ModelRegistryServiceStub(channel)
    finally:
        channel.close()
        asyncio.run_coroutine_threadsafe(state["server"].stop(None), loop).result(30)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(30)
        loop.close()
