"""SessionRecorder: what is appended is what the Parquet file holds, with the layout, encodings and
metadata of the stored session (storage/columns.py); group commit and durable_seq; the lifecycle; the index row."""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import duckdb
import numpy as np
import pyarrow.parquet as pq
import pytest

from jitdyn.errors import FailedPrecondition, InvalidArgument
from jitdyn.storage.columns import ARRAY_FIELDS, SCALAR_FIELDS
from jitdyn.storage.index import SessionIndex
from jitdyn.storage.log import read_log
from jitdyn.storage.recorder import SessionRecorder
from jitdyn.storage.records import SessionHeader, SessionSummaryInfo, TickRecord


def assert_rows_equal(rows: list[dict[str, Any]], records: list[TickRecord]) -> None:
    assert len(rows) == len(records)
    for row, record in zip(rows, records, strict=True):
        for f in SCALAR_FIELDS:
            assert row[f.name] == getattr(record, f.name), (f.name, record.seq)
        for name in ARRAY_FIELDS:
            expected = getattr(record, name)
            if expected is None:
                assert row[name] is None, (name, record.seq)
            else:
                assert row[name] == expected.tolist(), (name, record.seq)


def wait_until(predicate: Callable[[], bool], timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.002)
    return predicate()


def test_round_trip_parquet_equals_appended(
    data_root: Path, index: SessionIndex, make_header: Callable[..., SessionHeader], make_records: Any
) -> None:
    header = make_header()
    records = make_records(120)
    with SessionRecorder(data_root=data_root, index=index, header=header) as recorder:
        for record in records:
            recorder.append(record)
        location = recorder.close()

    assert location == f"frames/model=pendulum_3/date=2026-11-21/{header.session_id}.parquet"
    table = pq.read_table(data_root / location)
    rows = table.to_pylist()
    assert {r["session_id"] for r in rows} == {header.session_id}
    assert {r["model_name"] for r in rows} == {"pendulum_3"}
    assert_rows_equal(rows, records)
    assert not (data_root / "logs" / f"{header.session_id}.arrows").exists()

    row = index.get(header.session_id, tenant="")
    assert row.status == "COMPLETE"
    assert row.location == location
    assert row.log_path == ""
    assert row.ended_at is not None
    results = [r for r in records if r.kind == "result"]
    assert row.summary.ticks == 120
    assert row.summary.measured == sum(r.source == "MEASURED" for r in results)
    assert row.summary.predicted == sum(r.source == "PREDICTED" for r in results)
    assert row.summary.corrected == sum(r.source == "CORRECTED" for r in results)
    assert row.summary.rejected == sum(r.kind == "rejected" for r in records)
    assert row.summary.late == row.summary.corrected
    assert row.summary.frames == sum(r.frame_received for r in results) + row.summary.rejected
    assert row.summary.max_compute_us == max(r.compute_us for r in results)
    forces = np.array([r.qfrc_inverse for r in results])
    assert row.summary.stats["qfrc_inverse"] == {
        name: {"min": float(forces[:, i].min()), "max": float(forces[:, i].max())}
        for i, name in enumerate(header.dof_names)
    }


def test_parquet_metadata_readable_by_pyarrow_and_duckdb(
    data_root: Path, index: SessionIndex, make_header: Callable[..., SessionHeader], make_records: Any
) -> None:
    header = make_header(
        joint_names=("root", "slider", "elbow"),
        joint_types=("ball", "slide", "hinge"),
        dof_names=("root_0", "root_1", "root_2", "slider", "elbow"),
        nq=6,
        nv=5,
        nu=0,
        actuator_names=(),
    )
    with SessionRecorder(data_root=data_root, index=index, header=header) as recorder:
        location = recorder.close()
    path = data_root / location

    from_pyarrow = json.loads(pq.read_schema(path).metadata[b"jitdyn"])
    con = duckdb.connect(config={"autoinstall_known_extensions": False, "autoload_known_extensions": False})
    found = con.execute(
        "SELECT value FROM parquet_kv_metadata(?) WHERE key = 'jitdyn'", [str(path)]
    ).fetchone()
    assert found is not None
    (raw,) = found
    con.close()
    from_duckdb = json.loads(raw)
    assert from_duckdb == from_pyarrow
    assert from_pyarrow["model_id"] == header.model_id
    assert from_pyarrow["model_name"] == "pendulum_3"
    assert from_pyarrow["model_version"] == 1
    assert from_pyarrow["joint_names"] == ["root", "slider", "elbow"]
    assert from_pyarrow["qpos_names"] == ["root_qw", "root_qx", "root_qy", "root_qz", "slider", "elbow"]
    assert from_pyarrow["dof_names"] == ["root_0", "root_1", "root_2", "slider", "elbow"]
    assert from_pyarrow["dof_units"] == ["rad", "rad", "rad", "m", "rad"]
    assert from_pyarrow["dt"] == 0.01
    assert from_pyarrow["timestep"] == 0.002
    assert from_pyarrow["scenario"] == "PASSIVE"
    assert from_pyarrow["clock"] == "LOCKSTEP"
    assert from_pyarrow["estimator"] == header.estimator
    assert from_pyarrow["schema_version"] == 1
    # A zero-row session is a valid, typed file.
    assert pq.read_table(path).num_rows == 0


def test_parquet_encodings_and_compression(
    data_root: Path, index: SessionIndex, make_header: Callable[..., SessionHeader], make_records: Any
) -> None:
    header = make_header()
    with SessionRecorder(data_root=data_root, index=index, header=header) as recorder:
        for record in make_records(50):
            recorder.append(record)
        location = recorder.close()
    metadata = pq.ParquetFile(data_root / location).metadata
    group = metadata.row_group(0)
    columns = {group.column(i).path_in_schema: group.column(i) for i in range(group.num_columns)}
    dictionary_columns = {"session_id", "model_name", "kind", "source", "reject_reason"}
    for path, column in columns.items():
        assert column.compression == "ZSTD", path
        dictionary = any("DICTIONARY" in e for e in column.encodings)
        assert dictionary == (path in dictionary_columns), (path, column.encodings)
        if column.physical_type == "DOUBLE":
            assert "BYTE_STREAM_SPLIT" in column.encodings, (path, column.encodings)
    assert columns["qpos.list.element"].physical_type == "DOUBLE"
    schema = pq.read_schema(data_root / location)
    assert str(schema.field("qfrc_inverse").type) == "list<element: double>"


def test_row_groups_of_about_100k_rows(
    data_root: Path, index: SessionIndex, make_header: Callable[..., SessionHeader]
) -> None:
    header = make_header()
    qpos = np.zeros(3)
    with SessionRecorder(data_root=data_root, index=index, header=header, commit_every=50_000) as recorder:
        for seq in range(250_000):
            recorder.append(TickRecord(kind="result", seq=seq, source="MEASURED", qpos=qpos))
        location = recorder.close()
    metadata = pq.ParquetFile(data_root / location).metadata
    assert [metadata.row_group(i).num_rows for i in range(metadata.num_row_groups)] == [
        100_000,
        100_000,
        50_000,
    ]


def test_durable_seq_follows_results_not_rejections(
    data_root: Path, index: SessionIndex, make_header: Callable[..., SessionHeader]
) -> None:
    with SessionRecorder(data_root=data_root, index=index, header=make_header()) as recorder:
        assert recorder.durable_seq is None
        recorder.append(TickRecord(kind="rejected", seq=99, reject_reason="TOO_OLD"))
        recorder.flush()
        assert recorder.durable_seq is None
        for seq in range(3):
            recorder.append(TickRecord(kind="result", seq=seq, source="MEASURED"))
        recorder.append(TickRecord(kind="rejected", seq=1_000_000, reject_reason="OUT_OF_ORDER"))
        recorder.flush()
        assert recorder.durable_seq == 2
        recorder.append(TickRecord(kind="result", seq=1, source="CORRECTED"))
        recorder.flush()
        assert recorder.durable_seq == 2


def test_group_commit_by_count_and_by_interval(
    data_root: Path, index: SessionIndex, make_header: Callable[..., SessionHeader]
) -> None:
    # A long interval: only the count can trigger a commit.
    with SessionRecorder(
        data_root=data_root, index=index, header=make_header(), commit_every=4, commit_interval=30.0
    ) as recorder:
        for seq in range(3):
            recorder.append(TickRecord(kind="result", seq=seq, source="MEASURED"))
        time.sleep(0.2)
        assert recorder.durable_seq is None
        recorder.append(TickRecord(kind="result", seq=3, source="MEASURED"))
        assert wait_until(lambda: recorder.durable_seq == 3)
    # A large count: only the interval can.
    with SessionRecorder(
        data_root=data_root, index=index, header=make_header(), commit_every=10_000, commit_interval=0.02
    ) as recorder:
        recorder.append(TickRecord(kind="result", seq=0, source="MEASURED"))
        assert wait_until(lambda: recorder.durable_seq == 0)


def test_lifecycle_close_twice_append_after_close_and_failure(
    data_root: Path, index: SessionIndex, make_header: Callable[..., SessionHeader]
) -> None:
    header = make_header()
    recorder = SessionRecorder(data_root=data_root, index=index, header=header)
    recorder.append(TickRecord(kind="result", seq=0, source="MEASURED"))
    summary = SessionSummaryInfo(ticks=1, frames=1, measured=1, duration=0.5, stats={"note": "given"})
    location = recorder.close(summary)
    assert recorder.close() == location
    with pytest.raises(FailedPrecondition) as error:
        recorder.append(TickRecord(kind="result", seq=1, source="MEASURED"))
    assert str(error.value) == f"the recorder of session {header.session_id} is closed; append before close"
    assert index.get(header.session_id, tenant="").summary == summary

    failed = make_header()
    with pytest.raises(RuntimeError), SessionRecorder(data_root=data_root, index=index, header=failed) as rec:
        rec.append(TickRecord(kind="result", seq=0, source="MEASURED"))
        raise RuntimeError("the session broke")
    row = index.get(failed.session_id, tenant="")
    assert row.status == "FAILED"
    assert pq.read_table(data_root / row.location).num_rows == 1


def test_wrong_array_length_fails_the_recorder_loudly(
    data_root: Path, index: SessionIndex, make_header: Callable[..., SessionHeader]
) -> None:
    header = make_header()
    recorder = SessionRecorder(data_root=data_root, index=index, header=header, commit_interval=30.0)
    recorder.append(TickRecord(kind="result", seq=0, source="MEASURED", qpos=np.zeros(3)))
    with pytest.raises(InvalidArgument) as error:
        recorder.append(TickRecord(kind="result", seq=1, source="MEASURED", qpos=np.zeros(4)))
    assert str(error.value) == f"session {header.session_id}: qpos must have 3 values in every record, got 4"
    with pytest.raises(InvalidArgument):
        recorder.append(TickRecord(kind="result", seq=2, source="MEASURED"))
    with pytest.raises(InvalidArgument):
        recorder.flush()
    with pytest.raises(InvalidArgument):
        recorder.close()
    # What was durable stays in the log, the session OPEN, for recovery at the next start: the
    # rows before the bad one, not the bad one.
    assert index.get(header.session_id, tenant="").status == "OPEN"
    log = read_log(data_root / "logs" / f"{header.session_id}.arrows")
    assert log.table.column("seq").to_pylist() == [0]


def test_a_result_row_that_does_not_fit_fails_the_recorder(
    data_root: Path, index: SessionIndex, make_header: Callable[..., SessionHeader]
) -> None:
    header = make_header()
    recorder = SessionRecorder(data_root=data_root, index=index, header=header, commit_interval=30.0)
    vectors = [None] * len(ARRAY_FIELDS)
    vectors[ARRAY_FIELDS.index("qvel")] = np.zeros(2)
    # The row's vectors are copied into their columns when its window is committed: there the
    # misfit is named, and the recorder fails.
    recorder.append_result((0, "MEASURED", 0.0, 0.0, None, 0, None, None, False, False, 1, 2, tuple(vectors)))
    with pytest.raises(InvalidArgument) as error:
        recorder.flush(timeout=30)
    assert str(error.value) == f"session {header.session_id}: qvel must have 3 values in every record, got 2"
    with pytest.raises(InvalidArgument):
        recorder.close()


def test_record_of_the_wrong_type_fails_the_recorder(
    data_root: Path, index: SessionIndex, make_header: Callable[..., SessionHeader]
) -> None:
    header = make_header()
    recorder = SessionRecorder(data_root=data_root, index=index, header=header)
    with pytest.raises(InvalidArgument) as error:
        recorder.append(TickRecord(kind="result", seq="seven", source="MEASURED"))  # type: ignore[arg-type]
    assert str(error.value) == f"session {header.session_id}: seq must be int64, got 'seven'"
    with pytest.raises(InvalidArgument):
        recorder.append(TickRecord(kind="result", seq=1, source=7))  # type: ignore[arg-type]
    with pytest.raises(InvalidArgument):
        recorder.close()
    other = SessionRecorder(data_root=data_root, index=index, header=make_header())
    with pytest.raises(InvalidArgument) as error:
        other.append(TickRecord(kind="result", seq=1, source=7))  # type: ignore[arg-type]
    assert str(error.value) == f"session {other.header.session_id}: source must be a str, got 7"
    with pytest.raises(InvalidArgument):
        other.close()


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"session_id": "not-a-uuid"}, "session_id must be a UUID in canonical form"),
        ({"model_name": "../etc"}, "model_name must be 1 to 64 letters, digits"),
        (
            {"scenario": "passive"},
            "scenario must be one of PASSIVE, CONTROLLED, EXTERNAL, DRIVEN, got 'passive'",
        ),
        ({"nq": 4}, "the joints ['hinge', 'hinge', 'hinge'] span nq=3, nv=3, but the header says nq=4, nv=3"),
        ({"dof_names": ("a",)}, "dof_names must have nv=3 names, got 1"),
        ({"estimator": {"alpha": math.nan}}, "estimator settings must be JSON-serialisable"),
    ],
)
def test_header_is_validated(
    make_header: Callable[..., SessionHeader], overrides: dict[str, Any], message: str
) -> None:
    with pytest.raises(InvalidArgument) as error:
        make_header(**overrides)
    assert str(error.value).startswith(message)


def test_naive_start_time_is_refused(make_header: Callable[..., SessionHeader]) -> None:
    import datetime as dt

    with pytest.raises(InvalidArgument, match="started_at must be timezone-aware"):
        make_header(started_at=dt.datetime(2026, 1, 1))
