"""Group commit across sessions: one commit thread and one flush to disk per commit window for every
session a process records, as a database's write-ahead log does.

A session's ticks come `dt` apart (50 ms at 20 Hz), so a per-session commit thread had nothing to
group: each tick cost an Arrow batch of one row, a thread wake-up and an fsync. Here each row is
written, as it is appended, into its session's preallocated columns (storage/buffers.py); when a
session's window is due the thread takes every session that has rows, swaps their columns for
their spare ones (the tick never waits for a write), appends each to its session's own log as one
Arrow batch that views them, in one write, and one `syncfs` makes every log durable (one `fsync`
when a single log has new rows). Each session keeps its own log, so recovery, compaction and the
per-log flock are unchanged. Why the columns, and why every session's rows share each commit:
docs/decisions/0221-the-columns-pay-at-a-servers-load.md.

With a shared tier (replicas sharing a PostgreSQL index, storage/shared.py), a session's rows go
instead to the shared log: one transaction per window for every such session of the process, which
also renews their leases and refuses the rows of a session another replica took over (fencing).
While the database cannot be reached, the rows wait and are committed when it answers again
(durable_seq does not move meanwhile; answers go on), up to SHARED_OUTAGE_LIMIT.

    committer = GroupCommitter()                    # one per process (Services owns it)
    recorder = SessionRecorder(..., committer=committer)
    ...
    committer.close()
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final

import pyarrow as pa

from jitdyn.errors import InvalidArgument, JitdynError, Unavailable
from jitdyn.lifecycle import Closeable
from jitdyn.storage.buffers import INITIAL_ROWS, ResultRow, WindowRows
from jitdyn.storage.failures import STORAGE_ERRORS, storage_failure
from jitdyn.storage.records import TickRecord
from jitdyn.storage.shared import Fenced, Lease, SharedTier, Window

__all__ = [
    "COMMIT_SHARE",
    "MAX_WINDOW",
    "RENEW_DEADLINE_SHARE",
    "SHARED_OUTAGE_LIMIT",
    "CommitStats",
    "GroupCommitter",
    "default_committer",
]

# A commit costs about the same whatever it carries, so the window widens until the commit thread
# (its wake-ups and scans included) costs at most COMMIT_SHARE of a core, and never past
# MAX_WINDOW, which bounds how far durable_seq trails the newest answer (the measurements:
# docs/decisions/0040-group-commit-window.md, 0221-the-columns-pay-at-a-servers-load.md).
COMMIT_SHARE: Final = 0.01
MAX_WINDOW: Final = 0.1  # s
_COST_EWMA: Final = 0.2
# While the shared tier does not answer, a commit is retried this often (s), and the sessions
# waiting on it fail (UNAVAILABLE) once it has not answered for SHARED_OUTAGE_LIMIT (s).
_SHARED_RETRY: Final = 0.5
SHARED_OUTAGE_LIMIT: Final = 120.0
# A process whose leases were last renewed longer ago than this share of the TTL steps down: its
# sessions are told to move (Kubernetes' leader election: a renew deadline shorter than the lease).
RENEW_DEADLINE_SHARE: Final = 2 / 3

_log = logging.getLogger(__name__)

_libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
_syncfs: Final = getattr(_libc, "syncfs", None)


def _sync_all(fds: list[int]) -> None:
    """Make everything written to `fds` durable: one fsync for one file, else one syncfs of the
    file system they are on (Linux), else an fsync each."""
    if len(fds) == 1 or _syncfs is None:
        for fd in fds:
            os.fsync(fd)
        return
    if _syncfs(fds[0]) != 0:
        error = ctypes.get_errno()
        raise OSError(error, os.strerror(error))


@dataclass(frozen=True, slots=True)
class _Held:
    """Rows of a window the shared tier did not take, serialised: retried as they were, under the
    same key, never merged with newer rows."""

    data: bytes
    rows: int
    top_seq: int | None


@dataclass(frozen=True, slots=True)
class _Taken:
    """One session's rows of a window, as the thread wrote them."""

    rows: int
    top_seq: int | None


@dataclass
class _Session:
    """One registered log: where its rows go and what the recorder wants to know."""

    name: str
    fd: int  # -1: a session of the shared tier
    commit_every: int
    commit_interval: float
    on_durable: Callable[[int, int | None], None]  # (records committed, highest result seq)
    on_failure: Callable[[JitdynError], None]
    # The rows appended since the last take; `spare` is the other half of the double buffer, None
    # while the thread writes it.
    window: WindowRows
    spare: WindowRows | None = None
    # A window the shared tier did not take (it may have landed): the next take is this alone.
    held: _Held | None = None
    first_pending_at: float = 0.0
    flush: bool = False
    in_flight: bool = False  # taken by the thread, not yet durable
    failed: bool = False
    bytes_written: int = 0
    lease: Lease | None = None  # its log is the shared tier's, under this lease
    retry_at: float = 0.0  # the shared tier did not answer: not due before then (monotonic s)
    committed: int = 0  # records of a shared-tier session in windows the database took

    @property
    def pending(self) -> bool:
        return self.window.rows > 0 or self.held is not None

    def due(self, now: float, window: float) -> bool:
        return (
            self.pending
            and now >= self.retry_at
            and (
                self.flush
                or self.window.rows >= self.commit_every
                or now >= self.first_pending_at + max(self.commit_interval, window)
            )
        )

    def next_due(self, window: float) -> float:
        return max(self.retry_at, self.first_pending_at + max(self.commit_interval, window))


@dataclass(frozen=True)
class CommitStats:
    """Counters of a committer, for metrics and benchmarks."""

    commits: int  # windows written and made durable
    records: int
    syncs: int
    sessions: int  # logs registered now
    cpu_seconds: float  # the commit thread's CPU, writing and syncing
    window: float  # s: the least commit window now, widened to keep commits under COMMIT_SHARE
    errors: int = 0  # windows the storage did not take (a write or sync failed, the index did not answer)
    fenced: int = 0  # sessions whose writes were refused: another stream took them over


class GroupCommitter(Closeable):
    """The commit thread of a process. Thread-safe; `close` is safe to call twice."""

    def __init__(self, *, name: str = "jitdyn-commit", shared: SharedTier | None = None) -> None:
        self._shared = shared
        # When the last renewal that succeeded began (monotonic s): a failed one leaves it, so the
        # leases' standing is never overstated; the next try waits _SHARED_RETRY.
        self._renewed_at = time.monotonic()
        self._renew_retry_at = 0.0
        self._outage_since: float | None = None
        # The condition's own lock, taken directly where an append takes it: a Condition's
        # __enter__ and __exit__ are Python calls, cold microseconds on the tick's path.
        self._lock = threading.RLock()
        self._cond = threading.Condition(self._lock)
        self._sessions: dict[int, _Session] = {}
        self._next_key = 0
        self._stopping = False
        self._commits = 0
        self._records = 0
        self._syncs = 0
        self._cpu = 0.0
        self._errors = 0
        self._fenced = 0
        self._commit_cost = 0.0  # s of this thread's CPU per commit, a moving average
        self._wake_at = -math.inf  # when the waiting thread wakes by itself (monotonic s); -inf: awake
        self._window = 0.0  # s, the least window of every log: _commit_cost / COMMIT_SHARE
        self._thread = threading.Thread(target=self._run_guarded, name=name, daemon=True)
        self._thread.start()

    # Registration, from the recorders.

    def register(
        self,
        *,
        name: str,
        fd: int,
        lengths: dict[str, int],
        commit_every: int,
        commit_interval: float,
        on_durable: Callable[[int, int | None], None],
        on_failure: Callable[[JitdynError], None],
        lease: Lease | None = None,
    ) -> int:
        """Add a log open for appending on `fd`, or (`lease`, fd -1) a session of the shared tier;
        returns the key `append`, `flush` and `unregister` take."""
        if lease is not None and self._shared is None:
            raise InvalidArgument("a session of the shared tier needs a committer made with shared=")
        with self._cond:
            if self._stopping:
                raise Unavailable("the commit thread is stopped; the server is shutting down")
            if lease is not None and not any(s.lease for s in self._sessions.values()):
                self._renewed_at = time.monotonic()  # the lease was made (or taken) just now
            key = self._next_key
            self._next_key += 1
            window = WindowRows(lengths=lengths, capacity=min(commit_every, INITIAL_ROWS))
            self._sessions[key] = _Session(
                name=name,
                fd=fd,
                commit_every=commit_every,
                commit_interval=commit_interval,
                on_durable=on_durable,
                on_failure=on_failure,
                window=window,
                spare=window.spare(),
                lease=lease,
            )
            return key

    def append(self, key: int, record: TickRecord) -> None:
        """Write `record` into the columns of log `key`'s window. Never waits for the disk.

        InvalidArgument, naming the column, when the record does not fit the log's columns; it is
        then not stored."""
        with self._cond:
            session = self._sessions[key]
            session.window.append(record)
            self._appended(session)

    def append_result(self, key: int, values: ResultRow) -> None:
        """Write a tick's result into the columns of log `key`'s window, from its values as
        `WindowRows.append_result` takes them (no `TickRecord`). Never waits for the disk."""
        with self._lock:
            session = self._sessions[key]
            window = session.window
            window.append_result(values)
            # `_appended`, inlined: this is the tick's path.
            rows = window.rows
            if rows == 1 and session.held is None:
                session.first_pending_at = now = time.monotonic()
                if now + max(session.commit_interval, self._window) < self._wake_at:
                    self._cond.notify()
            elif rows >= session.commit_every:
                self._cond.notify()

    def _appended(self, session: _Session) -> None:
        rows = session.window.rows
        if rows == 1 and session.held is None:
            session.first_pending_at = now = time.monotonic()
            # The thread already wakes by then for another log's window: no need to wake it
            # now (a notify per record was 3 % of the event loop's time at 8 sessions).
            if now + max(session.commit_interval, self._window) < self._wake_at:
                self._cond.notify()
        elif rows >= session.commit_every:
            self._cond.notify()

    def request_flush(self, key: int) -> None:
        """Commit what log `key` has queued now, without waiting for its window."""
        with self._cond:
            session = self._sessions.get(key)
            if session is not None and session.pending:
                session.flush = True
                self._cond.notify()

    def unregister(self, key: int) -> None:
        """Commit what log `key` has queued and forget it (its recorder is closing)."""
        with self._cond:
            session = self._sessions.get(key)
            if session is None:
                return
            session.flush = True
            self._cond.notify_all()
            self._cond.wait_for(
                lambda: (
                    (not session.pending and not session.in_flight)
                    or session.failed
                    or not self._thread.is_alive()
                )
            )
            del self._sessions[key]

    def stats(self) -> CommitStats:
        with self._cond:
            return CommitStats(
                commits=self._commits,
                records=self._records,
                syncs=self._syncs,
                sessions=len(self._sessions),
                cpu_seconds=self._cpu,
                window=self._window,
                errors=self._errors,
                fenced=self._fenced,
            )

    def close(self) -> None:
        """Commit everything queued and stop the thread."""
        with self._cond:
            self._stopping = True
            for session in self._sessions.values():
                session.flush = True
            self._cond.notify_all()
        self._thread.join()

    # The thread.

    def _take_due(self) -> list[tuple[_Session, WindowRows | None, _Held | None]] | None:
        """Wait until some log is due; take its rows, and those of every other log that has any
        (they share the flush: the next commit is then a whole window away), swapping in their
        spare columns; or a window the shared
        tier did not take, alone. None when stopping with nothing left."""
        with self._cond:
            while True:
                now = time.monotonic()
                window = self._window
                due = [s for s in self._sessions.values() if not s.failed and s.due(now, window)]
                if due:
                    break
                if self._stopping and not any(s.pending for s in self._sessions.values() if not s.failed):
                    return None
                waiting = [s.next_due(window) for s in self._sessions.values() if s.pending and not s.failed]
                if not waiting and self._sessions:
                    # Nothing queued: wake in a window rather than be woken by the next row. A row
                    # appended meanwhile is due no sooner, and its tick pays no notify (each commit
                    # empties every log, so every commit's first row would).
                    waiting.append(now + max(window, min(s.commit_interval for s in self._sessions.values())))
                if self._shared is not None and any(s.lease for s in self._sessions.values()):
                    renew_at = max(self._renewed_at + self._shared.lease_ttl / 3, self._renew_retry_at)
                    if now >= renew_at:
                        return []  # the leases are renewed by the thread, outside the lock
                    waiting.append(renew_at)
                self._wake_at = min(waiting) if waiting else math.inf
                self._cond.wait(None if not waiting else max(0.0, self._wake_at - now))
                self._wake_at = -math.inf  # awake: it rescans every log before it waits again
            chosen = set(map(id, due))
            for s in self._sessions.values():
                if id(s) not in chosen and s.pending and not s.failed and now >= s.retry_at:
                    due.append(s)
            taken: list[tuple[_Session, WindowRows | None, _Held | None]] = []
            for s in due:
                if s.held is not None:
                    taken.append((s, None, s.held))
                    s.held = None
                    s.flush = s.window.rows > 0
                else:
                    taken.append((s, s.window, None))
                    s.window = s.spare if s.spare is not None else s.window.spare()
                    s.spare = None
                    s.flush = False
                s.in_flight = True
            return taken

    def _run(self) -> None:
        # A commit's cost is the thread's CPU from the end of the last one: its wake-ups and scans
        # while the window fills count, as its fsync and write do.
        cpu_started = time.thread_time()
        while True:
            taken = self._take_due()
            if taken is None:
                return
            written = self._write(taken)
            local = [(s, t) for s, t, _ in written if s.lease is None]
            durable: list[tuple[_Session, _Taken]] = []
            if local:
                try:
                    _sync_all([s.fd for s, _ in local])
                except OSError as exc:
                    self._count_error()
                    for s, _ in local:
                        self._fail(
                            s, storage_failure(f"session {s.name}: its log cannot be made durable", exc)
                        )
                else:
                    durable = local
            durable.extend(self._commit_shared([(s, t, d) for s, t, d in written if s.lease is not None]))
            if self._shared is not None and self._renew_due(time.monotonic()):
                self._renew_leases()
            with self._cond:
                self._commits += 1 if durable else 0
                self._syncs += 1 if durable else 0
                self._records += sum(t.rows for _, t in durable)
            for s, t in durable:
                s.on_durable(t.rows, t.top_seq)
            with self._cond:
                for s, rows, _ in taken:
                    if rows is not None:
                        # Its batch is serialised and written: the columns are the spare half now.
                        rows.clear()
                        s.spare = rows
                    s.in_flight = False
                cpu_now = time.thread_time()
                cost, cpu_started = cpu_now - cpu_started, cpu_now
                self._cpu += cost
                self._commit_cost += _COST_EWMA * (cost - self._commit_cost)
                self._window = min(MAX_WINDOW, self._commit_cost / COMMIT_SHARE)
                self._cond.notify_all()

    def _commit_shared(self, written: list[tuple[_Session, _Taken, bytes]]) -> list[tuple[_Session, _Taken]]:
        """One transaction for every shared-tier session's rows of this window: the durable ones.
        Rows the database did not take are held by their sessions, serialised, for the next try."""
        if not written or self._shared is None:
            return []
        windows = []
        for s, t, data in written:
            assert s.lease is not None
            windows.append(Window(s.lease, t.top_seq, data, first=s.committed))
        try:
            fenced = self._shared.commit(windows)
        except STORAGE_ERRORS as exc:
            self._count_error()
            now = time.monotonic()
            if self._outage_since is None:
                self._outage_since = now
                _log.warning("the shared tier does not answer; %d sessions' rows wait: %s", len(written), exc)
            if now - self._outage_since > SHARED_OUTAGE_LIMIT:
                for s, _, _ in written:
                    self._fail(s, storage_failure(f"session {s.name}: the shared tier is unreachable", exc))
                return []
            with self._cond:
                for s, t, data in written:
                    if not s.failed:
                        s.held = _Held(data, t.rows, t.top_seq)
                        s.first_pending_at = now
                        s.retry_at = now + _SHARED_RETRY
            return []
        if self._outage_since is not None:
            _log.warning("the shared tier answers again after %.1f s", time.monotonic() - self._outage_since)
            self._outage_since = None
        durable = []
        for s, t, _ in written:
            if s.name in fenced:
                self._fail(
                    s,
                    Fenced(
                        f"session {s.name} was taken over by another stream (a resume); this one ends, resume it"
                    ),
                )
            else:
                s.committed += t.rows
                durable.append((s, t))
        return durable

    def lease_lost(self) -> bool:
        """Whether this process holds leases it has not renewed within the renew deadline (the
        index did not answer): its sessions should move to a replica that can hold them."""
        if self._shared is None:
            return False
        with self._cond:
            held = any(s.lease is not None and not s.failed for s in self._sessions.values())
        deadline = RENEW_DEADLINE_SHARE * self._shared.lease_ttl
        return held and time.monotonic() - self._renewed_at > deadline

    def _renew_due(self, now: float) -> bool:
        ttl = self._shared.lease_ttl if self._shared is not None else math.inf
        return now - self._renewed_at >= ttl / 3 and now >= self._renew_retry_at

    def _renew_leases(self) -> None:
        """Extend the leases of every shared-tier session, those that committed nothing lately too."""
        if self._shared is None:
            return
        with self._cond:
            held = [(s, s.lease) for s in self._sessions.values() if s.lease is not None and not s.failed]
        started = time.monotonic()
        try:
            fenced = self._shared.renew([lease for _, lease in held if lease is not None])
        except STORAGE_ERRORS as exc:
            self._renew_retry_at = time.monotonic() + _SHARED_RETRY
            _log.warning("the shared tier does not answer; leases not renewed: %s", exc)
            return
        self._renewed_at = started
        for s, _ in held:
            if s.name in fenced:
                self._fail(
                    s,
                    Fenced(
                        f"session {s.name} was taken over by another stream (a resume); this one ends, resume it"
                    ),
                )

    def _write(
        self, taken: list[tuple[_Session, WindowRows | None, _Held | None]]
    ) -> list[tuple[_Session, _Taken, bytes]]:
        """Append each session's rows to its log (a local one: written, not yet synced; a shared
        one: serialised for `_commit_shared`); the sessions whose rows are, and what they carry."""
        written = []
        for s, rows, held in taken:
            one = self._write_one(s, rows, held)
            if one is not None:
                written.append(one)
        return written

    def _write_one(
        self, s: _Session, rows: WindowRows | None, held: _Held | None
    ) -> tuple[_Session, _Taken, bytes] | None:
        if held is not None:
            return s, _Taken(held.rows, held.top_seq), held.data
        assert rows is not None
        taken = _Taken(rows.rows, rows.top_seq)
        if taken.rows == 0:
            return None
        try:
            data = rows.batch().serialize()
        except InvalidArgument as exc:  # a vector that does not fit its column, named
            self._fail(s, InvalidArgument(f"session {s.name}: {exc}"))
            return None
        except (TypeError, ValueError, pa.ArrowException) as exc:
            self._fail(s, InvalidArgument(f"session {s.name}: a record cannot be stored: {exc}"))
            return None
        if s.lease is not None:
            return s, taken, data.to_pybytes()
        try:
            written = os.write(s.fd, data)
            if written != data.size:
                raise OSError(f"short write: {written} of {data.size} bytes")
        except OSError as exc:
            self._count_error()
            self._fail(s, storage_failure(f"session {s.name}: its log cannot be written", exc))
            return None
        s.bytes_written += data.size
        return s, taken, b""

    def _count_error(self) -> None:
        with self._cond:
            self._errors += 1

    def _fail(self, s: _Session, failure: JitdynError) -> None:
        _log.error("%s", failure)
        with self._cond:
            s.failed = True
            s.window.clear()
            s.held = None
            self._fenced += isinstance(failure, Fenced)
        s.on_failure(failure)

    def _run_guarded(self) -> None:
        try:
            self._run()
        except Exception as exc:  # noqa: BLE001 - any bug here must reach the recorders, not hang them
            _log.exception("the commit thread died")
            with self._cond:
                sessions = list(self._sessions.values())
            for s in sessions:
                s.on_failure(Unavailable(f"session {s.name}: the commit thread died: {exc!r}"))
            with self._cond:
                self._cond.notify_all()


_default: GroupCommitter | None = None
_default_lock = threading.Lock()


def default_committer() -> GroupCommitter:
    """The process's shared committer, for recorders made without one (tools, tests)."""
    global _default
    with _default_lock:
        if _default is None or not _default._thread.is_alive():
            _default = GroupCommitter(name="jitdyn-commit-default")
        return _default
