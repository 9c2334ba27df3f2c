"""The sessions of the SQL index: create, finish, get, list. Every read filters on the tenant.

    index = SessionIndex(open_index(url))
    rows, token = index.list(tenant="", model_name="pendulum_3", page_size=20)
    rows, token = index.list(tenant="", model_name="pendulum_3", page_size=20, page_token=token)

Lists are newest first and paged by keyset (started_at, session_id): a page token names the last
row of the previous page and the filters it was issued for, so pages stay stable while sessions
are added and a token cannot be replayed against other filters.
"""

from __future__ import annotations

import base64
import binascii
import builtins
import datetime as _dt
import hashlib
import json
import re
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Final, NotRequired, TypedDict, Unpack

import sqlalchemy as sa

from jitdyn.errors import FailedPrecondition, InvalidArgument, NotFound
from jitdyn.storage.records import FINAL_STATUSES, SessionHeader, SessionSummaryInfo, stored_word
from jitdyn.storage.schema import session_leases, session_log, sessions
from jitdyn.vocabulary import Clock, Scenario, SessionStatus

__all__ = ["MAX_PAGE_SIZE", "Ending", "SessionIndex", "SessionRow", "finish_session", "move_location"]

MAX_PAGE_SIZE: Final = 1000
_TOKEN_VERSION: Final = 1


@dataclass(frozen=True, slots=True, kw_only=True)
class SessionRow:
    """One session as the index holds it. `summary` is all zeros while the session is open;
    `location` is "" until it is compacted, then its Parquet file: a URI on the data root
    (storage/root.py) once published there, else a path relative to the data folder of the server
    that stored it."""

    session_id: str
    tenant: str
    model_id: str
    model_name: str
    model_version: int
    scenario: Scenario
    clock: Clock
    dt: float
    estimator: dict[str, object]
    subject_pseudonym: str
    subject_attributes: dict[str, str]
    started_at: _dt.datetime
    ended_at: _dt.datetime | None
    status: SessionStatus
    summary: SessionSummaryInfo
    location: str
    log_path: str


def _utc(value: _dt.datetime) -> _dt.datetime:
    """An aware UTC datetime; SQLite hands back naive ones, which the index always writes in UTC."""
    if value.tzinfo is None:
        return value.replace(tzinfo=_dt.UTC)
    return value.astimezone(_dt.UTC)


def _aware(name: str, value: _dt.datetime) -> _dt.datetime:
    if value.tzinfo is None or value.utcoffset() is None:
        raise InvalidArgument(f"{name} must be timezone-aware, got naive {value.isoformat()}")
    return value.astimezone(_dt.UTC)


def _row(mapping: sa.RowMapping) -> SessionRow:
    return SessionRow(
        session_id=mapping["session_id"],
        tenant=mapping["tenant"],
        model_id=mapping["model_id"],
        model_name=mapping["model_name"],
        model_version=int(mapping["model_version"]),
        scenario=Scenario(mapping["scenario"]),
        clock=Clock(mapping["clock"]),
        dt=float(mapping["dt"]),
        estimator=json.loads(mapping["estimator_json"]),
        subject_pseudonym=mapping["subject_pseudonym"],
        subject_attributes=json.loads(mapping["subject_attributes_json"]),
        started_at=_utc(mapping["started_at"]),
        ended_at=None if mapping["ended_at"] is None else _utc(mapping["ended_at"]),
        status=SessionStatus(mapping["status"]),
        summary=SessionSummaryInfo(
            ticks=int(mapping["ticks"]),
            frames=int(mapping["frames"]),
            measured=int(mapping["measured"]),
            predicted=int(mapping["predicted"]),
            corrected=int(mapping["corrected"]),
            rejected=int(mapping["rejected"]),
            late=int(mapping["late"]),
            mean_compute_us=float(mapping["mean_compute_us"]),
            max_compute_us=float(mapping["max_compute_us"]),
            duration=float(mapping["duration"]),
            stats=json.loads(mapping["stats_json"]),
        ),
        location=mapping["location"],
        log_path=mapping["log_path"],
    )


def _summary_values(summary: SessionSummaryInfo) -> dict[str, Any]:
    return {
        "ticks": summary.ticks,
        "frames": summary.frames,
        "measured": summary.measured,
        "predicted": summary.predicted,
        "corrected": summary.corrected,
        "rejected": summary.rejected,
        "late": summary.late,
        "mean_compute_us": summary.mean_compute_us,
        "max_compute_us": summary.max_compute_us,
        "duration": summary.duration,
        "stats_json": json.dumps(summary.stats),
    }


def _encode_token(row: SessionRow, fingerprint: str) -> str:
    payload = {"v": _TOKEN_VERSION, "s": row.started_at.isoformat(), "i": row.session_id, "f": fingerprint}
    raw = json.dumps(payload, separators=(",", ":")).encode()
    return base64.urlsafe_b64encode(raw).rstrip(b"=").decode()


def _decode_token(token: str, fingerprint: str) -> tuple[_dt.datetime, str]:
    bad = InvalidArgument(
        f"page_token {token[:40]!r} is not a token this server issued; pass the next_page_token of "
        "the previous page, or an empty token for the first page"
    )
    try:
        raw = base64.urlsafe_b64decode(token + "=" * (-len(token) % 4))
        payload = json.loads(raw)
        if not isinstance(payload, dict) or payload.get("v") != _TOKEN_VERSION:
            raise bad
        started_at = _dt.datetime.fromisoformat(payload["s"])
        session_id = str(uuid.UUID(payload["i"]))
        token_fingerprint = payload["f"]
    except (ValueError, TypeError, KeyError, binascii.Error, UnicodeDecodeError) as exc:
        raise bad from exc
    if started_at.tzinfo is None:
        raise bad
    if token_fingerprint != fingerprint:
        raise InvalidArgument(
            "page_token was issued for other filters; repeat the filters of the first page, or start "
            "again with an empty token"
        )
    return started_at.astimezone(_dt.UTC), session_id


# A session id or the start of one (ids are UUIDs); how many candidates an ambiguous one lists.
_ID_PREFIX: Final = re.compile(r"[0-9a-fA-F][0-9a-fA-F-]{0,35}")
_CANDIDATES_SHOWN: Final = 5


class SessionIndex:
    """The `sessions` table on an engine from `jitdyn.storage.db.open_index`. Thread-safe: each call
    takes its own connection from the engine's pool."""

    def __init__(self, engine: sa.Engine) -> None:
        self._engine = engine

    @property
    def engine(self) -> sa.Engine:
        return self._engine

    def create(
        self,
        header: SessionHeader,
        *,
        log_path: str,
        also: Callable[[sa.Connection], object] | None = None,
    ) -> None:
        """Add an OPEN session whose frames go to `log_path` (relative to the data root; "" for a
        log in the shared tier); `also` runs in the same transaction (the shared tier's lease)."""
        values = {
            "session_id": header.session_id,
            "tenant": header.tenant,
            "model_id": header.model_id,
            "model_name": header.model_name,
            "model_version": header.model_version,
            "scenario": str(header.scenario),
            "clock": str(header.clock),
            "dt": header.dt,
            "estimator_json": json.dumps(header.estimator),
            "subject_pseudonym": header.subject_pseudonym,
            "subject_attributes_json": json.dumps(header.subject_attributes),
            "started_at": _aware("started_at", header.started_at),
            "status": SessionStatus.OPEN.value,
            "log_path": log_path,
        }
        try:
            with self._engine.begin() as conn:
                conn.execute(sa.insert(sessions).values(**values))
                if also is not None:
                    also(conn)
        except sa.exc.IntegrityError as exc:
            raise FailedPrecondition(f"session {header.session_id} is already in the index") from exc

    def update_progress(self, session_id: str, summary: SessionSummaryInfo) -> None:
        """Record the counts so far of an OPEN session (for listings while it runs)."""
        with self._engine.begin() as conn:
            conn.execute(
                sa.update(sessions)
                .where(sessions.c.session_id == session_id, sessions.c.status == SessionStatus.OPEN.value)
                .values(**_summary_values(summary))
            )

    def finish(self, session_id: str, **ending: Unpack[Ending]) -> None:
        """End an OPEN session in one transaction: its status, summary, Parquet location and end.

        Raises FailedPrecondition when the session is not OPEN (already ended, or recovered by
        another server), NotFound when the index has no such session.
        """
        with self._engine.begin() as conn:
            finish_session(conn, session_id, **ending)

    def discard(self, session_id: str) -> None:
        """Remove the row of a session that was never served (its open failed or was abandoned
        before `opened` was sent): no frame of it exists, so nothing is to be kept."""
        with self._engine.begin() as conn:
            conn.execute(
                sa.delete(sessions).where(
                    sessions.c.session_id == session_id, sessions.c.status == SessionStatus.OPEN.value
                )
            )

    def get(self, session_id: str, *, tenant: str) -> SessionRow:
        """The session, if it belongs to `tenant`; NotFound otherwise (whoever else it belongs to)."""
        with self._engine.connect() as conn:
            mapping = (
                conn.execute(
                    sa.select(sessions).where(
                        sessions.c.session_id == session_id, sessions.c.tenant == tenant
                    )
                )
                .mappings()
                .one_or_none()
            )
        if mapping is None:
            raise NotFound(f"session {session_id!r} not found")
        return _row(mapping)

    def complete_id(self, prefix: str, *, tenant: str) -> str:
        """The one session id of the tenant that is `prefix` or starts with it, as git completes a
        commit. NotFound when none does; InvalidArgument naming the candidates when several do."""
        if not _ID_PREFIX.fullmatch(prefix):
            raise NotFound(f"session {prefix!r} not found: a session id is hexadecimal, like 0e0529f0")
        c = sessions.c
        query = (
            sa.select(c.session_id)
            .where(c.tenant == tenant, c.session_id.startswith(prefix.lower()))
            .order_by(c.session_id)
            .limit(_CANDIDATES_SHOWN + 1)
        )
        with self._engine.connect() as conn:
            found = [str(value) for value in conn.execute(query).scalars()]
        if prefix.lower() in found or len(found) == 1:
            return prefix.lower() if prefix.lower() in found else found[0]
        if not found:
            raise NotFound(f"session {prefix!r} not found: no session id starts with it")
        shown = ", ".join(found[:_CANDIDATES_SHOWN]) + (", ..." if len(found) > _CANDIDATES_SHOWN else "")
        raise InvalidArgument(
            f"session id prefix {prefix!r} is ambiguous: it starts {shown}; give more of it"
        )

    def list(
        self,
        *,
        tenant: str,
        model_name: str | None = None,
        model_version: int | None = None,
        model_id: str | None = None,
        scenario: Scenario | str | None = None,
        pseudonym: str | None = None,
        started_after: _dt.datetime | None = None,
        started_before: _dt.datetime | None = None,
        status: SessionStatus | str | None = None,
        page_size: int = 50,
        page_token: str = "",
    ) -> tuple[tuple[SessionRow, ...], str]:
        """A page of the tenant's sessions, newest first, and the token of the next page ("" on
        the last). Sessions started at or after `started_after` and before `started_before`."""
        if not 1 <= page_size <= MAX_PAGE_SIZE:
            raise InvalidArgument(f"page_size must be between 1 and {MAX_PAGE_SIZE}, got {page_size}")
        if scenario is not None:
            scenario = stored_word(Scenario, scenario, argument="scenario").value
        if status is not None:
            status = stored_word(SessionStatus, status, argument="status").value
        after = None if started_after is None else _aware("started_after", started_after)
        before = None if started_before is None else _aware("started_before", started_before)
        if after is not None and before is not None and after > before:
            raise InvalidArgument(
                f"started_after ({after.isoformat()}) must not be later than started_before "
                f"({before.isoformat()})"
            )
        filters = {
            "model_name": model_name,
            "model_version": model_version,
            "model_id": model_id,
            "scenario": scenario,
            "pseudonym": pseudonym,
            "after": None if after is None else after.isoformat(),
            "before": None if before is None else before.isoformat(),
            "status": status,
        }
        fingerprint = hashlib.sha256(json.dumps(filters, sort_keys=True).encode()).hexdigest()[:16]

        c = sessions.c
        query = sa.select(sessions).where(c.tenant == tenant)
        if model_name is not None:
            query = query.where(c.model_name == model_name)
        if model_version is not None:
            query = query.where(c.model_version == model_version)
        if model_id is not None:
            query = query.where(c.model_id == model_id)
        if scenario is not None:
            query = query.where(c.scenario == scenario)
        if pseudonym is not None:
            query = query.where(c.subject_pseudonym == pseudonym)
        if after is not None:
            query = query.where(c.started_at >= after)
        if before is not None:
            query = query.where(c.started_at < before)
        if status is not None:
            query = query.where(c.status == status)
        if page_token:
            last_started, last_id = _decode_token(page_token, fingerprint)
            query = query.where(
                sa.or_(
                    c.started_at < last_started, sa.and_(c.started_at == last_started, c.session_id < last_id)
                )
            )
        query = query.order_by(c.started_at.desc(), c.session_id.desc()).limit(page_size + 1)
        with self._engine.connect() as conn:
            rows = tuple(_row(m) for m in conn.execute(query).mappings())
        if len(rows) <= page_size:
            return rows, ""
        page = rows[:page_size]
        return page, _encode_token(page[-1], fingerprint)

    def all_sessions(self, *, tenant: str) -> builtins.list[SessionRow]:
        """Every session of the tenant, oldest first (for queries over the whole dataset)."""
        query = (
            sa.select(sessions)
            .where(sessions.c.tenant == tenant)
            .order_by(sessions.c.started_at, sessions.c.session_id)
        )
        with self._engine.connect() as conn:
            return [_row(m) for m in conn.execute(query).mappings()]

    def stored_location(self, session_id: str) -> tuple[SessionStatus, str] | None:
        """The status and location of a session, whatever its tenant (the server's own publishing
        of finished sessions is the reader); None when the index has no such session."""
        with self._engine.connect() as conn:
            row = conn.execute(
                sa.select(sessions.c.status, sessions.c.location).where(sessions.c.session_id == session_id)
            ).one_or_none()
        return None if row is None else (SessionStatus(row.status), str(row.location))

    def move_location(self, session_id: str, *, old: str, new: str) -> bool:
        """Point an ended session at `new` if it still points at `old` (its Parquet was published to
        the data root), and let go of its shared log; whether it did."""
        with self._engine.begin() as conn:
            return move_location(conn, session_id, old=old, new=new)

    def unfinished(self) -> builtins.list[SessionRow]:
        """Every OPEN session of every tenant: the server's own recovery at start is the one reader
        that is not a tenant's."""
        query = (
            sa.select(sessions)
            .where(sessions.c.status == SessionStatus.OPEN.value)
            .order_by(sessions.c.started_at)
        )
        with self._engine.connect() as conn:
            return [_row(m) for m in conn.execute(query).mappings()]


class Ending(TypedDict):
    """How a session ended, as `SessionIndex.finish` and `finish_session` take it: its final
    status, its summary, where its Parquet file is, and when (default: now)."""

    status: SessionStatus | str
    summary: SessionSummaryInfo
    location: str
    ended_at: NotRequired[_dt.datetime | None]


def move_location(conn: sa.Connection, session_id: str, *, old: str, new: str) -> bool:
    """`SessionIndex.move_location` inside the caller's transaction. The session's rows in the
    shared log and its lease go in the same transaction: they were kept until the data root held
    its Parquet, so that no finished session has its only copy on one replica's disk."""
    moved = conn.execute(
        sa.update(sessions)
        .where(sessions.c.session_id == session_id, sessions.c.location == old)
        .where(sessions.c.status != SessionStatus.OPEN.value)
        .values(location=new)
    ).rowcount
    if moved != 1:
        return False
    conn.execute(sa.delete(session_log).where(session_log.c.session_id == session_id))
    conn.execute(sa.delete(session_leases).where(session_leases.c.session_id == session_id))
    return True


def finish_session(conn: sa.Connection, session_id: str, **ending: Unpack[Ending]) -> None:
    """`SessionIndex.finish` inside the caller's transaction (the shared tier ends a lease in it too)."""
    status = stored_word(SessionStatus, ending["status"], argument="status", among=FINAL_STATUSES)
    ended_at = ending.get("ended_at")
    end = _dt.datetime.now(_dt.UTC) if ended_at is None else _aware("ended_at", ended_at)
    summary, location = ending["summary"], ending["location"]
    result = conn.execute(
        sa.update(sessions)
        .where(sessions.c.session_id == session_id, sessions.c.status == SessionStatus.OPEN.value)
        .values(
            status=status.value,
            ended_at=end,
            location=location,
            log_path="",
            **_summary_values(summary),
        )
    )
    if result.rowcount == 1:
        return
    current = conn.execute(
        sa.select(sessions.c.status).where(sessions.c.session_id == session_id)
    ).scalar_one_or_none()
    if current is None:
        raise NotFound(f"session {session_id} is not in the index")
    raise FailedPrecondition(f"session {session_id} is {current}, not OPEN; it was ended already")
