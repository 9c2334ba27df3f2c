"""run_query: DuckDB over the tenant's Parquet files (`frames`) joined with its index rows
(`sessions`); empty datasets; errors; nothing outside the tenant's files is readable."""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import sqlalchemy as sa

from jitdyn.errors import InvalidArgument
from jitdyn.storage.index import SessionIndex
from jitdyn.storage.query import run_query
from jitdyn.storage.recorder import SessionRecorder
from jitdyn.storage.records import SessionHeader, TickRecord


def record(
    data_root: Path,
    index: SessionIndex,
    header: SessionHeader,
    records: list[TickRecord],
    *,
    close: bool = True,
) -> SessionRecorder:
    recorder = SessionRecorder(data_root=data_root, index=index, header=header)
    for r in records:
        recorder.append(r)
    if close:
        recorder.close()
    return recorder


def test_frames_join_sessions(
    data_root: Path,
    engine: sa.Engine,
    index: SessionIndex,
    make_header: Callable[..., SessionHeader],
    make_records: Any,
) -> None:
    p3 = make_header(subject_pseudonym="ab" * 32, subject_attributes={"sex": "F"})
    p1 = make_header(
        model_name="pendulum_1",
        joint_names=("hinge",),
        joint_types=("hinge",),
        dof_names=("hinge",),
        actuator_names=("motor",),
        nq=1,
        nv=1,
        nu=1,
        started_at=dt.datetime(2026, 11, 22, 9, 0, tzinfo=dt.UTC),
    )
    records3 = make_records(30)
    records1 = make_records(10, nv=1)
    record(data_root, index, p3, records3)
    record(data_root, index, p1, records1)
    hidden = make_header(tenant="other")
    record(data_root, index, hidden, make_records(5))

    table = run_query(
        "SELECT s.model_name, s.subject_pseudonym, s.subject_attributes['sex'] AS sex, f.model, "
        "CAST(f.date AS VARCHAR) AS day, count(*) AS n, "
        "count(*) FILTER (WHERE f.source = 'CORRECTED') AS corrected, max(len(f.qpos)) AS nq "
        "FROM frames f JOIN sessions s USING (session_id) GROUP BY ALL ORDER BY s.model_name",
        data_root=data_root,
        engine=engine,
    )
    assert table.to_pylist() == [
        {
            "model_name": "pendulum_1",
            "subject_pseudonym": "",
            "sex": None,
            "model": "pendulum_1",
            "day": "2026-11-22",
            "n": len(records1),
            "corrected": sum(r.source == "CORRECTED" for r in records1),
            "nq": 1,
        },
        {
            "model_name": "pendulum_3",
            "subject_pseudonym": "ab" * 32,
            "sex": "F",
            "model": "pendulum_3",
            "day": "2026-11-21",
            "n": len(records3),
            "corrected": sum(r.source == "CORRECTED" for r in records3),
            "nq": 3,
        },
    ]
    qfrc = run_query(
        "SELECT qfrc_inverse FROM frames WHERE session_id = ? ORDER BY seq LIMIT 1".replace(
            "?", f"'{p3.session_id}'"
        ),
        data_root=data_root,
        engine=engine,
    )
    assert qfrc.column("qfrc_inverse").to_pylist() == [records3[0].qfrc_inverse.tolist()]

    # The other tenant sees only its own session, in both tables.
    other = run_query(
        "SELECT (SELECT count(DISTINCT session_id) FROM frames) AS f, (SELECT count(*) FROM sessions) AS s",
        data_root=data_root,
        engine=engine,
        tenant="other",
    )
    assert other.to_pylist() == [{"f": 1, "s": 1}]


def test_empty_dataset_and_open_sessions(
    data_root: Path, engine: sa.Engine, index: SessionIndex, make_header: Callable[..., SessionHeader]
) -> None:
    table = run_query("SELECT count(*) AS n, max(seq) AS m FROM frames", data_root=data_root, engine=engine)
    assert table.to_pylist() == [{"n": 0, "m": None}]
    header = make_header()
    recorder = record(
        data_root, index, header, [TickRecord(kind="result", seq=0, source="MEASURED")], close=False
    )
    table = run_query(
        "SELECT status, (SELECT count(*) FROM frames) AS n FROM sessions", data_root=data_root, engine=engine
    )
    assert table.to_pylist() == [{"status": "OPEN", "n": 0}]
    columns = run_query("SELECT * FROM frames", data_root=data_root, engine=engine).column_names
    assert columns[:3] == ["session_id", "model_name", "kind"]
    assert columns[-2:] == ["model", "date"]
    recorder.close()
    # In the query's own throw-away database; DuckDB reports the rows it wrote.
    assert run_query("CREATE TABLE t AS SELECT 1 AS x", data_root=data_root, engine=engine).to_pylist() == [
        {"Count": 1}
    ]
    assert run_query("CREATE VIEW v AS SELECT 1", data_root=data_root, engine=engine).num_rows == 0


@pytest.mark.parametrize(
    ("sql", "message"),
    [
        ("SELEC 1", 'the query failed: Parser Error: syntax error at or near "SELEC"'),
        ("SELECT nope FROM frames", 'the query failed: Binder Error: Referenced column "nope" not found'),
        ("SELECT * FROM read_csv('/etc/passwd')", "the query failed: Permission Error"),
        ("COPY (SELECT 1) TO '/tmp/jitdyn-query-escape.csv'", "the query failed: Permission Error"),
        (
            "SET enable_external_access = true",
            "the query failed: Invalid Input Error: Cannot change configuration",
        ),
        (
            "SELECT * FROM data_root",
            "the query failed: Catalog Error: Table with name data_root does not exist",
        ),
    ],
)
def test_bad_or_escaping_sql_is_invalid_argument(
    data_root: Path, engine: sa.Engine, sql: str, message: str
) -> None:
    with pytest.raises(InvalidArgument) as error:
        run_query(sql, data_root=data_root, engine=engine)
    assert str(error.value).startswith(message)


def test_another_tenants_file_cannot_be_read_by_path(
    data_root: Path,
    engine: sa.Engine,
    index: SessionIndex,
    make_header: Callable[..., SessionHeader],
    make_records: Any,
) -> None:
    hidden = make_header(tenant="other")
    record(data_root, index, hidden, make_records(5))
    path = data_root / index.get(hidden.session_id, tenant="other").location
    with pytest.raises(InvalidArgument, match="Permission Error"):
        run_query(f"SELECT * FROM read_parquet('{path}')", data_root=data_root, engine=engine)
