"""A whole server on the PostgreSQL index (as replicas sharing one index run): a session with an
identifying subject leaves no identifying byte in the data folder or in the index rows."""

from __future__ import annotations

import uuid
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
import sqlalchemy as sa

from jitdyn.client import Client, FrameData, SessionOptions
from jitdyn.server.transport.background import BackgroundServer

POSTGRES_URL = "postgresql+psycopg://root@127.0.0.1:5432/test"
SUBJECT = "patient-4711"
NAME = "Erika Mustermann"


@pytest.fixture()
def pg_server(tmp_path: Any, make_config: Callable[..., Any]) -> Iterator[tuple[BackgroundServer, str]]:
    schema = f"jitdyn_server_{uuid.uuid4().hex[:12]}"
    config = make_config(tmp_path / "data", index_url=POSTGRES_URL, index_schema=schema)
    try:
        with BackgroundServer(config) as running:
            yield running, schema
    finally:
        engine = sa.create_engine(POSTGRES_URL)
        with engine.begin() as conn:
            conn.execute(sa.text(f'DROP SCHEMA IF EXISTS "{schema}" CASCADE'))
        engine.dispose()


@pytest.mark.postgres
def test_a_session_indexed_in_postgres_keeps_no_identifying_byte(
    pg_server: tuple[BackgroundServer, str],
) -> None:
    server, schema = pg_server
    options = SessionOptions(
        model_name="pendulum_2",
        dt=0.05,
        subject_id=SUBJECT,
        subject_attributes={"side": "left", "height_m": "1.71"},
    )
    with Client(server.address) as client, client.open_session(options) as session:
        assert session.opened.dropped_attributes == ()
        for k in range(20):
            q = np.array([0.3 * np.cos(0.2 * k), 0.1])
            session.send_frame(FrameData(seq=k, t=k * 0.05, qpos=q, qvel=[0.0, 0.0]))
        summary = session.close()
        pseudonym = session.opened.subject_pseudonym
        stored = client.get_session(session.opened.session_id)
    assert stored.status == 2 and stored.location == summary.location  # COMPLETE
    assert dict(stored.subject_attributes) == {"side": "left", "height_m": "1.70"}
    assert stored.subject_pseudonym == pseudonym and len(pseudonym) == 64

    engine = sa.create_engine(POSTGRES_URL)
    with engine.connect() as conn:
        rows = conn.execute(sa.text(f'SELECT * FROM "{schema}".sessions')).all()
    engine.dispose()
    assert len(rows) == 1
    text = repr([tuple(row) for row in rows])
    assert SUBJECT not in text and NAME not in text and "Erika" not in text
    assert server.services is not None
    for path in server.services.data_root.rglob("*"):
        if path.is_file():
            data = path.read_bytes()
            assert SUBJECT.encode() not in data and b"Erika" not in data, path
            assert b"127.0.0.1" not in data, path  # no client address either
