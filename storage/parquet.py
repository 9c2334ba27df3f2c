"""A session's Parquet file: its encodings, its self-describing metadata, and its atomic write.

Floats are stored with BYTE_STREAM_SPLIT under zstd (the bytes of a float column compress far
better split by significance); dictionary encoding is kept for the id and category columns only,
where it pays. The key-value metadata "jitdyn" holds the JSON of `file_metadata`, readable with
`pq.read_schema(path).metadata` or DuckDB's `parquet_kv_metadata`.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any, Final

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from jitdyn.errors import InvalidArgument
from jitdyn.storage.columns import ARRAY_FIELDS, FRAME_SCHEMA, LOG_SCHEMA
from jitdyn.storage.layout import fsync_dir
from jitdyn.storage.records import SessionHeader

__all__ = [
    "METADATA_KEY",
    "ROW_GROUP_BYTES",
    "ROW_GROUP_SIZE",
    "SCHEMA_VERSION",
    "file_metadata",
    "header_from_json",
    "header_to_json",
    "read_metadata",
    "to_frame_table",
    "warm_up",
    "write_parquet",
    "write_parquet_stream",
]

# Bumped when a column is added, removed or changes meaning.
SCHEMA_VERSION: Final = 1
METADATA_KEY: Final = "jitdyn"
ROW_GROUP_SIZE: Final = 100_000

_DICTIONARY_COLUMNS: Final = ["session_id", "model_name", "kind", "source", "reject_reason"]
_FLOAT_SCALARS: Final = [f.name for f in LOG_SCHEMA if f.type == pa.float64()]
_INT_SCALARS: Final = [f.name for f in LOG_SCHEMA if pa.types.is_integer(f.type)]
# BYTE_STREAM_SPLIT cannot be combined with dictionary encoding; none of these columns has it.
_COLUMN_ENCODING: Final = (
    {name: "BYTE_STREAM_SPLIT" for name in _FLOAT_SCALARS}
    | {f"{name}.list.element": "BYTE_STREAM_SPLIT" for name in ARRAY_FIELDS}
    # seq counts up and the timings are small: deltas pack them into a few bits each.
    | {name: "DELTA_BINARY_PACKED" for name in _INT_SCALARS}
)


def warm_up() -> None:
    """Do now what pyarrow does at its first conversion of Python values: where pandas is installed
    it imports it then (0.37-0.44 s of Python here, holding the GIL). A server calls this before it
    serves: in its first session's commit it stalled the loop and held back the session's first
    durable acknowledgement (tests/cluster/test_durable.py waited 40 frames for one in vain)."""
    pa.array([0.0])


def file_metadata(header: SessionHeader) -> dict[str, Any]:
    """What a reader of the Parquet file needs to interpret its columns, as JSON-ready values."""
    return {
        "schema_version": SCHEMA_VERSION,
        "session_id": header.session_id,
        "model_id": header.model_id,
        "model_name": header.model_name,
        "model_version": header.model_version,
        "joint_names": list(header.joint_names),
        "joint_types": list(header.joint_types),
        "qpos_names": list(header.qpos_names),
        "dof_names": list(header.dof_names),
        # Of qpos for hinge and slide joints, of qvel (per second) and qacc (per second squared);
        # generalized forces are N along "m" and N m along "rad".
        "dof_units": list(header.dof_units),
        "actuator_names": list(header.actuator_names),
        "nq": header.nq,
        "nv": header.nv,
        "nu": header.nu,
        "nsensordata": header.nsensordata,
        "timestep": header.timestep,
        "dt": header.dt,
        "scenario": header.scenario,
        "clock": header.clock,
        "estimator": header.estimator,
        "subject_pseudonym": header.subject_pseudonym,
        "subject_attributes": header.subject_attributes,
        "date": header.date,
        "time_origin": "t: client clock, server_time: server clock; seconds since the session start",
    }


def header_to_json(header: SessionHeader) -> str:
    """The whole header as JSON, kept in the log so that recovery can rebuild the Parquet file:
    every field of SessionHeader, tuples as lists and the start as ISO 8601."""

    def plain(value: object) -> object:
        if isinstance(value, _dt.datetime):
            return value.astimezone(_dt.UTC).isoformat()
        return list(value) if isinstance(value, tuple) else value

    return json.dumps({f.name: plain(getattr(header, f.name)) for f in dataclasses.fields(SessionHeader)})


def header_from_json(text: str) -> SessionHeader:
    """The inverse of `header_to_json`; a field with a default may be missing (older logs)."""
    try:
        d = json.loads(text)
        values: dict[str, Any] = {}
        for f in dataclasses.fields(SessionHeader):
            if f.name not in d and f.default is not dataclasses.MISSING:
                continue
            value = d[f.name]
            if f.name == "started_at":
                value = _dt.datetime.fromisoformat(value)
            elif str(f.type).startswith("tuple"):
                value = tuple(value)
            values[f.name] = value
        return SessionHeader(**values)
    except (ValueError, KeyError, TypeError) as exc:
        raise InvalidArgument(f"the session header in the log is not readable: {exc!r}") from exc


def to_frame_table(log: pa.Table, *, session_id: str, model_name: str) -> pa.Table:
    """The log's rows with the constant id columns in front: FRAME_SCHEMA."""
    n = log.num_rows
    zeros = pa.array(np.zeros(n, dtype=np.int32))
    ids = [
        pa.DictionaryArray.from_arrays(zeros, pa.array([value], pa.string()))
        for value in (session_id, model_name)
    ]
    columns = ids + [log.column(name).combine_chunks() for name in LOG_SCHEMA.names]
    return pa.Table.from_arrays(columns, schema=FRAME_SCHEMA)


def write_parquet(table: pa.Table, *, path: Path, metadata: dict[str, Any]) -> None:
    """Write `table` to `path` atomically: a temporary file beside it, fsync, rename, fsync of the
    folder. A reader sees the old file or the whole new one, never a part."""
    write_parquet_stream([table], schema=table.schema, path=path, metadata=metadata)


# A row group is written once this much of it is buffered (or ROW_GROUP_SIZE rows are): what
# compaction holds in memory at most, whatever the session's length.
ROW_GROUP_BYTES: Final = 32 * 1024 * 1024


def write_parquet_stream(
    tables: Iterable[pa.Table], *, schema: pa.Schema, path: Path, metadata: dict[str, Any]
) -> None:
    """`write_parquet` of the concatenation of `tables` (each of `schema`), holding at most one row
    group (ROW_GROUP_SIZE rows or ROW_GROUP_BYTES) in memory."""
    schema = schema.with_metadata({METADATA_KEY: json.dumps(metadata, allow_nan=False)})
    tmp = path.with_name(f".{path.name}.tmp")
    # Readable by the server's user only, whatever the umask (DESIGN: Security and limits).
    with os.fdopen(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600), "wb") as f:
        with pq.ParquetWriter(
            f,
            schema,
            compression="zstd",
            use_dictionary=_DICTIONARY_COLUMNS,
            column_encoding=_COLUMN_ENCODING,
        ) as writer:
            pending: list[pa.Table] = []
            rows = size = 0

            def flush(*, whole: bool) -> None:
                # Full row groups of ROW_GROUP_SIZE rows; the rest waits for more rows unless
                # `whole` (the end, or ROW_GROUP_BYTES buffered).
                nonlocal rows, size
                if not pending:
                    return
                table = pa.concat_tables(pending)
                pending.clear()
                start = 0
                while table.num_rows - start >= ROW_GROUP_SIZE:
                    writer.write_table(table.slice(start, ROW_GROUP_SIZE))
                    start += ROW_GROUP_SIZE
                rest = table.slice(start)
                if whole and rest.num_rows:
                    writer.write_table(rest)
                elif rest.num_rows:
                    pending.append(rest)
                rows = sum(t.num_rows for t in pending)
                size = sum(t.nbytes for t in pending)

            for table in tables:
                pending.append(table.replace_schema_metadata(schema.metadata))
                rows += table.num_rows
                size += table.nbytes
                if rows >= ROW_GROUP_SIZE or size >= ROW_GROUP_BYTES:
                    flush(whole=size >= ROW_GROUP_BYTES)
            flush(whole=True)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    fsync_dir(path.parent)


def read_metadata(path: Path | str, *, filesystem: Any = None) -> dict[str, Any]:
    """The "jitdyn" metadata of a session's Parquet file (on `filesystem`, a pyarrow.fs one, when
    given: a data root's)."""
    raw = (pq.read_schema(path, filesystem=filesystem).metadata or {}).get(METADATA_KEY.encode())
    if raw is None:
        raise InvalidArgument(
            f"{path} has no {METADATA_KEY!r} key-value metadata; it is not a jitdyn session file"
        )
    value: dict[str, Any] = json.loads(raw)
    return value
