"""Shared fixtures: a real jitdyn server on a loopback port 0, and a client connected to it.

Imports of the server happen inside the fixtures, so that tests of one package do not need the
others to import.
"""

from __future__ import annotations

import secrets
import signal
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import grpc
import pytest

from jitdyn.mujoco_log import route_mujoco_messages

# MuJoCo's warnings go to logging, as in the server and the CLI, not to MUJOCO_LOG.TXT in the
# folder pytest runs from (tests/cli/test_first_contact.py checks that none is written).
route_mujoco_messages()


def pytest_configure(config: pytest.Config) -> None:
    """SIGTERM ends a run as Ctrl-C does, so the fixtures' finalizers stop the servers, HAProxy
    and moto they started: a terminated run left them serving, and the next tests' admission
    counted their CPU as the machine's load."""
    signal.signal(signal.SIGTERM, signal.default_int_handler)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The `timing` tests (wall-clock promises of a real server under load) run first: on the
    machine as CI finds it and in a test process whose heap the suite has not yet grown
    (docs/decisions/0010-timing-tests-first.md)."""
    items.sort(key=lambda item: item.get_closest_marker("timing") is None)  # stable: order kept


@pytest.fixture(scope="session")
def make_config() -> Callable[..., Any]:
    """Builds a server config for tests: port 0, its own data folder, a secret in its environment."""
    from jitdyn.server.transport.app import ServerConfig

    def build(data_root: Path, **overrides: object) -> ServerConfig:
        values: dict[str, object] = {
            "address": "127.0.0.1:0",
            "data_root": data_root,
            "workers": 2,
            "environ": {"JITDYN_SECRET": secrets.token_hex(32)},
            "shutdown_grace": 1.0,
        }
        values.update(overrides)
        return ServerConfig(**values)  # type: ignore[arg-type]

    return build


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory, make_config: Callable[..., Any]) -> Iterator[Any]:
    from jitdyn.server.transport.background import BackgroundServer

    with BackgroundServer(make_config(tmp_path_factory.mktemp("data"))) as running:
        yield running


@pytest.fixture()
def client(server: Any) -> Iterator[Any]:
    from jitdyn.client import Client

    with Client(server.address, timeout=60) as connected:
        yield connected


TENANT_METADATA = "x-test-tenant"


class _TenantFromMetadata(grpc.aio.ServerInterceptor):  # type: ignore[misc]
    """Sets jitdyn.server.transport.auth.current_tenant from the `x-test-tenant` metadata, as server/transport/app.py's key
    interceptor does from an API key, so servicer tests can act as any tenant without keys."""

    async def intercept_service(self, continuation: Any, details: grpc.HandlerCallDetails) -> Any:
        from jitdyn.server.transport.auth import current_tenant

        handler = await continuation(details)
        tenant = dict(details.invocation_metadata or ()).get(TENANT_METADATA, "")
        if handler is None or handler.unary_unary is None:
            return handler
        inner = handler.unary_unary

        async def with_tenant(request: Any, context: grpc.aio.ServicerContext) -> Any:
            current_tenant.set(tenant)
            return await inner(request, context)

        return grpc.unary_unary_rpc_method_handler(
            with_tenant,
            request_deserializer=handler.request_deserializer,
            response_serializer=handler.response_serializer,
        )


@pytest.fixture(scope="session")
def tenant_interceptor() -> grpc.aio.ServerInterceptor:
    """An interceptor for single-servicer test servers: the tenant comes from `as_tenant`."""
    return _TenantFromMetadata()


@pytest.fixture()
def as_tenant() -> Callable[[str], list[tuple[str, str]]]:
    """The call metadata that makes a test server with `tenant_interceptor` run an RPC for `tenant`."""
    return lambda tenant: [(TENANT_METADATA, tenant)]
