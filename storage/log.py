"""A session's append-only log: an Arrow IPC stream written through an unbuffered file.

A killed writer leaves a stream that reads back to its last complete batch (`read_log` stops at a
torn tail), where a Parquet file without its footer could not be read at all. The writer holds an
exclusive flock on the log while the session lives; the kernel drops it when the process dies, so
recovery can tell a live session (locked, maybe by another server sharing the data root) from a
dead one.
"""

from __future__ import annotations

import fcntl
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import pyarrow as pa

from jitdyn.lifecycle import Closeable
from jitdyn.storage.columns import LOG_SCHEMA, conform
from jitdyn.storage.layout import fsync_dir

__all__ = ["HEADER_KEY", "LogContents", "LogStream", "LogWriter", "read_log", "stream_log", "try_lock"]

HEADER_KEY: Final = b"jitdyn.header"


def try_lock(path: Path) -> int | None:
    """A read-only descriptor of `path` holding its exclusive flock, or None when another open
    file holds it (the session is live). Close the descriptor to release the lock."""
    fd = os.open(path, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return None
    except BaseException:
        os.close(fd)
        raise
    return fd


class LogWriter:
    """Writes record batches to a new log file; `write` returns once the batch is on disk.

    Not thread-safe: the recorder's commit thread is its only user.
    """

    def __init__(self, path: Path, *, header_json: str) -> None:
        # O_EXCL: a session id names one log, ever; an existing file is a bug, not something to
        # append to or overwrite.
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        self._file = os.fdopen(fd, "wb", buffering=0)
        self._lock_fd: int | None = None
        try:
            self._lock_fd = try_lock(path)
            if self._lock_fd is None:
                raise FileExistsError(f"{path} is locked by another writer")
            schema = LOG_SCHEMA.with_metadata({HEADER_KEY: header_json.encode()})
            self._writer = pa.ipc.new_stream(self._file, schema)
            # The stream's schema message goes out with the first batch; an empty one makes the
            # header durable before any frame is acknowledged.
            self._writer.write_batch(_empty_batch(schema))
            os.fsync(self._file.fileno())
            fsync_dir(path.parent)
        except BaseException:
            self._release()
            # A log without its header holds nothing to recover; leave no empty file behind.
            path.unlink(missing_ok=True)
            raise
        self.bytes_written = os.fstat(self._file.fileno()).st_size

    def write(self, batch: pa.RecordBatch) -> None:
        """Append `batch` and fsync it (tools and tests; the recorder appends through its committer)."""
        self._writer.write_batch(batch)
        os.fsync(self._file.fileno())

    def fileno(self) -> int:
        """The descriptor the group committer appends serialised batches to: an encapsulated IPC
        message (`RecordBatch.serialize()`) is exactly what the stream writer would write, in one
        write call instead of one per buffer."""
        return self._file.fileno()

    def size(self) -> int:
        """Bytes of the log on disk so far."""
        return os.fstat(self._file.fileno()).st_size if not self._file.closed else self.bytes_written

    def finish(self) -> None:
        """Write the end-of-stream marker and fsync; the lock is kept until `release`."""
        self._writer.close()
        os.fsync(self._file.fileno())
        self.bytes_written = os.fstat(self._file.fileno()).st_size

    def release(self) -> None:
        """Close the file and drop the lock (safe to call twice)."""
        self._release()

    def _release(self) -> None:
        if not self._file.closed:
            self._file.close()
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None


def _empty_batch(schema: pa.Schema) -> pa.RecordBatch:
    return pa.RecordBatch.from_arrays([pa.array([], type=f.type) for f in schema], schema=schema)


@dataclass(frozen=True, slots=True)
class LogContents:
    """What a log holds: its complete batches as one table (LOG_SCHEMA), the header JSON written at
    creation (None when even that did not reach the disk), and whether a torn tail was dropped."""

    table: pa.Table
    header_json: str | None
    torn: bool


def read_log(path: Path) -> LogContents:
    """Read a log back up to its last complete batch."""
    empty = LOG_SCHEMA.empty_table()
    if path.stat().st_size == 0:
        return LogContents(empty, None, torn=False)
    batches: list[pa.RecordBatch] = []
    torn = False
    with pa.memory_map(str(path)) as source:
        try:
            reader = pa.ipc.open_stream(source)
        except (pa.ArrowInvalid, OSError):
            return LogContents(empty, None, torn=True)
        while True:
            try:
                batches.append(reader.read_next_batch())
            except StopIteration:
                break
            except (pa.ArrowInvalid, OSError):
                # The writer died inside this batch: it was never fsynced, never acknowledged.
                torn = True
                break
        metadata = reader.schema.metadata or {}
        # The batches' buffers keep the mapping alive after the file object closes.
        table = pa.Table.from_batches([conform(b) for b in batches], schema=LOG_SCHEMA) if batches else empty
    raw = metadata.get(HEADER_KEY)
    return LogContents(table, raw.decode() if raw is not None else None, torn=torn)


class LogStream(Closeable):
    """A log read batch by batch, in bounded memory: each batch is read into its own buffers and
    freed when dropped (a memory map would keep every page it touched resident until it closes).
    `header_json` (None when even the header did not reach the disk), `batches()` once, then `torn`
    (whether a torn tail was dropped)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.header_json: str | None = None
        self.torn = False
        self._source: pa.OSFile | None = None
        self._reader: pa.ipc.RecordBatchStreamReader | None = None
        if path.stat().st_size == 0:
            return
        self._source = pa.OSFile(str(path))
        try:
            self._reader = pa.ipc.open_stream(self._source)
        except (pa.ArrowInvalid, OSError):
            self.torn = True
            self.close()
            return
        raw = (self._reader.schema.metadata or {}).get(HEADER_KEY)
        self.header_json = raw.decode() if raw is not None else None

    def batches(self) -> Iterator[pa.RecordBatch]:
        """The complete batches, in order, as LOG_SCHEMA."""
        if self._reader is None:
            return
        while True:
            try:
                batch = self._reader.read_next_batch()
            except StopIteration:
                return
            except (pa.ArrowInvalid, OSError):
                # The writer died inside this batch: it was never fsynced, never acknowledged.
                self.torn = True
                return
            if batch.num_rows:
                yield conform(batch)

    def close(self) -> None:
        if self._source is not None:
            self._source.close()
            self._source = None
        self._reader = None


def stream_log(path: Path) -> LogStream:
    """A log to read batch by batch (use as a context manager)."""
    return LogStream(path)
