"""The SDK resumes a session by itself (issue 19, must-have 5, client side): a LOCKSTEP session
through HAProxy whose replica is killed with -9 goes on on another replica with no error to the
caller, and the stored session is one session holding every frame; a replica drained by SIGTERM
moves its session the same way; the buffer of frames kept for a resume is bounded. The asyncio SDK
(`AsyncClient`) does the same, tested at the end."""

from __future__ import annotations

import asyncio
import os
import signal
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from _cluster import Balancer, Replica, behind_haproxy, session_owner, wait_for
from _raw import DT, new_model, session_row

from jitdyn.client import (
    AsyncClient,
    AsyncSession,
    Client,
    FrameData,
    ResumePolicy,
    SessionOptions,
    Summary,
    TickResult,
)
from jitdyn.errors import JitdynError, ResumeBufferFull, SessionLost

pytestmark = pytest.mark.postgres

FAST = ["--lease-ttl=1s", "--resume-timeout=5s"]
HOSTS = ("127.0.0.21", "127.0.0.22", "127.0.0.23")


def frame(k: int) -> FrameData:
    return FrameData(seq=k, t=k * DT, qpos=[0.3 * np.cos(0.2 * k), 0.1 * np.sin(0.3 * k)], qvel=[0.0, 0.0])


def options(mjcf: str) -> SessionOptions:
    return SessionOptions(inline_mjcf=mjcf, inline_name="pendulum_2_inline", dt=DT)


def cluster(
    start_replica: Callable[..., Replica], start_balancer: Callable[..., Balancer], tmp_path: Path
) -> tuple[list[Replica], Balancer]:
    """Three replicas behind HAProxy."""
    return behind_haproxy(start_replica, start_balancer, tmp_path / "shared-folder", HOSTS, extra=FAST)


owner = session_owner


def stored_seqs(folder: Path, location: str) -> list[int]:
    table = pq.read_table(folder / location, columns=["kind", "seq"])
    return sorted(
        s for k, s in zip(table["kind"].to_pylist(), table["seq"].to_pylist(), strict=True) if k == "result"
    )


def assert_every_frame_kept(path: Path, ticks: int) -> None:
    """Every frame sent is in the stored session: measured into a result, or, when its timewarp did
    not fit (a re-sent frame far behind the clock on a busy machine), kept with its values in a
    TOO_OLD rejection that says why."""
    rows = pq.read_table(path, columns=["kind", "seq", "frame_received", "reject_reason"]).to_pylist()
    measured = {r["seq"] for r in rows if r["kind"] == "result" and r["frame_received"]}
    refused = {r["seq"] for r in rows if r["kind"] == "rejected" and r["reject_reason"] == "TOO_OLD"}
    print(f"frames measured {len(measured)}, refused as too late to replay: {sorted(refused - measured)}")
    assert sorted(measured | refused) == list(range(ticks)), "every frame sent is in the record"
    assert len(measured) >= ticks - 5, "most frames are measured"


def test_a_killed_replica_s_session_resumes_on_another_without_an_error(
    start_replica: Callable[..., Replica],
    start_balancer: Callable[..., Balancer],
    index_url: str,
    tmp_path: Path,
) -> None:
    replicas, balancer = cluster(start_replica, start_balancer, tmp_path)
    with Client(balancer.address, timeout=30) as client:
        session = client.open_session(options(new_model()))
        assert session.opened.resume_token
        seqs = [session.send_frame(frame(k)).seq for k in range(40)]
        doomed = owner(replicas)
        doomed.kill()
        seqs += [session.send_frame(frame(k)).seq for k in range(40, 80)]
        summary = session.close()
    assert seqs == list(range(80)), "every frame answered once, in order"
    assert len(session.resumptions) == 1 and summary.resumes == 1 and summary.missed == 0
    resumption = session.resumptions[0]
    print(
        f"resumed after kill -9 in {1e3 * resumption.took:.0f} ms ({resumption.attempts} attempts, "
        f"cause {resumption.cause!r}) from tick {resumption.from_seq}: {resumption.reason}"
    )
    assert resumption.session_id == session.opened.session_id
    row = session_row(index_url, session.opened.session_id)
    assert row is not None and row["status"] == "COMPLETE"
    assert stored_seqs(tmp_path / "shared-folder", str(row["location"])) == list(range(80))


def test_a_draining_replica_moves_its_session_without_an_error(
    start_replica: Callable[..., Replica],
    start_balancer: Callable[..., Balancer],
    index_url: str,
    tmp_path: Path,
) -> None:
    replicas, balancer = cluster(start_replica, start_balancer, tmp_path)
    with Client(balancer.address, timeout=30) as client:
        session = client.open_session(options(new_model()))
        seqs = [session.send_frame(frame(k)).seq for k in range(30)]
        leaving = owner(replicas)
        os.killpg(leaving.process.pid, signal.SIGTERM)
        wait_for(
            lambda: balancer.server_states().get(leaving.name) != "UP",
            timeout=10,
            what="haproxy kept the draining replica UP",
        )
        seqs += [session.send_frame(frame(k)).seq for k in range(30, 60)]
        summary = session.close()
    leaving.process.wait(timeout=20)
    assert seqs == list(range(60))
    assert summary.resumes == 1 and session.resumptions[0].cause.startswith("moving")
    print(f"moved in {1e3 * session.resumptions[0].took:.0f} ms from tick {session.resumptions[0].from_seq}")
    row = session_row(index_url, session.opened.session_id)
    assert row is not None and row["status"] == "COMPLETE"
    assert stored_seqs(tmp_path / "shared-folder", str(row["location"])) == list(range(60))


def test_round_robin_over_several_addresses_and_a_bounded_resume_buffer(
    start_replica: Callable[..., Replica], tmp_path: Path
) -> None:
    folder = tmp_path / "shared-folder"
    replicas = [start_replica(f"r{n}", host, data=folder, extra=FAST) for n, host in enumerate(HOSTS[:2])]
    target = "ipv4:" + ",".join(r.address for r in replicas)
    policy = ResumePolicy(max_unacknowledged=5)
    with Client(target, channel_options=[("grpc.lb_policy_name", "round_robin")], resume=policy) as client:
        session = client.open_session(options(new_model()))
        for k in range(5):
            session.send(frame(k))  # pipelined: no answer read, so none acknowledged yet
        with pytest.raises(ResumeBufferFull, match="max_unacknowledged"):
            session.send(frame(5))
        answered = []
        for answer in session.results(timeout=10):
            answered.append(answer.seq)
            if len(answered) == 5:
                break
        assert answered == list(range(5))
        session.cancel()
    with Client(target, channel_options=[("grpc.lb_policy_name", "round_robin")], resume=False) as client:
        session = client.open_session(options(new_model()))
        session.send_frame(frame(0))
        owner(replicas).kill()
        with pytest.raises(Exception) as broken:
            for k in range(1, 40):
                session.send_frame(frame(k))
        print(f"with resume off: {type(broken.value).__name__}: {broken.value}")
        assert type(broken.value).__name__ in ("Unavailable", "JitdynError")


# 10 s: runs with the slow tests (pytest -m slow), to keep CI under 20 minutes; its async variant runs in CI.
@pytest.mark.slow
def test_a_realtime_session_resumes_and_its_record_keeps_every_frame(
    start_replica: Callable[..., Replica],
    start_balancer: Callable[..., Balancer],
    index_url: str,
    tmp_path: Path,
) -> None:
    """REALTIME: the ticks that pass while the session moves are answered late from the frames the
    SDK re-sends (the server replays them in order with the estimator), not skipped: no tick goes
    unanswered, and the stored session holds every frame the client sent, as a measured result."""
    replicas, balancer = cluster(start_replica, start_balancer, tmp_path)
    ticks = 80
    with Client(balancer.address, timeout=30) as client:
        session = client.open_session(
            SessionOptions(inline_mjcf=new_model(), inline_name="pendulum_2_inline", dt=DT, clock="REALTIME")
        )
        answered: dict[int, float] = {}
        for k in range(ticks):
            time.sleep(max(0.0, k * DT - session.now()))
            session.send(frame(k))
            if k == 30:
                owner(replicas).kill()
            for answer in session.poll():
                if isinstance(answer, TickResult) and answer.source != "CORRECTED":
                    answered.setdefault(answer.seq, answer.received_at - session.clock_start)
        for answer in session.results(timeout=10):
            if isinstance(answer, TickResult) and answer.source != "CORRECTED":
                answered.setdefault(answer.seq, answer.received_at - session.clock_start)
                if answer.seq == ticks - 1:
                    break
        summary = session.close()
    late = [k for k, at in answered.items() if at > k * DT + session.opened.grace]
    print(f"resumed {summary.resumes}x; ticks missed {summary.missed}; answered late: {sorted(late)}")
    assert summary.resumes == 1 and summary.missed == 0
    assert sorted(answered) == list(range(ticks)), "every tick answered once"
    row = session_row(index_url, session.opened.session_id)
    assert row is not None and row["status"] == "COMPLETE"
    assert_every_frame_kept(tmp_path / "shared-folder" / str(row["location"]), ticks)


def test_an_async_session_resumes_after_its_replica_is_killed(
    start_replica: Callable[..., Replica],
    start_balancer: Callable[..., Balancer],
    index_url: str,
    tmp_path: Path,
) -> None:
    replicas, balancer = cluster(start_replica, start_balancer, tmp_path)

    async def run() -> tuple[list[int], AsyncSession, Summary]:
        async with AsyncClient(balancer.address, timeout=30) as client:
            session = await client.open_session(options(new_model()))
            assert session.opened.resume_token
            seqs = [(await session.send_frame(frame(k))).seq for k in range(40)]
            owner(replicas).kill()
            seqs += [(await session.send_frame(frame(k))).seq for k in range(40, 80)]
            return seqs, session, await session.close()

    seqs, session, summary = asyncio.run(run())
    assert seqs == list(range(80)), "every frame answered once, in order"
    assert len(session.resumptions) == 1 and summary.resumes == 1 and summary.missed == 0
    resumption = session.resumptions[0]
    print(
        f"async: resumed after kill -9 in {1e3 * resumption.took:.0f} ms ({resumption.attempts} "
        f"attempts, cause {resumption.cause!r}) from tick {resumption.from_seq}: {resumption.reason}"
    )
    assert resumption.session_id == session.opened.session_id
    row = session_row(index_url, session.opened.session_id)
    assert row is not None and row["status"] == "COMPLETE"
    assert stored_seqs(tmp_path / "shared-folder", str(row["location"])) == list(range(80))


# 8 s: runs with the slow tests (pytest -m slow), to keep CI under 20 minutes; the session variant runs in CI.
@pytest.mark.slow
def test_a_draining_replica_moves_its_async_session(
    start_replica: Callable[..., Replica],
    start_balancer: Callable[..., Balancer],
    index_url: str,
    tmp_path: Path,
) -> None:
    replicas, balancer = cluster(start_replica, start_balancer, tmp_path)

    async def run() -> tuple[list[int], AsyncSession, Summary, Replica]:
        async with AsyncClient(balancer.address, timeout=30) as client:
            session = await client.open_session(options(new_model()))
            seqs = [(await session.send_frame(frame(k))).seq for k in range(30)]
            leaving = owner(replicas)
            os.killpg(leaving.process.pid, signal.SIGTERM)
            wait_for(
                lambda: balancer.server_states().get(leaving.name) != "UP",
                timeout=10,
                what="haproxy kept the draining replica UP",
            )
            seqs += [(await session.send_frame(frame(k))).seq for k in range(30, 60)]
            return seqs, session, await session.close(), leaving

    seqs, session, summary, leaving = asyncio.run(run())
    leaving.process.wait(timeout=20)
    assert seqs == list(range(60))
    assert summary.resumes == 1 and session.resumptions[0].cause.startswith("moving")
    print(
        f"async: moved in {1e3 * session.resumptions[0].took:.0f} ms from tick {session.resumptions[0].from_seq}"
    )
    row = session_row(index_url, session.opened.session_id)
    assert row is not None and row["status"] == "COMPLETE"
    assert stored_seqs(tmp_path / "shared-folder", str(row["location"])) == list(range(60))


def test_an_async_realtime_session_resumes_and_its_record_keeps_every_frame(
    start_replica: Callable[..., Replica],
    start_balancer: Callable[..., Balancer],
    index_url: str,
    tmp_path: Path,
) -> None:
    """As the sync REALTIME test, with a producer and a consumer task: the producer's writes wait
    while the reader task resumes, and no tick goes unanswered."""
    replicas, balancer = cluster(start_replica, start_balancer, tmp_path)
    ticks = 80
    answered: dict[int, float] = {}

    async def run() -> tuple[AsyncSession, Summary]:
        async with AsyncClient(balancer.address, timeout=30) as client:
            session = await client.open_session(
                SessionOptions(
                    inline_mjcf=new_model(), inline_name="pendulum_2_inline", dt=DT, clock="REALTIME"
                )
            )

            async def produce() -> None:
                for k in range(ticks):
                    await asyncio.sleep(max(0.0, k * DT - session.now()))
                    await session.send(frame(k))
                    if k == 30:
                        await asyncio.to_thread(lambda: owner(replicas).kill())

            async def consume() -> None:
                async for answer in session.results(timeout=10):
                    if isinstance(answer, TickResult) and answer.source != "CORRECTED":
                        answered.setdefault(answer.seq, answer.received_at - session.clock_start)
                        if answer.seq == ticks - 1:
                            return

            await asyncio.gather(produce(), consume())
            return session, await session.close()

    session, summary = asyncio.run(run())
    late = [k for k, at in answered.items() if at > k * DT + session.opened.grace]
    print(
        f"async: resumed {summary.resumes}x (from tick {session.resumptions[0].from_seq} in "
        f"{1e3 * session.resumptions[0].took:.0f} ms); ticks missed {summary.missed}; answered late: {sorted(late)}"
    )
    assert summary.resumes == 1 and summary.missed == 0
    assert sorted(answered) == list(range(ticks)), (
        f"ticks unanswered: {sorted(set(range(ticks)) - set(answered))}"
    )
    row = session_row(index_url, session.opened.session_id)
    assert row is not None and row["status"] == "COMPLETE"
    assert_every_frame_kept(tmp_path / "shared-folder" / str(row["location"]), ticks)


def test_an_async_session_s_resume_buffer_is_bounded_and_resumption_can_be_off(
    start_replica: Callable[..., Replica], tmp_path: Path
) -> None:
    replica = start_replica("r0", HOSTS[0], data=tmp_path / "shared-folder", extra=FAST)

    async def bounded() -> list[int]:
        async with AsyncClient(replica.address, resume=ResumePolicy(max_unacknowledged=5)) as client:
            session = await client.open_session(options(new_model()))
            for k in range(5):
                await session.send(frame(k))  # pipelined: sent faster than a commit window
            assert session.unacknowledged == 5
            with pytest.raises(ResumeBufferFull, match="max_unacknowledged"):
                await session.send(frame(5))
            answered = []
            async for answer in session.results(timeout=10):
                answered.append(answer.seq)
                if len(answered) == 5:
                    break
            session.cancel()
            return answered

    assert asyncio.run(bounded()) == list(range(5))

    async def off() -> BaseException:
        async with AsyncClient(replica.address, resume=False) as client:
            session = await client.open_session(options(new_model()))
            await session.send_frame(frame(0))
            await asyncio.to_thread(replica.kill)
            with pytest.raises(JitdynError) as broken:
                for k in range(1, 40):
                    await session.send_frame(frame(k))
            return broken.value

    error = asyncio.run(off())
    print(f"async, with resume off: {type(error).__name__}: {error}")
    assert not isinstance(error, SessionLost)
