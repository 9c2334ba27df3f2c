"""The shared tier's commit window on the real PostgreSQL: each window appends every session's rows
and renews its lease in one statement, raises durable_seq to the window's newest result, and
commits a window that holds only rejections (no result: durable_seq stays) as well; a window
whose COMMIT landed but whose answer was lost (the connection dropped) is stored once."""

from __future__ import annotations

import asyncio
import contextlib
import threading
from pathlib import Path

import pyarrow.parquet as pq
import pytest
import sqlalchemy as sa

from jitdyn.storage.commit import GroupCommitter
from jitdyn.storage.index import SessionIndex
from jitdyn.storage.parquet import header_to_json
from jitdyn.storage.recorder import SessionRecorder
from jitdyn.storage.records import TickRecord
from jitdyn.storage.schema import session_leases, session_log
from jitdyn.storage.shared import Lease, SharedTier, Window

from .conftest import POSTGRES_URL, build_header, build_records, postgres_index

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
    assert tier.commit([Window(first, None, b"rejections", first=0)]) == set()
    assert _durable(engine, first) is None
    assert (
        tier.commit([Window(first, 4, b"results", first=1), Window(second, None, b"rejections", first=0)])
        == set()
    )
    assert (_durable(engine, first), _durable(engine, second)) == (4, None)
    assert tier.commit([Window(first, None, b"more rejections", first=6)]) == set()
    assert _durable(engine, first) == 4, "a window without results leaves durable_seq where it was"

    with engine.connect() as conn:
        logged = conn.execute(sa.select(sa.func.count()).select_from(session_log)).scalar_one()
    assert logged == 4


class CommitCutter:
    """A TCP forward to PostgreSQL that, once armed, lets the next COMMIT through and then drops the
    connection before its answer comes back: the commit lands, and the client cannot know it did."""

    def __init__(self) -> None:
        self.armed = False
        self.cuts = 0
        self._loop = asyncio.new_event_loop()
        self._server = self._loop.run_until_complete(asyncio.start_server(self._accept, "127.0.0.1", 0))
        self.port = int(self._server.sockets[0].getsockname()[1])
        self._thread = threading.Thread(target=self._loop.run_forever, daemon=True)
        self._thread.start()

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        upstream_reader, upstream_writer = await asyncio.open_connection("127.0.0.1", 5432)

        cutting = asyncio.Event()

        async def up() -> None:
            while data := await reader.read(65536):
                if self.armed and b"COMMIT\x00" in data:
                    self.armed = False
                    self.cuts += 1
                    cutting.set()  # from here nothing PostgreSQL answers reaches the client
                upstream_writer.write(data)
                await upstream_writer.drain()
                if cutting.is_set():
                    await asyncio.sleep(0.3)  # PostgreSQL commits meanwhile
                    writer.transport.abort()
                    upstream_writer.transport.abort()
                    return
            upstream_writer.close()

        async def down() -> None:
            while (data := await upstream_reader.read(65536)) and not cutting.is_set():
                writer.write(data)
                await writer.drain()
            if not cutting.is_set():
                writer.close()

        try:
            with contextlib.suppress(OSError):
                await asyncio.gather(up(), down())
        finally:
            writer.close()
            upstream_writer.close()

    def close(self) -> None:
        async def stop() -> None:
            self._server.close()
            tasks = [task for task in asyncio.all_tasks() if task is not asyncio.current_task()]
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            await asyncio.sleep(0.05)  # the transports' closing callbacks

        asyncio.run_coroutine_threadsafe(stop(), self._loop).result(timeout=5)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=5)
        self._loop.close()


def test_a_window_whose_commit_answer_was_lost_is_stored_once(tmp_path: Path) -> None:
    cutter = CommitCutter()
    try:
        with postgres_index(POSTGRES_URL.replace(":5432/", f":{cutter.port}/")) as engine:
            windows, location, records = _cut_once(cutter, engine, tmp_path)
    finally:
        cutter.close()
    stored = pq.read_table(tmp_path / location, columns=["seq"]).column("seq").to_pylist()
    print(
        f"connection dropped after {cutter.cuts} COMMIT; windows stored at records {windows}; {len(stored)} rows"
    )
    assert cutter.cuts == 1
    assert stored == [r.seq for r in records]
    assert windows[0] == 0 and len(set(windows)) == len(windows)


def _cut_once(
    cutter: CommitCutter, engine: sa.Engine, tmp_path: Path
) -> tuple[list[int], str, list[TickRecord]]:
    """A session whose first commit window's answer is lost: the keys of its stored windows, its
    stored location, its records."""
    tier = SharedTier(engine, owner="replica-a", lease_ttl=30)
    committer = GroupCommitter(shared=tier)
    try:
        recorder = SessionRecorder(
            data_root=tmp_path,
            index=SessionIndex(engine),
            header=build_header(),
            committer=committer,
            shared=tier,
            commit_every=10,
        )
        records = build_records(30)
        cutter.armed = True
        for record in records[:10]:
            recorder.append(record)
        recorder.flush(timeout=20)  # the first try's answer is lost; the retry finds it stored
        for record in records[10:]:
            recorder.append(record)
        recorder.flush(timeout=20)
        with engine.connect() as conn:
            windows = conn.execute(sa.select(session_log.c.first_record).order_by(session_log.c.pk)).scalars()
            keys = [int(w) for w in windows]
        return keys, recorder.close(), records
    finally:
        committer.close()
