"""WindowRows: the batch viewing a window's columns equals the one `records_to_batch` converts from
the same records (the plain reference), window after window of the same columns, through growth,
widths that change, failed appends and an IPC round trip; and it views the columns, not a copy."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pyarrow as pa
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from jitdyn.errors import InvalidArgument
from jitdyn.storage.buffers import WindowRows
from jitdyn.storage.columns import ARRAY_FIELDS, LOG_SCHEMA, expected_lengths, records_to_batch
from jitdyn.storage.records import SessionHeader, TickRecord


def assert_same(rows: WindowRows, records: list[TickRecord]) -> None:
    batch = rows.batch()
    batch.validate(full=True)
    expected = records_to_batch(records)
    assert batch.schema.equals(LOG_SCHEMA)
    assert batch.equals(expected)
    assert pa.ipc.read_record_batch(batch.serialize(), LOG_SCHEMA).equals(expected)


@pytest.mark.parametrize(("capacity", "window"), [(1, 7), (16, 5), (16, 16), (64, 120)])
def test_windows_equal_the_converted_records(
    make_header: Callable[..., SessionHeader], make_records: Any, capacity: int, window: int
) -> None:
    records: list[TickRecord] = make_records(300, seed=capacity)
    rows = WindowRows(lengths=expected_lengths(make_header()), capacity=capacity)
    for start in range(0, len(records), window):
        part = records[start : start + window]
        for record in part:
            rows.append(record)
        assert rows.rows == len(part)
        seqs = [r.seq for r in part if r.kind == "result"]
        assert rows.top_seq == (max(seqs) if seqs else None)
        assert_same(rows, part)
        rows.clear()
    assert rows.rows == 0 and rows.top_seq is None


def test_the_batch_views_the_columns(make_header: Callable[..., SessionHeader], make_records: Any) -> None:
    rows = WindowRows(lengths=expected_lengths(make_header()))
    records: list[TickRecord] = make_records(10)
    for record in records:
        rows.append(record)
    batch = rows.batch()
    qpos = rows.batch().column("qpos")
    # The vectors and the numbers are the block's and the column's memory, not copies.
    block = next(v.block for v in rows._vectors if v.name == "qpos")
    assert block is not None
    assert qpos.values.buffers()[1].address == block.ctypes.data
    seq = next(s.values for s in rows._scalars if s.field.name == "seq")
    assert isinstance(seq, np.ndarray)
    assert batch.column("seq").buffers()[1].address == seq.ctypes.data
    # A copy handed on (the records' arrays may change afterwards) stays what was appended.
    records[0].qpos[:] = 99.0  # type: ignore[index]
    assert batch.column("qpos")[0].as_py() != [99.0] * 3


def test_widths_not_fixed_by_the_model_may_change(make_header: Callable[..., SessionHeader]) -> None:
    records = [
        TickRecord(kind="rejected", seq=9, reject_reason="TOO_OLD", reject_message="é" * 400),
        TickRecord(kind="result", seq=0, source="MEASURED", covariance_diagonal=None),
        TickRecord(
            kind="result", seq=1, source="MEASURED", covariance_diagonal=np.ones(4), late_compute=True
        ),
        TickRecord(kind="result", seq=2, source="PREDICTED", covariance_diagonal=np.arange(6.0)),
        TickRecord(
            kind="result", seq=3, source="MEASURED", forecast_weights=np.ones(2), filter_state=[1.0, 2.0]
        ),  # type: ignore[arg-type]
    ]
    rows = WindowRows(lengths=expected_lengths(make_header()), capacity=2)
    for record in records:
        rows.append(record)
    assert_same(rows, records)
    rows.clear()
    # The next window starts at the width its first vector has.
    for record in records[3:]:
        rows.append(record)
    assert_same(rows, records[3:])


@pytest.mark.parametrize(
    ("bad", "message"),
    [
        (
            TickRecord(kind="result", seq=5, qpos=np.zeros(4)),
            "qpos must have 3 values in every record, got 4",
        ),
        (
            TickRecord(kind="result", seq=5, qvel=np.zeros((1, 3))),
            "qvel must hold 1-D vectors, got an array of shape (1, 3)",
        ),
        (TickRecord(kind="result", seq="five"), "seq must be int64, got 'five'"),  # type: ignore[arg-type]
        (TickRecord(kind="result", seq=2**63), f"seq must be int64, got {2**63}"),
        (TickRecord(kind="result", seq=5, source=3), "source must be a str, got 3"),  # type: ignore[arg-type]
        (TickRecord(kind="result", seq=5, frame_received=1), "frame_received must be a bool, got 1"),  # type: ignore[arg-type]
    ],
)
def test_a_record_that_does_not_fit_is_refused_and_not_stored(
    make_header: Callable[..., SessionHeader], make_records: Any, bad: TickRecord, message: str
) -> None:
    records: list[TickRecord] = make_records(6)
    rows = WindowRows(lengths=expected_lengths(make_header()), capacity=4)
    for record in records[:3]:
        rows.append(record)
    with pytest.raises(InvalidArgument) as error:
        rows.append(bad)
    assert str(error.value) == message
    for record in records[3:]:
        rows.append(record)
    assert_same(rows, records)


def test_capacity_is_checked(make_header: Callable[..., SessionHeader]) -> None:
    with pytest.raises(InvalidArgument, match="capacity must be >= 1 row, got 0"):
        WindowRows(lengths=expected_lengths(make_header()), capacity=0)
    with pytest.raises(InvalidArgument, match=r"lengths must name array columns of the log, got \['nis'\]"):
        WindowRows(lengths={"nis": 1})


def test_a_column_present_absent_or_mixed_window_after_window(
    make_header: Callable[..., SessionHeader],
) -> None:
    # Each window starts in the pattern of the previous one's last row and breaks it somewhere.
    windows = ["PPPP", "PPAP", "AAAA", "AAPA", "P", "A", "PPPPPPPPPPPPPPPPPPPA", "AP", "PA"]
    rows = WindowRows(lengths=expected_lengths(make_header()), capacity=2)
    seq = 0
    for pattern in windows:
        records = []
        for mark in pattern:
            present = mark == "P"
            records.append(
                TickRecord(
                    kind="result",
                    seq=seq,
                    qpos=np.full(3, float(seq)) if present else None,
                    covariance_diagonal=np.full(2 + seq % 3, 1.0) if present else None,
                )
            )
            seq += 1
        for record in records:
            rows.append(record)
        assert_same(rows, records)
        rows.clear()


def test_a_mixed_window_after_a_wider_dense_one(make_header: Callable[..., SessionHeader]) -> None:
    """A session whose filter changed (its state 3 wide, then 2) in a window that also holds rows
    without one (a rejected frame): the row-by-row window must not keep the wider window's offsets,
    which Arrow checks against the narrower block (a server's commit failed so: "Length spanned by
    list offsets (48) larger than values array (length 32)")."""
    rows = WindowRows(lengths=expected_lengths(make_header()), capacity=16)
    wide = [TickRecord(kind="result", seq=k, filter_state=np.full(3, float(k))) for k in range(16)]
    for record in wide:
        rows.append(record)
    assert_same(rows, wide)
    rows.clear()
    narrow = [
        TickRecord(kind="rejected", seq=16, reject_reason="TOO_OLD", reject_message="late"),
        *(TickRecord(kind="result", seq=k, filter_state=np.full(2, float(k))) for k in range(17, 27)),
    ]
    for record in narrow:
        append_row(rows, record)
    assert_same(rows, narrow)


_ROW = st.tuples(st.booleans(), st.integers(0, 4), st.booleans())  # a result?, its width, by values?


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    windows=st.lists(st.lists(_ROW, min_size=1, max_size=20), min_size=1, max_size=6),
    capacity=st.sampled_from([1, 4, 16]),
)
def test_any_windows_of_any_widths_equal_the_converted_records(
    make_header: Callable[..., SessionHeader], windows: list[list[tuple[bool, int, bool]]], capacity: int
) -> None:
    """Windows one after another, each row a result or a rejected frame, its width-free vectors
    (the covariance, the filter state) absent or of a width of its own, written as a record or from
    its values: every window's batch equals the records converted, as Arrow reads it back."""
    rows = WindowRows(lengths=expected_lengths(make_header()), capacity=capacity)
    seq = 0
    for window in windows:
        records = []
        for result, width, by_values in window:
            vector = None if width == 0 else np.full(width, float(seq))
            record = (
                TickRecord(kind="result", seq=seq, covariance_diagonal=vector, filter_state=vector)
                if result
                else TickRecord(kind="rejected", seq=seq, reject_reason="TOO_OLD", reject_message="late")
            )
            (append_row if by_values else WindowRows.append)(rows, record)
            records.append(record)
            seq += 1
        assert_same(rows, records)
        rows.clear()


def append_row(rows: WindowRows, record: TickRecord) -> None:
    """`record` through the tick's path: a result's values straight into the row, a rejection as a
    record (what the server does with each)."""
    if record.kind != "result":
        rows.append(record)
        return
    rows.append_result(
        (
            record.seq,
            record.source,
            record.t,
            record.server_time,
            record.frame_t,
            record.late_ticks,
            record.frame_delay,
            record.nis,
            record.reinitialised,
            record.late_compute,
            record.compute_us,
            record.receive_to_send_us,
            tuple(getattr(record, name) for name in ARRAY_FIELDS),
        )
    )


@pytest.mark.parametrize(("capacity", "window"), [(1, 7), (16, 5), (64, 120)])
def test_result_rows_written_from_their_values_equal_the_converted_records(
    make_header: Callable[..., SessionHeader], make_records: Any, capacity: int, window: int
) -> None:
    records: list[TickRecord] = make_records(300, seed=capacity + 7)
    # A result's frame_received is whether its frame (frame_t) arrived.
    assert all(r.frame_received == (r.frame_t is not None) for r in records if r.kind == "result")
    rows = WindowRows(lengths=expected_lengths(make_header()), capacity=capacity)
    for start in range(0, len(records), window):
        part = records[start : start + window]
        for record in part:
            append_row(rows, record)
        seqs = [r.seq for r in part if r.kind == "result"]
        assert rows.top_seq == (max(seqs) if seqs else None)
        assert_same(rows, part)
        rows.clear()


def test_a_result_row_holds_its_vectors_until_the_batch_copies_them(
    make_header: Callable[..., SessionHeader],
) -> None:
    rows = WindowRows(lengths=expected_lengths(make_header()))
    qpos = np.array([1.0, 2.0, 3.0])
    vectors: list[np.ndarray | None] = [None] * len(ARRAY_FIELDS)
    vectors[ARRAY_FIELDS.index("qpos")] = qpos
    rows.append_result((4, "MEASURED", 0.2, 0.25, None, 0, None, None, False, False, 10, 20, tuple(vectors)))
    batch = rows.batch()
    qpos[:] = 9.0  # the caller's array changes once the window's batch was built
    assert batch.column("qpos").to_pylist() == [[1.0, 2.0, 3.0]]
    with pytest.raises(InvalidArgument, match="^a row needs 15 vectors"):
        rows.append_result((5, "MEASURED", 0.3, 0.35, None, 0, None, None, False, False, 10, 20, (qpos,)))
    # The row refused left nothing behind.
    assert rows.rows == 1 and rows.batch().column("seq").to_pylist() == [4]
    rows.clear()
    vectors[ARRAY_FIELDS.index("qvel")] = np.zeros(5)
    rows.append_result((5, "MEASURED", 0.3, 0.35, None, 0, None, None, False, False, 10, 20, tuple(vectors)))
    with pytest.raises(InvalidArgument, match="^qvel must have 3 values in every record, got 5$"):
        rows.batch()


def test_a_steady_result_row_takes_the_straight_line(
    make_header: Callable[..., SessionHeader], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Once its words are encoded, a result's row is written by the straight line, not as a
    record (which would give the same batch, at twice the cost)."""
    rows = WindowRows(lengths=expected_lengths(make_header()))
    vectors = tuple(np.ones(3) if name in ("qpos", "qvel", "qacc") else None for name in ARRAY_FIELDS)
    rows.append_result((0, "MEASURED", 0.0, 0.0, None, 0, None, None, False, False, 1, 2, vectors))
    rows.clear()

    def checked(row: int, record: TickRecord) -> bool:
        raise AssertionError(f"row {row} went the checked way")

    monkeypatch.setattr(rows, "_write_checked", checked)
    for seq in range(3):
        rows.append_result((seq, "MEASURED", 0.0, 0.0, None, 0, None, None, False, False, 1, 2, vectors))
    assert rows.batch().column("qvel").to_pylist() == [[1.0, 1.0, 1.0]] * 3
