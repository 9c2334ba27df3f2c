"""SessionIndex on SQLite and PostgreSQL: create, finish, get, list with filters and keyset pages,
tenant isolation on every read; and the migrations agreeing with storage.schema."""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable

import pytest
import sqlalchemy as sa
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext

from jitdyn.errors import FailedPrecondition, InvalidArgument, NotFound
from jitdyn.storage.db import upgrade
from jitdyn.storage.index import SessionIndex, SessionRow
from jitdyn.storage.records import SessionHeader, SessionSummaryInfo
from jitdyn.storage.schema import metadata
from jitdyn.vocabulary import Scenario, SessionStatus

T0 = dt.datetime(2026, 11, 21, 10, 0, 0, tzinfo=dt.UTC)


def add(index: SessionIndex, header: SessionHeader) -> SessionHeader:
    index.create(header, log_path=f"logs/{header.session_id}.arrows")
    return header


def all_pages(index: SessionIndex, page_size: int, **filters: object) -> list[list[SessionRow]]:
    pages: list[list[SessionRow]] = []
    token = ""
    while True:
        rows, token = index.list(page_size=page_size, page_token=token, **filters)  # type: ignore[arg-type]
        pages.append(list(rows))
        if not token:
            return pages


def test_create_get_and_finish(index: SessionIndex, make_header: Callable[..., SessionHeader]) -> None:
    header = add(
        index,
        make_header(
            tenant="lab-a",
            subject_pseudonym="ab" * 32,
            subject_attributes={"sex": "F"},
            started_at=dt.datetime(2026, 11, 21, 11, 0, 0, 123456, tzinfo=dt.timezone(dt.timedelta(hours=1))),
        ),
    )
    row = index.get(header.session_id, tenant="lab-a")
    # The index holds text; a row holds the vocabulary's members.
    assert row.status is SessionStatus.OPEN and row.scenario is Scenario(header.scenario)
    assert row.started_at == dt.datetime(2026, 11, 21, 10, 0, 0, 123456, tzinfo=dt.UTC)
    assert row.started_at.tzinfo == dt.UTC
    assert row.ended_at is None
    assert row.estimator == header.estimator
    assert row.subject_attributes == {"sex": "F"}
    assert row.summary == SessionSummaryInfo()
    assert row.log_path == f"logs/{header.session_id}.arrows"

    progress = SessionSummaryInfo(ticks=5, frames=5, measured=5)
    index.update_progress(header.session_id, progress)
    assert index.get(header.session_id, tenant="lab-a").summary == progress

    summary = SessionSummaryInfo(
        ticks=10,
        frames=11,
        measured=8,
        predicted=2,
        corrected=1,
        rejected=1,
        late=1,
        mean_compute_us=12.5,
        max_compute_us=40.0,
        duration=0.1,
        stats={"qfrc_inverse": {"hinge_1": {"min": -1.0, "max": 2.0}}},
    )
    end = T0 + dt.timedelta(minutes=5)
    index.finish(
        header.session_id, status="COMPLETE", summary=summary, location="frames/x.parquet", ended_at=end
    )
    row = index.get(header.session_id, tenant="lab-a")
    assert (row.status, row.summary, row.location, row.log_path, row.ended_at) == (
        "COMPLETE",
        summary,
        "frames/x.parquet",
        "",
        end,
    )
    with pytest.raises(FailedPrecondition) as error:
        index.finish(header.session_id, status="RECOVERED", summary=summary, location="x")
    assert str(error.value) == f"session {header.session_id} is COMPLETE, not OPEN; it was ended already"
    with pytest.raises(NotFound, match="is not in the index"):
        index.finish("00000000-0000-0000-0000-000000000000", status="FAILED", summary=summary, location="")
    with pytest.raises(
        InvalidArgument, match="status must be one of COMPLETE, RECOVERED, FAILED, ABANDONED, got 'OPEN'"
    ):
        index.finish(header.session_id, status="OPEN", summary=summary, location="")
    with pytest.raises(FailedPrecondition, match="already in the index"):
        index.create(header, log_path="")


def test_another_tenants_session_is_not_found(
    index: SessionIndex, make_header: Callable[..., SessionHeader]
) -> None:
    header = add(index, make_header(tenant="lab-a"))
    with pytest.raises(NotFound) as error:
        index.get(header.session_id, tenant="lab-b")
    assert str(error.value) == f"session {header.session_id!r} not found"
    with pytest.raises(NotFound):
        index.get(header.session_id, tenant="")
    assert index.list(tenant="lab-b") == ((), "")
    assert index.all_sessions(tenant="lab-b") == []
    assert [r.session_id for r in index.all_sessions(tenant="lab-a")] == [header.session_id]
    assert [r.session_id for r in index.unfinished()] == [header.session_id]


def test_pages_are_newest_first_complete_and_stable(
    index: SessionIndex, make_header: Callable[..., SessionHeader]
) -> None:
    # Ties in started_at on purpose: the session id breaks them.
    headers = [add(index, make_header(started_at=T0 + dt.timedelta(seconds=i // 2))) for i in range(7)]
    add(index, make_header(tenant="other"))
    pages = all_pages(index, 3, tenant="")
    assert [len(p) for p in pages] == [3, 3, 1]
    listed = [r.session_id for page in pages for r in page]
    expected = sorted(headers, key=lambda h: (h.started_at, h.session_id), reverse=True)
    assert listed == [h.session_id for h in expected]

    # A session added after the first page does not shift the later pages.
    first, token = index.list(tenant="", page_size=3)
    add(index, make_header(started_at=T0 + dt.timedelta(hours=1)))
    second, _ = index.list(tenant="", page_size=3, page_token=token)
    assert [r.session_id for r in (*first, *second)] == listed[:6]


def test_filters(index: SessionIndex, make_header: Callable[..., SessionHeader]) -> None:
    a = add(index, make_header(model_name="pendulum_1", model_id="sha256:1", started_at=T0))
    b = add(
        index,
        make_header(
            scenario="CONTROLLED", subject_pseudonym="cd" * 32, started_at=T0 + dt.timedelta(hours=1)
        ),
    )
    c = add(index, make_header(started_at=T0 + dt.timedelta(hours=2)))
    index.finish(c.session_id, status="RECOVERED", summary=SessionSummaryInfo(), location="")

    def ids(**filters: object) -> set[str]:
        return {r.session_id for page in all_pages(index, 50, tenant="", **filters) for r in page}

    assert ids(model_name="pendulum_1") == {a.session_id}
    assert ids(model_id="sha256:1") == {a.session_id}
    assert ids(scenario="CONTROLLED") == {b.session_id}
    assert ids(pseudonym="cd" * 32) == {b.session_id}
    assert ids(status="RECOVERED") == {c.session_id}
    assert ids(status="OPEN") == {a.session_id, b.session_id}
    assert ids(started_after=T0 + dt.timedelta(hours=1)) == {b.session_id, c.session_id}
    assert ids(started_before=T0 + dt.timedelta(hours=1)) == {a.session_id}
    assert ids(started_after=T0, started_before=T0 + dt.timedelta(hours=2)) == {a.session_id, b.session_id}
    assert ids(model_name="pendulum_1", scenario="CONTROLLED") == set()


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        ({"page_size": 0}, "page_size must be between 1 and 1000, got 0"),
        ({"page_size": 1001}, "page_size must be between 1 and 1000, got 1001"),
        (
            {"scenario": "passive"},
            "scenario must be one of PASSIVE, CONTROLLED, EXTERNAL, DRIVEN, got 'passive'",
        ),
        (
            {"status": "DONE"},
            "status must be one of OPEN, COMPLETE, RECOVERED, FAILED, ABANDONED, got 'DONE'",
        ),
        (
            {"started_after": T0 + dt.timedelta(seconds=1), "started_before": T0},
            (
                "started_after (2026-11-21T10:00:01+00:00) must not be later than started_before "
                "(2026-11-21T10:00:00+00:00)"
            ),
        ),
        (
            {"started_after": dt.datetime(2026, 1, 1)},
            "started_after must be timezone-aware, got naive 2026-01-01T00:00:00",
        ),
        ({"page_token": "garbage!"}, "page_token 'garbage!' is not a token this server issued"),
        ({"page_token": "eyJ2IjoyfQ"}, "page_token 'eyJ2IjoyfQ' is not a token this server issued"),
    ],
)
def test_bad_list_arguments(index: SessionIndex, arguments: dict[str, object], message: str) -> None:
    with pytest.raises(InvalidArgument) as error:
        index.list(tenant="", **arguments)  # type: ignore[arg-type]
    assert str(error.value).startswith(message)


def test_token_is_bound_to_its_filters(
    index: SessionIndex, make_header: Callable[..., SessionHeader]
) -> None:
    for i in range(3):
        add(index, make_header(started_at=T0 + dt.timedelta(seconds=i)))
    _, token = index.list(tenant="", page_size=1)
    assert token
    with pytest.raises(InvalidArgument) as error:
        index.list(tenant="", page_size=1, page_token=token, scenario="PASSIVE")
    assert str(error.value) == (
        "page_token was issued for other filters; repeat the filters of the first page, or start again "
        "with an empty token"
    )
    # Another tenant replaying the token sees only its own (no) sessions.
    assert index.list(tenant="intruder", page_size=1, page_token=token) == ((), "")


def test_migrations_match_the_schema_module(engine: sa.Engine) -> None:
    upgrade(engine)  # idempotent
    with engine.connect() as conn:
        schema = (conn.get_execution_options().get("schema_translate_map") or {}).get(None)
        if schema is not None:
            conn.execute(sa.text(f'SET search_path TO "{schema}"'))
        context = MigrationContext.configure(conn, opts={"compare_type": True})
        assert compare_metadata(context, metadata) == []
