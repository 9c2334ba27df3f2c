"""Fixtures of the storage tests: a data root, an index on SQLite and on PostgreSQL (each test in
its own schema, dropped afterwards), session headers and seeded records, and a live gRPC server
with the SessionServicer on a loopback port 0."""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import threading
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import grpc
import numpy as np
import pytest
import sqlalchemy as sa

from jitdyn.storage.db import open_index
from jitdyn.storage.index import SessionIndex
from jitdyn.storage.records import SessionHeader, TickRecord

POSTGRES_URL = "postgresql+psycopg://root@127.0.0.1:5432/test"


@pytest.fixture()
def data_root(tmp_path: Path) -> Path:
    root = tmp_path / "data"
    root.mkdir()
    return root


@contextlib.contextmanager
def postgres_index(url: str = POSTGRES_URL) -> Iterator[sa.Engine]:
    """A migrated index in a fresh PostgreSQL schema (reached at `url`), dropped afterwards."""
    schema = f"jitdyn_test_{uuid.uuid4().hex[:12]}"
    engine = open_index(url, schema=schema)
    try:
        yield engine
    finally:
        engine.dispose()
        admin = sa.create_engine(POSTGRES_URL)
        with admin.begin() as conn:
            conn.execute(sa.text(f'DROP SCHEMA IF EXISTS "{schema}" CASCADE'))
        admin.dispose()


@pytest.fixture(params=["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def engine(request: pytest.FixtureRequest, data_root: Path) -> Iterator[sa.Engine]:
    """A migrated index: a SQLite file in the data root, or a fresh PostgreSQL schema."""
    if request.param == "sqlite":
        engine = open_index(f"sqlite:///{data_root / 'index.sqlite'}")
        yield engine
        engine.dispose()
        return
    with postgres_index() as engine:
        yield engine


@pytest.fixture()
def index(engine: sa.Engine) -> SessionIndex:
    return SessionIndex(engine)


def build_header(**overrides: Any) -> SessionHeader:
    """A pendulum_3-like header (three hinges, three motors); fields overridable."""
    values: dict[str, Any] = {
        "session_id": str(uuid.uuid4()),
        "tenant": "",
        "model_id": "sha256:" + "ab" * 32,
        "model_name": "pendulum_3",
        "model_version": 1,
        "joint_names": ("hinge_1", "hinge_2", "hinge_3"),
        "joint_types": ("hinge", "hinge", "hinge"),
        "dof_names": ("hinge_1", "hinge_2", "hinge_3"),
        "actuator_names": ("motor_1", "motor_2", "motor_3"),
        "nq": 3,
        "nv": 3,
        "nu": 3,
        "nsensordata": 0,
        "timestep": 0.002,
        "dt": 0.01,
        "scenario": "PASSIVE",
        "clock": "LOCKSTEP",
        "estimator": {"estimator": "UKF", "preset": "JITDYN", "sigma_points": "MERWE", "alpha": 0.001},
        "subject_pseudonym": "",
        "subject_attributes": {},
        "started_at": dt.datetime(2026, 11, 21, 10, 0, 0, tzinfo=dt.UTC),
    }
    values.update(overrides)
    return SessionHeader(**values)


@pytest.fixture()
def make_header() -> Callable[..., SessionHeader]:
    return build_header


def build_records(n: int, *, seed: int = 0, nv: int = 3) -> list[TickRecord]:
    """A seeded mix: MEASURED ticks, a PREDICTED tick every 5th, its CORRECTED answer two ticks
    later, and a rejected frame every 7th; optional fields absent in some rows."""
    rng = np.random.default_rng(seed)
    records: list[TickRecord] = []
    for seq in range(n):
        predicted = seq % 5 == 3
        records.append(
            TickRecord(
                kind="result",
                seq=seq,
                source="PREDICTED" if predicted else "MEASURED",
                t=seq * 0.01,
                server_time=seq * 0.01 + 1e-4,
                frame_received=not predicted,
                frame_t=None if predicted else seq * 0.01,
                frame_qpos=None if predicted else rng.standard_normal(nv),
                frame_qvel=None if predicted else rng.standard_normal(nv),
                frame_delay=None if predicted else 0.0,
                qpos=rng.standard_normal(nv),
                qvel=rng.standard_normal(nv),
                qacc=rng.standard_normal(nv),
                qfrc_inverse=rng.standard_normal(nv),
                covariance_diagonal=rng.random(2 * nv),
                filter_state=rng.standard_normal(2 * nv),
                nis=None if predicted else float(rng.random()),
                reinitialised=seq == 2,
                compute_us=int(rng.integers(10, 500)),
                receive_to_send_us=int(rng.integers(10, 900)),
            )
        )
        if seq % 5 == 0 and seq >= 5:
            late = seq - 2
            records.append(
                TickRecord(
                    kind="result",
                    seq=late,
                    source="CORRECTED",
                    t=late * 0.01,
                    server_time=seq * 0.01 + 2e-4,
                    frame_received=True,
                    frame_t=late * 0.01,
                    frame_qpos=rng.standard_normal(nv),
                    frame_qvel=rng.standard_normal(nv),
                    late_ticks=2,
                    frame_delay=0.02,
                    qpos=rng.standard_normal(nv),
                    qvel=rng.standard_normal(nv),
                    qacc=rng.standard_normal(nv),
                    qfrc_inverse=rng.standard_normal(nv),
                    covariance_diagonal=rng.random(2 * nv),
                    filter_state=rng.standard_normal(2 * nv),
                    nis=float(rng.random()),
                    compute_us=int(rng.integers(10, 500)),
                    receive_to_send_us=int(rng.integers(10, 900)),
                )
            )
        if seq % 7 == 6:
            records.append(
                TickRecord(
                    kind="rejected",
                    seq=seq + 1000,
                    t=(seq + 1000) * 0.01,
                    server_time=seq * 0.01 + 3e-4,
                    reject_reason="BAD_CHECKSUM",
                    reject_message=f"frame {seq + 1000}: checksum 0x1 does not match the frame's 0x2",
                )
            )
    return records


@pytest.fixture()
def make_records() -> Callable[..., list[TickRecord]]:
    return build_records


@pytest.fixture()
def session_server(index: SessionIndex, tenant_interceptor: grpc.aio.ServerInterceptor) -> Iterator[str]:
    """A grpc.aio server with the SessionServicer on 127.0.0.1:0, in its own event-loop thread;
    yields its address."""
    from jitdyn.server.transport.session_service import SessionServicer
    from jitdyn.v1 import session_pb2_grpc

    loop = asyncio.new_event_loop()
    started = threading.Event()
    state: dict[str, Any] = {}

    async def start() -> None:
        server = grpc.aio.server(interceptors=[tenant_interceptor])
        session_pb2_grpc.add_SessionServiceServicer_to_server(  # type: ignore[no-untyped-call]
            SessionServicer(index), server
        )
        state["port"] = server.add_insecure_port("127.0.0.1:0")
        await server.start()
        state["server"] = server

    def run() -> None:
        asyncio.set_event_loop(loop)
        loop.run_until_complete(start())
        started.set()
        loop.run_forever()

    thread = threading.Thread(target=run, name="session-server", daemon=True)
    thread.start()
    if not started.wait(30):
        raise RuntimeError("the test gRPC server did not start within 30 s")
    try:
        yield f"127.0.0.1:{state['port']}"
    finally:
        asyncio.run_coroutine_threadsafe(state["server"].stop(None), loop).result(30)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(30)
        loop.close()
