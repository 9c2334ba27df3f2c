"""Shared fixtures: a real jitdyn server on a loopback port 0, and a client connected to it.

Imports of the server happen inside the fixtures, so that tests of one package do not need the
others to import.
"""

from __future__ import annotations

import secrets
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest


@pytest.fixture(scope="session")
def make_config() -> Callable[..., Any]:
    """Builds a server config for tests: port 0, its own data folder, a secret in its environment."""
    from server.app import ServerConfig

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
    from server.background import BackgroundServer

    with BackgroundServer(make_config(tmp_path_factory.mktemp("data"))) as running:
        yield running


@pytest.fixture()
def client(server: Any) -> Iterator[Any]:
    from client import Client

    with Client(server.address, timeout=60) as connected:
        yield connected
