"""The crash-safe recorder of one session, and the recovery of sessions a dead server left open.

    with SessionRecorder(data_root=root, index=index, header=header) as recorder:
        recorder.append_result(values)    # a tick's row (a ResultRow), into its columns; cheap
        recorder.append(record)           # a TickRecord (rejected frames, tools)
        result.durable_seq = recorder.durable_seq
        location = recorder.close(summary) # blocking: compaction; run it in a thread

`append` only writes the row into the session's preallocated columns; the process's commit thread
(storage/commit.py, shared by every session) appends what has queued to the session's log and
makes it durable together with the other sessions' rows of the same window (group commit), every
`commit_every` records or `commit_interval` seconds after the first queued one, whichever comes
first (the commit thread widens the window, up to commit.MAX_WINDOW, while its commits carry too
few records to be worth their fixed cost). `close` compacts the
log to Parquet, marks the session ended in the index in one transaction, then deletes the log. On
start, `recover_unfinished` does the same for every session whose server died.

With a shared tier (`shared=`, replicas sharing a PostgreSQL index), the log is the shared tier's
(storage/shared.py) instead of a local file: `durable_seq` then means off this host, a session can
be continued on another replica (`resumed=`), and one whose stream ended without a close is
`park`ed for a resume rather than ended; `finish_orphan` ends one nobody resumed.

With a data root (`root=`, storage/root.py), the Parquet written in the data folder is published
there before the index is told, which then holds its URI (storage/publish.py).
"""

from __future__ import annotations

import enum
import logging
import os
import threading
from collections.abc import Callable
from contextlib import AbstractContextManager
from pathlib import Path
from types import TracebackType
from typing import Any, Self

from jitdyn.errors import FailedPrecondition, InvalidArgument, JitdynError, Unavailable
from jitdyn.storage.buffers import ResultRow
from jitdyn.storage.columns import expected_lengths
from jitdyn.storage.commit import GroupCommitter, default_committer
from jitdyn.storage.failures import STORAGE_ERRORS, storage_failure
from jitdyn.storage.index import SessionIndex, SessionRow
from jitdyn.storage.layout import frames_location, fsync_dir, log_location, make_dirs
from jitdyn.storage.log import LogStream, LogWriter, stream_log, try_lock
from jitdyn.storage.parquet import header_from_json, header_to_json, write_frames
from jitdyn.storage.publish import drop_local_copy, publish_frames, settle_copies
from jitdyn.storage.records import FINAL_STATUSES, SessionHeader, SessionSummaryInfo, TickRecord, stored_word
from jitdyn.storage.root import DataRoot, is_uri
from jitdyn.storage.shared import Fenced, Lease, SharedLogStream, SharedTier, TakenOver
from jitdyn.storage.summary import Summariser
from jitdyn.vocabulary import SessionStatus

__all__ = ["SessionRecorder", "finish_orphan", "publish_unpublished", "recover_unfinished"]

_log = logging.getLogger(__name__)


class _State(enum.Enum):
    OPEN = "open"
    CLOSED = "closed"


def _compact(
    *,
    data_root: Path,
    header: SessionHeader,
    log: LogStream | SharedLogStream,
    summariser: Summariser | None = None,
    epoch: int | None = None,
) -> str:
    """Write the log's rows, read batch by batch in bounded memory, as the session's Parquet file
    (adding them to `summariser`; named for `epoch`, a shared-tier session's); its location
    relative to the data root."""
    location = frames_location(
        model_name=header.model_name, date=header.date, session_id=header.session_id, epoch=epoch
    )
    folder = make_dirs(data_root, str(Path(location).parent))
    write_frames(
        log.batches(),
        header=header,
        path=folder / Path(location).name,
        on_rows=summariser.add if summariser is not None else None,
    )
    return location


def _delete_log(path: Path) -> None:
    path.unlink(missing_ok=True)
    fsync_dir(path.parent)


class SessionRecorder:
    """Records one session: an append-only log while it runs, Parquet and an index row after.

    Creating one creates and fsyncs the log and inserts the index row, and `close` compacts: both
    block on the disk and the database, so call them off the event loop (asyncio.to_thread).

    `durable_seq` is the highest tick seq of a result such that it and every record appended before
    it are on disk. Rejected frames are on disk in the same order but do not advance it: their seq
    is whatever the client sent, and says nothing about the ticks before it.
    """

    def __init__(
        self,
        *,
        data_root: Path,
        index: SessionIndex,
        header: SessionHeader,
        commit_every: int = 64,
        commit_interval: float = 0.010,
        committer: GroupCommitter | None = None,
        shared: SharedTier | None = None,
        resumed: TakenOver | None = None,
        root: DataRoot | None = None,
    ) -> None:
        if resumed is not None and shared is None:
            raise InvalidArgument("a resumed session needs the shared tier (shared=)")
        if commit_every < 1:
            raise InvalidArgument(f"commit_every must be >= 1, got {commit_every}")
        if not commit_interval > 0:
            raise InvalidArgument(f"commit_interval must be > 0 seconds, got {commit_interval}")
        self._data_root = data_root
        self._root = root
        self._index = index
        self._header = header
        self._committer = committer if committer is not None else default_committer()

        # Taken directly by append_result (a Condition's __enter__ is a Python call).
        self._lock = threading.RLock()
        self._cond = threading.Condition(self._lock)
        self._appended = 0
        self._committed = 0
        self._commits = 0
        self._failure: JitdynError | None = None
        self._durable_seq: int | None = None
        self._state = _State.OPEN
        self._location = ""
        self._stored_summary: SessionSummaryInfo | None = None
        self._close_error: BaseException | None = None
        self._shared = shared
        self._resumed = resumed is not None
        self._lease: Lease | None = None
        self._writer: LogWriter | None = None
        self._registered = False
        if shared is not None:
            self._open_shared(shared, resumed, commit_every=commit_every, commit_interval=commit_interval)
            return

        self._log_location = log_location(header.session_id)
        self._log_path = data_root / self._log_location
        try:
            make_dirs(data_root, str(Path(self._log_location).parent))
            # The log (with the header) is durable before the index names it, so an OPEN row always
            # has a log to recover from.
            self._writer = LogWriter(self._log_path, header_json=header_to_json(header))
        except STORAGE_ERRORS as error:
            raise storage_failure(f"session {header.session_id} could not be opened", error) from None
        try:
            index.create(header, log_path=self._log_location)
        except BaseException as error:
            self._writer.release()
            _delete_log(self._log_path)
            if isinstance(error, STORAGE_ERRORS):
                raise storage_failure(f"session {header.session_id} could not be opened", error) from None
            raise
        try:
            self._key = self._committer.register(
                name=header.session_id,
                fd=self._writer.fileno(),
                lengths=expected_lengths(header),
                commit_every=commit_every,
                commit_interval=commit_interval,
                on_durable=self._on_durable,
                on_failure=self._on_failure,
            )
        except BaseException:
            self._state = _State.CLOSED
            self._writer.release()
            self._index.discard(header.session_id)
            _delete_log(self._log_path)
            raise
        self._registered = True

    def _open_shared(
        self, shared: SharedTier, resumed: TakenOver | None, *, commit_every: int, commit_interval: float
    ) -> None:
        header = self._header
        if resumed is not None:
            self._lease = resumed.lease
            self._durable_seq = resumed.durable_seq
        else:
            leases: list[Lease] = []
            try:
                self._index.create(
                    header,
                    log_path="",
                    also=lambda conn: leases.append(
                        shared.create(header, header_json=header_to_json(header), conn=conn)
                    ),
                )
            except STORAGE_ERRORS as error:
                raise storage_failure(f"session {header.session_id} could not be opened", error) from None
            self._lease = leases[0]
        try:
            self._key = self._committer.register(
                name=header.session_id,
                fd=-1,
                lengths=expected_lengths(header),
                commit_every=commit_every,
                commit_interval=commit_interval,
                on_durable=self._on_durable,
                on_failure=self._on_failure,
                lease=self._lease,
            )
        except BaseException:
            self._state = _State.CLOSED
            if resumed is None:
                shared.discard(self._lease)
            raise
        self._registered = True

    @property
    def header(self) -> SessionHeader:
        return self._header

    @property
    def resumable(self) -> bool:
        """Whether another stream may continue this session (its log is in the shared tier)."""
        return self._shared is not None

    @property
    def epoch(self) -> int | None:
        """The lease epoch this recorder holds the session under; None without a shared tier."""
        return None if self._lease is None else self._lease.epoch

    @property
    def stored_summary(self) -> SessionSummaryInfo | None:
        """The summary the index holds, once `close` stored the session: for a resumed session,
        computed from all of its rows (the stream's own counts are only its latest part)."""
        return self._stored_summary

    @property
    def durable_seq(self) -> int | None:
        """The highest result seq durable with everything appended before it; None before any."""
        return self._durable_seq

    @property
    def commits(self) -> int:
        """Group commits (record batches written and fsynced) so far."""
        return self._commits

    @property
    def log_bytes(self) -> int:
        """Bytes of the local log on disk so far (0: the log is the shared tier's)."""
        return self._writer.size() if self._writer is not None else 0

    def append(self, record: TickRecord) -> None:
        """Write a record into the session's columns for the next group commit (rejected frames,
        tools, importers; a tick's result takes `append_result`). Never waits for the disk. The
        record's arrays are held until its window is committed: they must not change meanwhile.

        Raises FailedPrecondition after close; InvalidArgument, naming the column, for a record
        that does not fit the session's columns (a wrong length or type: a bug, which ends the
        recorder as a failed write does); and Unavailable once the log could not be written (the
        session cannot promise durability any more and should end).
        """
        self._append(self._committer.append, record)

    def append_result(self, values: ResultRow) -> None:
        """`append` of a tick's result from its values, without a `TickRecord`: the row is written
        straight into the session's columns (storage/buffers.py `ResultRow` says what each value
        is). Raises as `append` does; a vector that does not fit its column fails the recorder
        when its window is committed."""
        with self._lock:  # `_append`, inlined: this is the tick's path
            if self._state is not _State.OPEN or self._failure is not None:
                self._append(self._committer.append_result, values)  # raises what append raises
                return
            try:
                self._committer.append_result(self._key, values)
            except InvalidArgument as exc:
                self._failure = InvalidArgument(f"session {self._header.session_id}: {exc}")
                self._cond.notify_all()
                raise self._failure from None
            self._appended += 1

    def _append(self, write: Callable[[int, Any], None], values: Any) -> None:
        with self._cond:
            if self._state is not _State.OPEN:
                raise FailedPrecondition(
                    f"the recorder of session {self._header.session_id} is closed; append before close"
                )
            if self._failure is not None:
                raise self._failure
            # Under the recorder's lock, so that `close` cannot unregister in between (the commit
            # thread never takes this lock while holding the committer's: no inversion).
            try:
                write(self._key, values)
            except InvalidArgument as exc:
                self._failure = InvalidArgument(f"session {self._header.session_id}: {exc}")
                self._cond.notify_all()
                raise self._failure from None
            self._appended += 1

    def flush(self, timeout: float | None = None) -> None:
        """Commit what is queued now and wait until it is durable (for tests and shutdown)."""
        with self._cond:
            target = self._appended
        self._committer.request_flush(self._key)
        with self._cond:
            if not self._cond.wait_for(
                lambda: self._committed >= target or self._failure is not None, timeout=timeout
            ):
                raise Unavailable(
                    f"session {self._header.session_id}: the log did not become durable within {timeout} s"
                )
            if self._failure is not None:
                raise self._failure

    def _on_durable(self, records: int, top_seq: int | None) -> None:
        # On the commit thread, once this session's rows of a window are on disk.
        with self._cond:
            self._committed += records
            self._commits += 1
            if top_seq is not None and (self._durable_seq is None or top_seq > self._durable_seq):
                self._durable_seq = top_seq
            self._cond.notify_all()

    def _on_failure(self, failure: JitdynError) -> None:
        with self._cond:
            if self._failure is None:
                self._failure = failure
            self._cond.notify_all()

    def _stop_committing(self) -> None:
        if self._registered:
            self._registered = False
            self._committer.unregister(self._key)

    def close(
        self,
        summary: SessionSummaryInfo | None = None,
        *,
        status: SessionStatus | str = SessionStatus.COMPLETE,
    ) -> str:
        """End the session: commit what is queued, compact the log to Parquet, mark the session
        `status` with `summary` (None: computed from the rows) in one index transaction, delete the
        log. Returns the Parquet location: its URI on the data root (`root=`), else relative to
        the data folder. Blocks for the compaction (and the publish);
        call it off the event loop. A second call returns the same location and does nothing."""
        status = stored_word(SessionStatus, status, argument="status", among=FINAL_STATUSES)
        with self._cond:
            if self._state is _State.CLOSED:
                if self._close_error is not None:
                    raise self._close_error
                return self._location
            self._state = _State.CLOSED
        self._stop_committing()
        try:
            if self._shared is not None:
                return self._close_shared(self._shared, summary, status)
            return self._close_local(summary, status)
        except BaseException as exc:
            self._close_error = exc
            raise

    def _close_local(self, summary: SessionSummaryInfo | None, status: SessionStatus) -> str:
        assert self._writer is not None
        try:
            if self._failure is not None:
                # The log holds what was durable; the session stays OPEN, and the next start
                # recovers it.
                raise self._failure
            self._writer.finish()

            def end(summary: SessionSummaryInfo, location: str) -> None:
                self._index.finish(self._header.session_id, status=status, summary=summary, location=location)
                _delete_log(self._log_path)

            return self._store(stream_log(self._log_path), summary, end)
        finally:
            # Released only now: until the index says the session ended, its lock keeps a
            # recovering server away from it.
            self._writer.release()

    def _close_shared(
        self, shared: SharedTier, summary: SessionSummaryInfo | None, status: SessionStatus
    ) -> str:
        lease = self._lease
        assert lease is not None
        if self._failure is not None:
            # What was committed stays in the shared tier; a resume or a live replica ends it.
            raise self._failure

        def end(summary: SessionSummaryInfo, location: str) -> None:
            pending = self._root is not None and not is_uri(location)
            shared.finish(lease, status=status, summary=summary, location=location, pending_upload=pending)

        # A resumed session's counts on this stream are only its latest part: its summary is
        # computed from all of its rows.
        return self._store(
            shared.stream(self._header.session_id), None if self._resumed else summary, end, epoch=lease.epoch
        )

    def _store(
        self,
        opened_log: AbstractContextManager[LogStream | SharedLogStream],
        summary: SessionSummaryInfo | None,
        end: Callable[[SessionSummaryInfo, str], None],
        *,
        epoch: int | None = None,
    ) -> str:
        """Compact the log to Parquet (summarising its rows when `summary` is None), publish it,
        `end(summary, location)` the session in the index, drop the local copy; returns where the
        Parquet file is stored. A storage error becomes Unavailable naming the session."""
        try:
            summariser = Summariser(dof_names=self._header.dof_names)
            with opened_log as log:
                location = _compact(
                    data_root=self._data_root,
                    header=self._header,
                    log=log,
                    summariser=summariser if summary is None else None,
                    epoch=epoch,
                )
            summary = summariser.result() if summary is None else summary
            stored = publish_frames(self._root, data=self._data_root, relative=location)
            try:
                end(summary, stored)
            except Fenced:
                settle_copies(self._root, relative=location, location=stored, won=False)
                raise
            drop_local_copy(data=self._data_root, relative=location, location=stored)
            settle_copies(self._root, relative=location, location=stored, won=True)
        except STORAGE_ERRORS as error:
            raise storage_failure(f"session {self._header.session_id} could not be stored", error) from None
        self._location, self._stored_summary = stored, summary
        return stored

    def park(self) -> None:
        """The stream ended without a close (its client's connection broke, or this server is
        stopping): commit what is queued and let go of the session, which any replica may resume;
        nobody resuming it within the resume timeout leaves it to be stored as ABANDONED. Blocking.
        Without a shared tier, the session is closed as ABANDONED."""
        if self._shared is None or self._lease is None:
            self.close(status=SessionStatus.ABANDONED)
            return
        with self._cond:
            if self._state is _State.CLOSED:
                return
            self._state = _State.CLOSED
        self._stop_committing()
        if isinstance(self._failure, Fenced):
            return  # another stream holds the session now: nothing is this one's to let go of
        if self._failure is not None:
            raise self._failure
        try:
            self._shared.park(self._lease, ended_as=SessionStatus.ABANDONED)
        except STORAGE_ERRORS as error:
            # Its lease runs out by itself: a live replica ends it as RECOVERED.
            raise storage_failure(f"session {self._header.session_id} could not be parked", error) from None

    def discard(self) -> None:
        """Undo a session that was never served (its open failed, or its client left before
        `opened`): no log, no index row remain. Safe after close, and twice."""
        with self._cond:
            if self._state is _State.CLOSED:
                return
            self._state = _State.CLOSED
        self._stop_committing()
        if self._shared is not None and self._lease is not None:
            if self._resumed:
                # Not this stream's to undo: the session lives on for another resume.
                self._shared.park(self._lease, ended_as=SessionStatus.RECOVERED)
            else:
                self._shared.discard(self._lease)
            return
        assert self._writer is not None
        try:
            self._index.discard(self._header.session_id)
        finally:
            self._writer.release()
            _delete_log(self._log_path)

    def fail(self, summary: SessionSummaryInfo | None = None) -> str:
        """`close` with status FAILED: the session ended by an error; what was received is kept."""
        return self.close(summary, status=SessionStatus.FAILED)

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._state is _State.CLOSED:
            return
        if exc_type is None:
            self.close()
        else:
            self.fail()


def _recover_one(*, data_root: Path, index: SessionIndex, row: SessionRow, root: DataRoot | None) -> bool:
    path = data_root / row.log_path
    fd = try_lock(path)
    if fd is None:
        _log.info("session %s is open in a live server; left alone", row.session_id)
        return False
    try:
        with stream_log(path) as log:
            if log.header_json is None:
                # The log died before its header was durable; no frame was acknowledged, and the
                # index row, written after, cannot exist. Kept for a human to look at.
                _log.warning("session %s: log %s has no header; not recovered", row.session_id, path)
                return False
            header = header_from_json(log.header_json)
            summariser = Summariser(dof_names=header.dof_names)
            location = _compact(data_root=data_root, header=header, log=log, summariser=summariser)
            if log.torn:
                _log.info("session %s: dropped a torn last batch (never acknowledged)", row.session_id)
        summary = summariser.result()
        stored = publish_frames(root, data=data_root, relative=location)
        index.finish(row.session_id, status=SessionStatus.RECOVERED, summary=summary, location=stored)
        _delete_log(path)
        drop_local_copy(data=data_root, relative=location, location=stored)
        return True
    finally:
        os.close(fd)


def recover_unfinished(*, data_root: Path, index: SessionIndex, root: DataRoot | None = None) -> list[str]:
    """Compact every OPEN session whose log is here and not held by a live writer to Parquet, and
    mark it RECOVERED with a summary computed from its rows (published to `root`, when given).
    Returns the recovered session ids.

    A session whose log is missing is left OPEN with a warning: its log may be on another server's
    data root. A session another server recovers at the same moment is skipped.
    """
    recovered: list[str] = []
    for row in index.unfinished():
        if not row.log_path:
            continue  # its log is the shared tier's: a live replica ends it (finish_orphan)
        path = data_root / row.log_path
        if not path.is_file():
            _log.warning(
                "session %s is OPEN but its log %s is not under %s", row.session_id, row.log_path, data_root
            )
            continue
        try:
            if _recover_one(data_root=data_root, index=index, row=row, root=root):
                recovered.append(row.session_id)
        except (FailedPrecondition, FileNotFoundError):
            _log.info("session %s was ended by another server meanwhile", row.session_id)
    return recovered


def finish_orphan(
    *, data_root: Path, shared: SharedTier, taken: TakenOver, root: DataRoot | None = None
) -> str:
    """End a session of the shared tier that nobody resumed (taken over by `SharedTier.claim_orphan`):
    its shared log compacted to Parquet under `data_root`, the index row ended as the lease says
    (RECOVERED: its server died; ABANDONED: its stream ended without a close). Blocking."""
    header = header_from_json(taken.header_json)
    summariser = Summariser(dof_names=header.dof_names)
    with shared.stream(header.session_id) as log:
        location = _compact(
            data_root=data_root, header=header, log=log, summariser=summariser, epoch=taken.lease.epoch
        )
    stored = publish_frames(root, data=data_root, relative=location)
    try:
        shared.finish(
            taken.lease,
            status=taken.ended_as,
            summary=summariser.result(),
            location=stored,
            pending_upload=root is not None and not is_uri(stored),
        )
    except Fenced:
        settle_copies(root, relative=location, location=stored, won=False)
        raise
    drop_local_copy(data=data_root, relative=location, location=stored)
    settle_copies(root, relative=location, location=stored, won=True)
    return stored


def publish_unpublished(*, data_root: Path, shared: SharedTier, root: DataRoot) -> str | None:
    """Publish one ended session whose Parquet never reached `root` and whose replica let it be
    (`SharedTier.claim_unpublished`): compacted again from its shared log, uploaded, the index
    pointed at it, the log let go. Its id, or None when none waits. Blocking; a failed upload
    raises and leaves the session to the next try, once this hold runs out."""
    claimed = shared.claim_unpublished()
    if claimed is None:
        return None
    header = header_from_json(claimed.header_json)
    with shared.stream(header.session_id) as log:
        location = _compact(data_root=data_root, header=header, log=log, epoch=claimed.lease.epoch)
    uri = root.publish(data_root / location, location)
    won = shared.published(header.session_id, old=claimed.location, new=uri)
    if won:
        _log.warning(
            "session %s: published to the data root from the shared log (%s)", header.session_id, uri
        )
    settle_copies(root, relative=location, location=uri, won=won)
    (data_root / location).unlink(missing_ok=True)
    return header.session_id
