"""The shared tier of replicas that share a PostgreSQL index: each open session's lease (owner,
epoch, expiry) and its log, one row per commit window, so that an acknowledged frame survives the
loss of the replica that answered it (why PostgreSQL and not the object store:
docs/decisions/0120-durable-off-the-host.md).

    tier = SharedTier(engine, owner=new_owner_id(), lease_ttl=10.0)
    lease = tier.create(header)                 # epoch 1, owned by this process
    fenced = tier.commit([Window(lease, top_seq, data, first=0)])   # one transaction for all sessions
    taken = tier.take_over(session_id, tenant=t, token_epoch=e)  # a resume elsewhere: epoch + 1

Every write names the epoch it holds; one made under an older epoch changes nothing and is
reported fenced, so a replica cut off and back cannot write to a session another has taken over.
"""

from __future__ import annotations

import datetime as _dt
import uuid
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Final

import pyarrow as pa
import sqlalchemy as sa
from sqlalchemy.dialects import postgresql

from jitdyn.errors import NotFound, PermissionDenied, Unavailable
from jitdyn.lifecycle import Closeable
from jitdyn.storage.columns import LOG_SCHEMA, STORED_SINCE, conform
from jitdyn.storage.index import finish_session, move_location
from jitdyn.storage.records import SessionHeader, SessionSummaryInfo
from jitdyn.storage.schema import session_leases, session_log, sessions
from jitdyn.vocabulary import SessionStatus

__all__ = [
    "Fenced",
    "Lease",
    "SharedLogStream",
    "SharedTier",
    "TakenOver",
    "Unpublished",
    "Window",
    "new_owner_id",
]

# The log rows of one session read per query while compacting (bounded memory).
_READ_PAGE: Final = 256


def _read_batch(data: bytes) -> pa.RecordBatch:
    """A row's batch as LOG_SCHEMA; one written before the newest columns were stored has the
    schema without them (an IPC batch does not carry its schema)."""
    try:
        return pa.ipc.read_record_batch(pa.py_buffer(data), LOG_SCHEMA)
    except (OSError, pa.ArrowInvalid):
        older = pa.schema([f for f in LOG_SCHEMA if f.name not in STORED_SINCE])
        return conform(pa.ipc.read_record_batch(pa.py_buffer(data), older))


class Fenced(Unavailable):
    """A write under an epoch that is no longer the session's: another replica took it over. It
    travels as UNAVAILABLE, which the SDK resumes: the session lives on with its new holder."""


def new_owner_id() -> str:
    """A random id for this server process's leases: never a host name (nothing stored names a host)."""
    return uuid.uuid4().hex


@dataclass(frozen=True, slots=True)
class Lease:
    """A session held under `epoch` by this process."""

    session_id: str
    epoch: int


@dataclass(frozen=True, slots=True)
class TakenOver:
    """A session taken over: its new lease, the header it was opened with, and how far it is stored."""

    lease: Lease
    header_json: str
    durable_seq: int | None
    ended_as: SessionStatus


@dataclass(frozen=True, slots=True)
class Unpublished:
    """An ended session whose Parquet is not on the data root yet, held for publishing from its
    shared log: its lease, the header it was opened with, and the location the index holds."""

    lease: Lease
    header_json: str
    location: str


@dataclass(frozen=True, slots=True)
class Window:
    """One session's rows of a commit window: an encapsulated Arrow IPC record batch (LOG_SCHEMA),
    the highest result seq among them (None: only rejections), and how many records of the
    session's stream under this lease came before them (the window's key: retried, it is stored
    once)."""

    lease: Lease
    top_seq: int | None
    data: bytes
    first: int


def _seconds(value: float) -> sa.ColumnElement[_dt.timedelta]:
    return sa.type_coerce(sa.cast(value, sa.Float) * sa.literal_column("interval '1 second'"), sa.Interval())


# Expiry is judged on one clock, PostgreSQL's (the transaction's start), never on a replica's: a host
# whose clock is off neither takes live sessions nor keeps dead ones.
_NOW: Final = sa.func.now()


def _is_open(c: sa.ColumnClause[str] | sa.Column[str]) -> sa.ColumnElement[bool]:
    """The lease's session is still OPEN in the index (not ended and waiting for its upload)."""
    return sa.exists().where(sessions.c.session_id == c, sessions.c.status == SessionStatus.OPEN.value)


class SharedTier:
    """Leases and logs in the index database. Thread-safe (a connection per call)."""

    def __init__(self, engine: sa.Engine, *, owner: str, lease_ttl: float) -> None:
        self.engine = engine
        self.owner = owner
        self.lease_ttl = lease_ttl

    def _expiry(self) -> sa.ColumnElement[_dt.datetime]:
        return _NOW + _seconds(self.lease_ttl)

    def create(self, header: SessionHeader, *, header_json: str, conn: sa.Connection) -> Lease:
        """The lease of a new session, epoch 1, in the caller's transaction (the index row's)."""
        conn.execute(
            sa.insert(session_leases).values(
                session_id=header.session_id,
                tenant=header.tenant,
                owner=self.owner,
                epoch=1,
                expires_at=self._expiry(),
                durable_seq=None,
                header_json=header_json,
                ended_as=SessionStatus.RECOVERED.value,
            )
        )
        return Lease(header.session_id, 1)

    def commit(self, windows: Sequence[Window]) -> set[str]:
        """Append every session's window to its log and renew its lease, in one transaction; the
        sessions whose epoch is no longer theirs are left out and returned (fenced)."""
        if not windows:
            return set()
        leases = session_leases.c
        values = sa.values(
            sa.column("sid", sa.String),
            sa.column("ep", sa.BigInteger),
            sa.column("top", sa.BigInteger),
            name="window",
        ).data([(w.lease.session_id, w.lease.epoch, w.top_seq) for w in windows])
        with self.engine.begin() as conn:
            # One statement for every session: the row locks it takes order the commit against a
            # take-over (whichever comes second sees the other's epoch); PostgreSQL's greatest()
            # ignores NULL. `top` is cast: in a window of only rejections (top NULL in every row)
            # PostgreSQL types the VALUES column as text, and greatest(bigint, text) fails.
            kept = set(
                conn.execute(
                    sa.update(session_leases)
                    .where(leases.session_id == values.c.sid, leases.epoch == values.c.ep)
                    .values(
                        expires_at=self._expiry(),
                        durable_seq=sa.func.greatest(
                            leases.durable_seq, sa.cast(values.c.top, sa.BigInteger)
                        ),
                    )
                    .returning(leases.session_id)
                ).scalars()
            )
            rows = [
                {
                    "session_id": w.lease.session_id,
                    "epoch": w.lease.epoch,
                    "data": w.data,
                    "first_record": w.first,
                }
                for w in windows
                if w.lease.session_id in kept
            ]
            if rows:
                # A window whose earlier COMMIT landed though its answer was lost is there already.
                conn.execute(
                    postgresql.insert(session_log).on_conflict_do_nothing(
                        index_elements=["session_id", "epoch", "first_record"]
                    ),
                    rows,
                )
        return {w.lease.session_id for w in windows} - kept

    def renew(self, leases: Sequence[Lease]) -> set[str]:
        """Extend the leases this process holds; the session ids no longer held (fenced)."""
        if not leases:
            return set()
        c = session_leases.c
        held: set[str] = set()
        with self.engine.begin() as conn:
            expires = self._expiry()
            for lease in leases:
                if conn.execute(
                    sa.update(session_leases)
                    .where(c.session_id == lease.session_id, c.epoch == lease.epoch)
                    .values(expires_at=expires)
                ).rowcount:
                    held.add(lease.session_id)
        return {lease.session_id for lease in leases} - held

    def park(self, lease: Lease, *, ended_as: SessionStatus) -> None:
        """Let go of a session whose stream ended without a close: anyone may resume it now, and
        nobody doing so within the resume timeout leaves it to be stored as `ended_as`."""
        c = session_leases.c
        with self.engine.begin() as conn:
            updated = conn.execute(
                sa.update(session_leases)
                .where(c.session_id == lease.session_id, c.epoch == lease.epoch)
                .values(owner="", expires_at=_NOW, ended_as=ended_as.value)
            ).rowcount
        if updated != 1:
            raise Fenced(f"session {lease.session_id} was taken over by another stream")

    def take_over(self, session_id: str, *, tenant: str, token_epoch: int) -> TakenOver:
        """Hold an OPEN session under a new epoch, whoever held it (its old holder's writes are
        fenced from now on), for a resume token issued under `token_epoch`. NotFound for a session
        that is not open here; PermissionDenied for a stale token: one older than a token already
        presented for the session (docs/decisions/0164-bound-resume-tokens.md)."""
        c = session_leases.c
        with self.engine.begin() as conn:
            held = conn.execute(
                sa.select(c.token_epoch)
                .where(c.session_id == session_id, c.tenant == tenant, _is_open(c.session_id))
                .with_for_update()
            ).one_or_none()
            if held is None:
                raise NotFound(f"session {session_id!r} is not open: it is unknown, or it has ended")
            if token_epoch < held.token_epoch:
                raise PermissionDenied(
                    f"open.resume.token of session {session_id!r} is stale: it was issued under lease "
                    f"epoch {token_epoch}, and the session has since been resumed with a token of "
                    f"epoch {held.token_epoch}; resume with the newest token the session was given"
                )
            row = conn.execute(
                sa.update(session_leases)
                .where(c.session_id == session_id)
                .values(
                    epoch=c.epoch + 1, owner=self.owner, expires_at=self._expiry(), token_epoch=token_epoch
                )
                .returning(c.epoch, c.header_json, c.durable_seq, c.ended_as)
            ).one()
        return TakenOver(
            lease=Lease(session_id, int(row.epoch)),
            header_json=row.header_json,
            durable_seq=None if row.durable_seq is None else int(row.durable_seq),
            ended_as=SessionStatus(row.ended_as),
        )

    def claim_orphan(self, *, resume_timeout: float) -> TakenOver | None:
        """Take over one session whose lease ran out more than `resume_timeout` ago (its server
        died, or its stream ended, and nobody resumed it); None when there is none."""
        c = session_leases.c
        stale = _NOW - _seconds(resume_timeout)
        with self.engine.begin() as conn:
            candidate = conn.execute(
                sa.select(c.session_id, c.tenant)
                # Never this process's own: a session it still serves whose renewals the database
                # missed (an outage) is not an orphan; another replica may take it, fencing it.
                .where(c.expires_at < stale, c.owner != self.owner, _is_open(c.session_id))
                .order_by(c.expires_at)
                .limit(1)
                .with_for_update(skip_locked=True)
            ).one_or_none()
            if candidate is None:
                return None
            row = conn.execute(
                sa.update(session_leases)
                .where(c.session_id == candidate.session_id)
                .values(epoch=c.epoch + 1, owner=self.owner, expires_at=self._expiry())
                .returning(c.epoch, c.header_json, c.durable_seq, c.ended_as)
            ).one()
        return TakenOver(
            lease=Lease(candidate.session_id, int(row.epoch)),
            header_json=row.header_json,
            durable_seq=None if row.durable_seq is None else int(row.durable_seq),
            ended_as=SessionStatus(row.ended_as),
        )

    def published(self, session_id: str, *, old: str, new: str) -> bool:
        """The data root holds the ended session's Parquet at `new`: the index points there if it
        still pointed at `old`, and the log rows and lease go (storage.index.move_location)."""
        with self.engine.begin() as conn:
            return move_location(conn, session_id, old=old, new=new)

    def ping(self) -> None:
        """Ask the database the simplest question: raises as any query would when it cannot answer."""
        with self.engine.connect() as conn:
            conn.execute(sa.select(1))

    def stream(self, session_id: str) -> SharedLogStream:
        """The session's log, batch by batch (use as a context manager)."""
        return SharedLogStream(self.engine, session_id)

    def finish(
        self,
        lease: Lease,
        *,
        status: SessionStatus,
        summary: SessionSummaryInfo,
        location: str,
        pending_upload: bool = False,
    ) -> None:
        """End the session in one transaction: the lease (fenced), the index row, the log rows.

        `pending_upload` (its Parquet is meant for the data root, whose upload failed) keeps the
        log rows and the lease, held by this process for one TTL: the rows are the only copy off this host until
        the data root holds the Parquet. This process publishes its local file meanwhile
        (storage/publish.py), and once the lease runs out any replica publishes from the rows
        (`claim_unpublished`); whichever moves the location first lets go of the rows."""
        c = session_leases.c
        fence = sa.and_(c.session_id == lease.session_id, c.epoch == lease.epoch)
        with self.engine.begin() as conn:
            if not pending_upload:
                done = conn.execute(sa.delete(session_leases).where(fence)).rowcount
            else:
                done = conn.execute(
                    sa.update(session_leases)
                    .where(fence)
                    .values(owner=self.owner, expires_at=self._expiry(), ended_as=SessionStatus(status).value)
                ).rowcount
            if done != 1:
                raise Fenced(f"session {lease.session_id} was taken over by another stream")
            finish_session(conn, lease.session_id, status=status, summary=summary, location=location)
            if not pending_upload:
                conn.execute(sa.delete(session_log).where(session_log.c.session_id == lease.session_id))

    def claim_unpublished(self) -> Unpublished | None:
        """Hold one ended session whose Parquet the data root lacks and whose holder's lease ran
        out (its replica died, or cannot publish), for one TTL under a new epoch; None when there
        is none."""
        c = session_leases.c
        with self.engine.begin() as conn:
            candidate = conn.execute(
                sa.select(c.session_id, sessions.c.location)
                .join(sessions, sessions.c.session_id == c.session_id)
                .where(c.expires_at < _NOW, sessions.c.status != SessionStatus.OPEN.value)
                .order_by(c.expires_at)
                .limit(1)
                .with_for_update(of=session_leases, skip_locked=True)
            ).one_or_none()
            if candidate is None:
                return None
            row = conn.execute(
                sa.update(session_leases)
                .where(c.session_id == candidate.session_id)
                .values(epoch=c.epoch + 1, owner=self.owner, expires_at=self._expiry())
                .returning(c.epoch, c.header_json)
            ).one()
        return Unpublished(
            lease=Lease(candidate.session_id, int(row.epoch)),
            header_json=row.header_json,
            location=str(candidate.location),
        )

    def discard(self, lease: Lease) -> None:
        """Remove a session that was never served: its lease, its log rows, its index row."""
        with self.engine.begin() as conn:
            conn.execute(sa.delete(session_leases).where(session_leases.c.session_id == lease.session_id))
            conn.execute(sa.delete(session_log).where(session_log.c.session_id == lease.session_id))
            conn.execute(
                sa.delete(sessions).where(
                    sessions.c.session_id == lease.session_id,
                    sessions.c.status == SessionStatus.OPEN.value,
                )
            )


class SharedLogStream(Closeable):
    """A session's shared log read page by page, as `storage.log.LogStream` reads a local one:
    `batches()` once; `torn` is always False (a window is committed whole or not at all)."""

    torn = False

    def __init__(self, engine: sa.Engine, session_id: str) -> None:
        self._engine = engine
        self._session_id = session_id

    def batches(self) -> Iterator[pa.RecordBatch]:
        last = -1
        c = session_log.c
        while True:
            with self._engine.connect() as conn:
                page = conn.execute(
                    sa.select(c.pk, c.data)
                    .where(c.session_id == self._session_id, c.pk > last)
                    .order_by(c.pk)
                    .limit(_READ_PAGE)
                ).all()
            if not page:
                return
            for row in page:
                last = row.pk
                batch = _read_batch(row.data)
                if batch.num_rows:
                    yield batch

    def close(self) -> None:
        """Nothing is held between pages."""
