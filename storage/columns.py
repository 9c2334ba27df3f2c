"""The columns of a session's frame table, and the conversion of `TickRecord`s into them.

The same Arrow schema serves the crash-safe log and, with `session_id` and `model_name` in front,
the Parquet file. Arrays are list<float64> columns whatever the model, so that one schema reads
every session and every reader (DuckDB, pandas, polars, Spark) agrees on the type.
"""

from __future__ import annotations

import operator
from collections.abc import Sequence
from typing import Final

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import pyarrow.compute as pc

from jitdyn.errors import InvalidArgument
from jitdyn.storage.records import SessionHeader, TickRecord

__all__ = [
    "ARRAY_FIELDS",
    "FLOAT_LIST",
    "FRAME_COLUMN_NOTES",
    "FRAME_SCHEMA",
    "ID_COLUMNS",
    "LOG_SCHEMA",
    "SCALAR_FIELDS",
    "STORED_SINCE",
    "check_lengths",
    "conform",
    "expected_lengths",
    "list_matrix",
    "records_to_batch",
]

# Parquet names the element of a list "element"; naming it so in Arrow too keeps the log's, the
# Parquet file's and a read-back table's types identical.
FLOAT_LIST: Final = pa.list_(pa.field("element", pa.float64()))

SCALAR_FIELDS: Final[tuple[pa.Field, ...]] = (
    pa.field("kind", pa.string(), nullable=False),
    pa.field("seq", pa.int64(), nullable=False),
    pa.field("source", pa.string(), nullable=False),
    pa.field("t", pa.float64(), nullable=False),
    pa.field("server_time", pa.float64(), nullable=False),
    pa.field("frame_received", pa.bool_(), nullable=False),
    pa.field("frame_t", pa.float64()),
    pa.field("late_ticks", pa.int32(), nullable=False),
    pa.field("frame_delay", pa.float64()),
    pa.field("nis", pa.float64()),
    pa.field("reinitialised", pa.bool_(), nullable=False),
    # Answered without the estimator (the server was overloaded); null in files written before it
    # was stored.
    pa.field("late_compute", pa.bool_()),
    pa.field("compute_us", pa.int64(), nullable=False),
    pa.field("receive_to_send_us", pa.int64(), nullable=False),
    pa.field("reject_reason", pa.string(), nullable=False),
    pa.field("reject_message", pa.string(), nullable=False),
)

ARRAY_FIELDS: Final[tuple[str, ...]] = (
    "frame_qpos",
    "frame_qvel",
    "frame_qacc",
    "frame_ctrl",
    "frame_sensordata",
    "qpos",
    "qvel",
    "qacc",
    "qfrc_inverse",
    "qacc_forward",
    "actuator_force",
    "sensordata",
    "covariance_diagonal",
    "filter_state",
    # A PREDICTED tick answered by the forecast combination: each predictor's weight, in the order
    # of Result.forecast_weights.
    "forecast_weights",
)

LOG_SCHEMA: Final = pa.schema([*SCALAR_FIELDS, *(pa.field(name, FLOAT_LIST) for name in ARRAY_FIELDS)])

# Constant per file; dictionary-typed so that they cost a few bytes, not a string per row.
ID_COLUMNS: Final[tuple[pa.Field, ...]] = (
    pa.field("session_id", pa.dictionary(pa.int32(), pa.string()), nullable=False),
    pa.field("model_name", pa.dictionary(pa.int32(), pa.string()), nullable=False),
)

FRAME_SCHEMA: Final = pa.schema([*ID_COLUMNS, *LOG_SCHEMA])

# What each column of the `frames` view holds, with its unit: `sessions query --help` prints these.
# The arrays' elements are named, with their units, by the `coordinates` table (storage.query,
# docs/decisions/0183).
FRAME_COLUMN_NOTES: Final = {
    "session_id": "the session",
    "model_name": "the model's name",
    "kind": "result (an answer) or rejected (a frame refused)",
    "seq": "the tick, from 0",
    "source": "MEASURED, PREDICTED or CORRECTED; empty for a rejected frame",
    "t": "s: the tick's time on the client's clock, since the session's start",
    "server_time": "s: when the server answered, on its clock, since the session's start",
    "frame_received": "the tick's frame was there when it was answered",
    "frame_t": "s: the frame's own client time",
    "late_ticks": "ticks: a CORRECTED result's count of ticks answered since it was due, itself included; 0 else",
    "frame_delay": "s: REALTIME, the frame's arrival after its tick's deadline, server clock (< 0: early)",
    "nis": "the filter's normalised innovation squared (no unit)",
    "reinitialised": "the divergence guard restarted the filter at this tick",
    "late_compute": "answered without the estimator, the server overloaded (null: not stored then)",
    "compute_us": "us: the server's compute time of the answer",
    "receive_to_send_us": "us: from the arrival of what made the answer (or the tick's deadline) to its send",
    "reject_reason": "a rejected frame's reason (BAD_SHAPE, TOO_OLD, ...)",
    "reject_message": "the server's words for it",
    "frame_qpos": "(nq) the frame's qpos: rad or m per coordinates.unit, quaternions unitless",
    "frame_qvel": "(nv) the frame's qvel: rad/s or m/s",
    "frame_qacc": "(nv) the frame's qacc: rad/s^2 or m/s^2",
    "frame_ctrl": "(nu) the frame's controls, in the actuators' units",
    "frame_sensordata": "(nsensordata) the frame's sensor values, in the sensors' units",
    "qpos": "(nq) the answered qpos",
    "qvel": "(nv) the answered qvel",
    "qacc": "(nv) the answered qacc",
    "qfrc_inverse": "(nv) inverse dynamics' generalized force: N m on a rotation, N on a translation",
    "qacc_forward": "(nv) forward dynamics' qacc under the answered state",
    "actuator_force": "(nu) the actuators' forces",
    "sensordata": "(nsensordata) the answered sensor values",
    "covariance_diagonal": "(state) the filter's variances, in the squared units of its state",
    "filter_state": "(state) the filter's state [q, qd] or [q, qd, qdd] (or with the force)",
    "forecast_weights": "(4) a gap's weights of MODEL, STATIC, CONSTANT_VELOCITY, CONSTANT_ACCELERATION",
    "model": "the Hive partition: the model's name",
    "date": "the Hive partition: the session's start date (UTC)",
}

_GETTERS: Final = {f.name: operator.attrgetter(f.name) for f in SCALAR_FIELDS} | {
    name: operator.attrgetter(name) for name in ARRAY_FIELDS
}


# The columns added to LOG_SCHEMA since the first stored sessions; older logs and files lack them.
STORED_SINCE: Final = frozenset({"late_compute", "forecast_weights"})


def conform(batch: pa.RecordBatch) -> pa.RecordBatch:
    """`batch` as LOG_SCHEMA: the columns it lacks (it was written before they were stored) added
    as nulls, so that every reader sees one schema whatever wrote the file. A batch of LOG_SCHEMA is
    returned as it is (its schema's metadata kept)."""
    schema = batch.schema
    if schema.equals(LOG_SCHEMA):
        return batch
    names = set(schema.names)
    columns = [
        batch.column(f.name) if f.name in names else pa.nulls(batch.num_rows, f.type) for f in LOG_SCHEMA
    ]
    return pa.RecordBatch.from_arrays(columns, schema=LOG_SCHEMA)


def expected_lengths(header: SessionHeader) -> dict[str, int]:
    """The length every present array of a column must have, for the columns fixed by the model.
    covariance_diagonal and filter_state depend on the scenario and are not checked."""
    nq, nv, nu, ns = header.nq, header.nv, header.nu, header.nsensordata
    return {
        "frame_qpos": nq,
        "frame_qvel": nv,
        "frame_qacc": nv,
        "frame_ctrl": nu,
        "frame_sensordata": ns,
        "qpos": nq,
        "qvel": nv,
        "qacc": nv,
        "qfrc_inverse": nv,
        "qacc_forward": nv,
        "actuator_force": nu,
        "sensordata": ns,
    }


def check_lengths(records: Sequence[TickRecord], lengths: dict[str, int]) -> None:
    """Raise InvalidArgument naming the column when a present array of `records` has the wrong
    length for its session (`lengths` from `expected_lengths`)."""
    checked = [(name, _GETTERS[name], expected) for name, expected in lengths.items()]
    for position, record in enumerate(records):
        for name, getter, expected in checked:
            array = getter(record)
            if array is not None and len(array) != expected:
                raise InvalidArgument(
                    f"{name} must have {expected} values in every record, got {len(array)} "
                    f"in the record at position {position} of the batch"
                )


def _list_column(name: str, arrays: list[object], expected: int | None) -> pa.Array:
    # pyarrow converts a list of 1-D arrays (or None) in C++, 6-10x faster than assembling offsets
    # and values here (7 against 70 us for a commit of two pendulum records, per column); what it
    # cannot convert, the slow path below explains, naming the column.
    try:
        column = pa.array(arrays, type=FLOAT_LIST)
    except (pa.ArrowInvalid, pa.ArrowTypeError):
        return _list_column_checked(name, arrays, expected)
    if expected is not None and column.null_count < len(column):
        lengths = pc.list_value_length(column).to_numpy(zero_copy_only=False)
        wrong = np.flatnonzero((lengths != expected) & column.is_valid().to_numpy(zero_copy_only=False))
        if wrong.size:
            raise InvalidArgument(
                f"{name} must have {expected} values in every record, got {int(lengths[wrong[0]])} "
                f"in the record at position {int(wrong[0])} of the batch"
            )
    return column


def _list_column_checked(name: str, arrays: list[object], expected: int | None) -> pa.Array:
    n = len(arrays)
    present = [a for a in arrays if a is not None]
    if not present:
        return pa.nulls(n, FLOAT_LIST)
    lengths = np.fromiter((0 if a is None else len(a) for a in arrays), dtype=np.int32, count=n)  # type: ignore[arg-type]
    if expected is not None:
        mask_present = np.fromiter((a is not None for a in arrays), dtype=bool, count=n)
        wrong = np.flatnonzero(mask_present & (lengths != expected))
        if wrong.size:
            raise InvalidArgument(
                f"{name} must have {expected} values in every record, got {int(lengths[wrong[0]])} "
                f"in the record at position {int(wrong[0])} of the batch"
            )
    offsets = np.zeros(n + 1, dtype=np.int32)
    np.cumsum(lengths, out=offsets[1:])
    values = np.concatenate(present).astype(np.float64, copy=False)  # type: ignore[arg-type]
    if values.ndim != 1:
        raise InvalidArgument(f"{name} must hold 1-D vectors, got arrays of {values.ndim} dimensions")
    mask = None
    if len(present) < n:
        mask = pa.array(np.fromiter((a is None for a in arrays), dtype=bool, count=n))
    return pa.ListArray.from_arrays(pa.array(offsets), pa.array(values), type=FLOAT_LIST, mask=mask)


def records_to_batch(
    records: Sequence[TickRecord], *, lengths: dict[str, int] | None = None
) -> pa.RecordBatch:
    """The records as one batch of LOG_SCHEMA; `lengths` (from `expected_lengths`) checks the
    array lengths and raises InvalidArgument naming the column on a mismatch."""
    columns: list[pa.Array] = []
    for f in SCALAR_FIELDS:
        getter = _GETTERS[f.name]
        columns.append(pa.array([getter(r) for r in records], type=f.type))
    for name in ARRAY_FIELDS:
        getter = _GETTERS[name]
        expected = None if lengths is None else lengths.get(name)
        columns.append(_list_column(name, [getter(r) for r in records], expected))
    return pa.RecordBatch.from_arrays(columns, schema=LOG_SCHEMA)


def list_matrix(column: pa.ChunkedArray | pa.Array) -> npt.NDArray[np.float64] | None:
    """(rows, width) of an array column of LOG_SCHEMA, NaN where a row has no array; None when no
    row has one."""
    column = column.combine_chunks() if isinstance(column, pa.ChunkedArray) else column
    lengths = pc.list_value_length(column).fill_null(0).to_numpy(zero_copy_only=False)
    width = int(lengths.max()) if len(lengths) else 0
    if width == 0:
        return None
    out = np.full((len(column), width), np.nan)
    present = np.flatnonzero(lengths == width)
    values = pc.list_flatten(column.take(pa.array(present))).to_numpy(zero_copy_only=False)
    out[present] = values.reshape(len(present), width)
    # Rows of another length (never written by the recorder) are left NaN rather than misplaced.
    return out
