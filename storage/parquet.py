"""A session's Parquet file: its encodings, its self-describing metadata, and its atomic write
from the session's log (`write_frames`), a row group at a time.

Floats are stored with BYTE_STREAM_SPLIT under zstd (the bytes of a float column compress far
better split by significance); dictionary encoding is kept for the id and category columns only,
where it pays. The key-value metadata "jitdyn" holds the JSON of `file_metadata`, readable with
`pq.read_schema(path).metadata` or DuckDB's `parquet_kv_metadata`.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import datetime as _dt
import json
import os
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, Final

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from jitdyn.errors import InvalidArgument
from jitdyn.storage.columns import ARRAY_FIELDS, FRAME_SCHEMA, ID_COLUMNS, LOG_SCHEMA
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
    "write_frames",
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
    """The log's rows with the constant id columns in front: FRAME_SCHEMA (the log's columns as they
    are chunked, not copied)."""
    zeros = pa.array(np.zeros(log.num_rows, dtype=np.int32))
    ids = [
        pa.DictionaryArray.from_arrays(zeros, pa.array([value], pa.string()))
        for value in (session_id, model_name)
    ]
    return pa.Table.from_arrays(ids + [log.column(name) for name in LOG_SCHEMA.names], schema=FRAME_SCHEMA)


# A row group is written once this much of it is buffered (or ROW_GROUP_SIZE rows are): what
# compaction holds in memory at most, whatever the session's length.
ROW_GROUP_BYTES: Final = 32 * 1024 * 1024

# Runs of small log batches are copied into one chunk of up to this many bytes before a row group is
# converted and written: pyarrow's cost is per chunk and column (~30 us a compute call, a column
# written), and a 20 Hz session's group commits hold a tick or two each.
_CHUNK_BYTES: Final = 4 * 1024 * 1024


@contextlib.contextmanager
def _atomic_writer(path: Path, schema: pa.Schema) -> Iterator[pq.ParquetWriter]:
    """A ParquetWriter of `schema` with the file's encodings, writing a temporary file beside `path`
    that replaces `path` (fsync, rename, fsync of the folder) once the block ends without error. A
    reader sees the old file or the whole new one, never a part."""
    tmp = path.with_name(f".{path.name}.tmp")
    # Readable by the server's user only, whatever the umask (README.md, Security and limits).
    with os.fdopen(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600), "wb") as f:
        with pq.ParquetWriter(
            f,
            schema,
            compression="zstd",
            use_dictionary=_DICTIONARY_COLUMNS,
            column_encoding=_COLUMN_ENCODING,
        ) as writer:
            yield writer
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    fsync_dir(path.parent)


def write_frames(
    batches: Iterable[pa.RecordBatch],
    *,
    header: SessionHeader,
    path: Path,
    on_rows: Callable[[pa.Table], None] | None = None,
    group_rows: int = ROW_GROUP_SIZE,
    group_bytes: int = ROW_GROUP_BYTES,
) -> None:
    """Write a session's log, `batches` of LOG_SCHEMA as a log stream yields them, to `path`
    atomically as FRAME_SCHEMA with `file_metadata(header)`, holding at most one row group in
    memory; every row is given once to `on_rows` (a row group's rows at a time, LOG_SCHEMA) before
    it is written.

    Row groups hold `group_rows` rows, except that once `group_bytes` of frames are buffered, what is
    buffered is written as a shorter one. The frames of a batch count pyarrow's `nbytes` of its rows
    with their id columns."""
    schema = FRAME_SCHEMA.with_metadata({METADATA_KEY: json.dumps(file_metadata(header), allow_nan=False)})
    buffered = _RowGroupBuffer(header, group_bytes=group_bytes)
    with _atomic_writer(path, schema) as writer:

        def write_groups(table: pa.Table, *, whole: bool) -> int:
            # Full row groups of `group_rows` rows, then the rest if `whole`; the rows left unwritten.
            start = 0
            while table.num_rows - start >= group_rows or (whole and start < table.num_rows):
                rows = table.slice(start, group_rows)
                if on_rows is not None:
                    on_rows(rows)
                writer.write_table(
                    to_frame_table(rows, session_id=header.session_id, model_name=header.model_name)
                )
                start += rows.num_rows
            return int(table.num_rows) - start

        for batch in batches:
            buffered.add(batch)
            whole = buffered.full
            if whole or buffered.rows >= group_rows:
                left = write_groups(buffered.take(), whole=whole)
                if left:
                    # Fewer than `group_rows` rows were buffered before this batch: the rows left are
                    # its tail, and wait for more.
                    buffered.add(batch.slice(batch.num_rows - left), exact=True)
        write_groups(buffered.take(), whole=True)


class _RowGroupBuffer:
    """The log batches of the row group being gathered: their rows, and whether their frames reach
    `group_bytes` (why the count is kept and how it is made cheap:
    docs/decisions/0142-compaction-a-row-group-at-a-time.md).

    pyarrow's `nbytes` costs ~150 us a batch here, more than the rest of the compaction of a batch of
    a tick or two, so it is only counted once the batches' IPC sizes reach `group_bytes`. A batch
    decoded from a log references no byte its IPC message does not hold (buffers written whole, a
    validity bitmap only where there are nulls), nor does a column `conform` added."""

    def __init__(self, header: SessionHeader, *, group_bytes: int) -> None:
        self._group_bytes = group_bytes
        # What the id columns add to a batch's frames: the two one-value dictionaries, and an index
        # per row in each.
        empty = to_frame_table(
            LOG_SCHEMA.empty_table(), session_id=header.session_id, model_name=header.model_name
        )
        self._ids_bytes = int(empty.nbytes)
        self._id_row_bytes = sum(int(f.type.index_type.bit_width) // 8 for f in ID_COLUMNS)
        self._batches: collections.deque[tuple[pa.RecordBatch, int]] = collections.deque()  # and bytes
        self.rows = 0
        self._bound = 0  # at least the frames' bytes
        self._bytes: int | None = None  # the frames' bytes, once counted

    @property
    def full(self) -> bool:
        """Whether the frames buffered reach `group_bytes`."""
        return self._bytes is not None and self._bytes >= self._group_bytes

    def _ids(self, batch: pa.RecordBatch) -> int:
        return self._ids_bytes + self._id_row_bytes * int(batch.num_rows)

    def add(self, batch: pa.RecordBatch, *, exact: bool = False) -> None:
        """Gather `batch` (`exact`: count its bytes now; a slice's IPC size may fall short of its
        nbytes by the alignment of its bitmaps)."""
        self.rows += batch.num_rows
        if self._bytes is not None:
            size = int(batch.nbytes)
            self._bytes += size + self._ids(batch)
        else:
            size = int(batch.nbytes) if exact else pa.ipc.get_record_batch_size(batch)
            self._bound += size + self._ids(batch)
        self._batches.append((batch, size))
        if self._bytes is None and self._bound >= self._group_bytes:
            self._bytes = sum(int(b.nbytes) + self._ids(b) for b, _ in self._batches)

    def take(self) -> pa.Table:
        """The buffered rows as one table (LOG_SCHEMA), each run of small batches copied into one
        chunk and freed as soon as it is; nothing is left buffered."""
        pieces: list[pa.Table] = []
        run: list[pa.RecordBatch] = []
        run_bytes = 0
        while self._batches:
            batch, size = self._batches.popleft()
            if run and run_bytes + size > _CHUNK_BYTES:
                pieces.append(_copied(run))
                run_bytes = 0
            run.append(batch)
            run_bytes += size
        if run:
            pieces.append(_copied(run))
        self.rows = self._bound = 0
        self._bytes = None
        return pa.concat_tables(pieces) if pieces else LOG_SCHEMA.empty_table()


def _copied(run: list[pa.RecordBatch]) -> pa.Table:
    """The batches of `run` as one chunk, emptying `run` a batch at a time: freeing hundreds of
    batches in one statement holds the GIL for milliseconds."""
    table = pa.Table.from_batches(run, schema=LOG_SCHEMA).combine_chunks()
    while run:
        run.pop()
    return table


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
