"""The shared tier's commit window on the real PostgreSQL: each window appends every session's rows
and renews its lease in one statement, raises durable_seq to the window's newest result, and
commits a window that holds only rejections (no result: durable_seq stays) as well."""

from __future__ import annotations

import pytest
import sqlalchemy as sa

from jitdyn.storage.index import SessionIndex
from jitdyn.storage.parquet import header_to_json
from jitdyn.storage.schema import session_leases, session_log
from jitdyn.storage.shared import Lease, SharedTier, Window

from .conftest import build_header

pytestmark = pytest.mark.postgres


@pytest.fixture(params=["postgres"])
def engine(request: pytest.FixtureRequest, engine: sa.Engine) -> sa.Engine:
    return engine


def _open(index: SessionIndex, tier: SharedTier) -> Lease:
    header = build_header()
    leases: list[Lease] = []
    index.create(
        header,
        log_path="",
        also=lambda conn: leases.append(tier.create(header, header_json=header_to_json(header), conn=conn)),
    )
    return leases[0]


def _durable(engine: sa.Engine, lease: Lease) -> int | None:
    with engine.connect() as conn:
        return conn.execute(
            sa.select(session_leases.c.durable_seq).where(session_leases.c.session_id == lease.session_id)
        ).scalar_one()


def test_windows_with_and_without_results_commit_and_raise_durable_seq(engine: sa.Engine) -> None:
    index = SessionIndex(engine)
    tier = SharedTier(engine, owner="replica-a", lease_ttl=30)
    first, second = _open(index, tier), _open(index, tier)

    # Only rejections, one session alone: every `top` is NULL.
    assert tier.commit([Window(first, None, b"rejections")]) == set()
    assert _durable(engine, first) is None
    assert tier.commit([Window(first, 4, b"results"), Window(second, None, b"rejections")]) == set()
    assert (_durable(engine, first), _durable(engine, second)) == (4, None)
    assert tier.commit([Window(first, None, b"more rejections")]) == set()
    assert _durable(engine, first) == 4, "a window without results leaves durable_seq where it was"

    with engine.connect() as conn:
        logged = conn.execute(sa.select(sa.func.count()).select_from(session_log)).scalar_one()
    assert logged == 4
