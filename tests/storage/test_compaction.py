"""write_frames, the compaction of a session's log to Parquet, against the plain per-batch writer it
replaced (kept here as the reference): the same rows, schema, metadata, row groups and summary, for
logs of tiny group commits, with row groups cut by rows, by bytes and by both."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from jitdyn.storage.columns import FRAME_SCHEMA, LOG_SCHEMA, STORED_SINCE, records_to_batch
from jitdyn.storage.log import HEADER_KEY, stream_log
from jitdyn.storage.parquet import (
    _COLUMN_ENCODING,  # the reference writes with the file's encodings
    _DICTIONARY_COLUMNS,
    METADATA_KEY,
    ROW_GROUP_BYTES,
    ROW_GROUP_SIZE,
    file_metadata,
    header_to_json,
    write_frames,
)
from jitdyn.storage.records import SessionHeader, SessionSummaryInfo, TickRecord
from jitdyn.storage.summary import Summariser


def reference_write(
    batches: Iterator[pa.RecordBatch],
    *,
    header: SessionHeader,
    path: Path,
    summariser: Summariser,
    group_rows: int,
    group_bytes: int,
) -> None:
    """Each batch summarised and converted on its own, the tables concatenated and cut into row
    groups: `group_rows` rows, or what is buffered once `group_bytes` (their nbytes) are."""
    schema = FRAME_SCHEMA.with_metadata({METADATA_KEY: json.dumps(file_metadata(header), allow_nan=False)})
    with pq.ParquetWriter(
        path, schema, compression="zstd", use_dictionary=_DICTIONARY_COLUMNS, column_encoding=_COLUMN_ENCODING
    ) as writer:
        pending: list[pa.Table] = []
        rows = size = 0

        def flush(*, whole: bool) -> None:
            nonlocal rows, size
            if not pending:
                return
            table = pa.concat_tables(pending)
            pending.clear()
            start = 0
            while table.num_rows - start >= group_rows:
                writer.write_table(table.slice(start, group_rows))
                start += group_rows
            rest = table.slice(start)
            if whole and rest.num_rows:
                writer.write_table(rest)
            elif rest.num_rows:
                pending.append(rest)
            rows = sum(t.num_rows for t in pending)
            size = sum(t.nbytes for t in pending)

        for batch in batches:
            log = pa.Table.from_batches([batch])
            summariser.add(log)
            n = log.num_rows
            ids = [
                pa.DictionaryArray.from_arrays(pa.array(np.zeros(n, dtype=np.int32)), pa.array([value]))
                for value in (header.session_id, header.model_name)
            ]
            columns = ids + [log.column(name).combine_chunks() for name in LOG_SCHEMA.names]
            table = pa.Table.from_arrays(columns, schema=FRAME_SCHEMA).replace_schema_metadata(
                schema.metadata
            )
            pending.append(table)
            rows += table.num_rows
            size += table.nbytes
            if rows >= group_rows or size >= group_bytes:
                flush(whole=size >= group_bytes)
        flush(whole=True)


def write_log(
    path: Path, header: SessionHeader, commits: list[list[TickRecord]], *, older: bool = False
) -> None:
    """A log of these group commits, as the commit thread writes it (without its fsyncs); `older`:
    without the columns stored since the first sessions."""
    schema = pa.schema([f for f in LOG_SCHEMA if not older or f.name not in STORED_SINCE])
    with (
        pa.OSFile(str(path), "wb") as sink,
        pa.ipc.new_stream(
            sink, schema.with_metadata({HEADER_KEY: header_to_json(header).encode()})
        ) as stream,
    ):
        for records in commits:
            batch = records_to_batch(records)
            stream.write_batch(
                pa.RecordBatch.from_arrays([batch.column(f.name) for f in schema], schema=schema)
            )


def commits_of(
    records: list[TickRecord], *, seed: int, most: int, big: int | None = None
) -> list[list[TickRecord]]:
    """The records in group commits of 1 to `most` records, one of `big` records a third of the way."""
    rng = np.random.default_rng(seed)
    commits: list[list[TickRecord]] = []
    i = 0
    while i < len(records):
        n = big if big is not None and len(commits) == 40 else int(rng.integers(1, most + 1))
        commits.append(records[i : i + n])
        i += n
    return commits


def groups(path: Path) -> list[int]:
    metadata = pq.ParquetFile(path).metadata
    return [metadata.row_group(i).num_rows for i in range(metadata.num_row_groups)]


def column_chunks(path: Path) -> list[tuple[object, ...]]:
    metadata = pq.ParquetFile(path).metadata
    return [
        (
            c.path_in_schema,
            c.compression,
            c.encodings,
            c.num_values,
            c.statistics.to_dict() if c.statistics else None,
        )
        for g in range(metadata.num_row_groups)
        for c in (metadata.row_group(g).column(i) for i in range(metadata.num_columns))
    ]


@pytest.mark.parametrize(
    ("ticks", "most", "big", "group_rows", "group_bytes", "older", "row_groups"),
    [
        pytest.param(600, 2, None, ROW_GROUP_SIZE, ROW_GROUP_BYTES, False, 1, id="20 Hz session"),
        pytest.param(1500, 7, 700, 300, ROW_GROUP_BYTES, False, 7, id="cut by rows"),
        pytest.param(1200, 3, None, ROW_GROUP_SIZE, 60_000, False, 12, id="cut by bytes"),
        pytest.param(1500, 9, 500, 250, 120_000, False, 9, id="cut by both"),
        pytest.param(1200, 3, None, ROW_GROUP_SIZE, 60_000, True, 12, id="older log, cut by bytes"),
    ],
)
def test_write_frames_stores_what_the_per_batch_writer_stored(
    tmp_path: Path,
    make_header: Callable[..., SessionHeader],
    make_records: Callable[..., list[TickRecord]],
    ticks: int,
    most: int,
    big: int | None,
    group_rows: int,
    group_bytes: int,
    older: bool,
    row_groups: int,
) -> None:
    header = make_header()
    log = tmp_path / "session.arrows"
    write_log(
        log, header, commits_of(make_records(ticks), seed=ticks + most, most=most, big=big), older=older
    )

    reference, written = tmp_path / "reference.parquet", tmp_path / "written.parquet"
    summaries: list[SessionSummaryInfo] = []
    for path in (reference, written):
        summariser = Summariser(dof_names=header.dof_names)
        with stream_log(log) as stream:
            if path == reference:
                reference_write(
                    stream.batches(),
                    header=header,
                    path=path,
                    summariser=summariser,
                    group_rows=group_rows,
                    group_bytes=group_bytes,
                )
            else:
                write_frames(
                    stream.batches(),
                    header=header,
                    path=path,
                    on_rows=summariser.add,
                    group_rows=group_rows,
                    group_bytes=group_bytes,
                )
        summaries.append(summariser.result())

    assert len(groups(written)) == row_groups, groups(written)
    assert groups(written) == groups(reference)
    assert pq.read_schema(written).equals(pq.read_schema(reference), check_metadata=True)
    assert pq.read_table(written).equals(pq.read_table(reference))
    assert column_chunks(written) == column_chunks(reference)
    assert summaries[1] == summaries[0]
    assert written.read_bytes() == reference.read_bytes()
