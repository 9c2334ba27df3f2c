"""Fixtures of the hostile-client suite: `serve(*flags)` starts a real `jitdyn serve` process on a
loopback port 0 with its own data folder and secret, stopped after the test. Helpers live in
_hostile.py, importable from the tests as `_hostile`."""

from __future__ import annotations

import os
import secrets
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))

from _hostile import Served


@pytest.fixture()
def env() -> dict[str, str]:
    environ = dict(os.environ)
    environ["JITDYN_SECRET"] = secrets.token_hex(32)
    environ.pop("JITDYN_INDEX_URL", None)
    environ.pop("JITDYN_SECRET_FILE", None)
    return environ


@pytest.fixture()
def serve(tmp_path: Path, env: dict[str, str]) -> Iterator[Callable[..., Served]]:
    """serve(*flags, data=None) -> a running `jitdyn serve`; stopped after the test."""
    started: list[Served] = []

    def start(*args: str, data: Path | None = None, environ: dict[str, str] | None = None) -> Served:
        served = Served(
            data or tmp_path / "data",
            environ or env,
            list(args),
            output=tmp_path / f"server-{len(started)}.out",
        )
        started.append(served)
        return served

    yield start
    for served in started:
        served.stop()
