"""Leases that keep both promises, real time and nothing lost, with a short TTL so that each case
runs in seconds: PostgreSQL cut off from every replica for longer than a lease and its resume
timeout, and back at a different moment for each, takes no session from its live owner; a replica
cut off from it alone (a host of its own, `ip netns`) hands its session to a healthy one through
the SDK, without an error or a lost frame."""

from __future__ import annotations

import asyncio
import json
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from _cluster import NetnsHost, Replica, TcpForward, free_port
from _raw import DT, RawSession, new_model, open_message, session_row
from test_durable import stored_seqs
from test_resume import frame

from jitdyn.client import AsyncClient, AsyncSession, Client, Session, SessionOptions

pytestmark = pytest.mark.postgres

TTL = 1.0  # s, the lease; sessions nobody resumes are claimed RESUME after it ran out
RESUME = 1.0
SHORT = [f"--lease-ttl={TTL:g}s", f"--resume-timeout={RESUME:g}s"]
OUTAGE = 2 * (TTL + RESUME)  # every lease ran out, and every resume timeout after it


def _through_forward(
    start_replica: Callable[..., Replica], index_url: str, name: str, host: str
) -> tuple[Replica, TcpForward, int]:
    port = free_port()
    forward = TcpForward(listen=("127.0.0.1", port), target=("127.0.0.1", 5432))
    across = index_url.replace("127.0.0.1:5432", f"127.0.0.1:{port}")
    return start_replica(name, host, index_url=across, extra=SHORT), forward, port


# gRPC's client-side balancing over the replicas' addresses, skipping one whose session service is
# NOT_SERVING in health (as HAProxy's check and a Kubernetes readiness probe do).
BALANCED = [
    (
        "grpc.service_config",
        json.dumps(
            {
                "loadBalancingConfig": [{"round_robin": {}}],
                "healthCheckConfig": {"serviceName": "jitdyn.v1.DynamicsService"},
            }
        ),
    )
]


def _open_on(replica: Replica, client: Client) -> Session:
    """A session the balancer put on `replica` (others it put elsewhere are closed)."""
    for _ in range(10):
        session = client.open_session(
            SessionOptions(inline_mjcf=new_model(), inline_name="pendulum_2_inline", dt=DT)
        )
        if replica.metrics().get("jitdyn_open_sessions", 0) == 1:
            return session
        session.close()
    raise AssertionError(f"the balancer never put a session on {replica.name}")


# The SDK's variant (15 s) runs with the slow tests (pytest -m slow), to keep CI under 20 minutes.
@pytest.mark.parametrize("client", ["raw", pytest.param("sdk", marks=pytest.mark.slow)])
def test_postgresql_down_for_every_replica_takes_no_session_from_its_live_owner(
    start_replica: Callable[..., Replica], index_url: str, client: str
) -> None:
    """The owner and another replica lose PostgreSQL together for longer than a lease and its
    resume timeout; the other gets it back first (the outage ended there first). The session goes
    on answering on its owner throughout the outage, is not claimed by the other, and is stored
    whole. The owner tells it to move (its leases passed their deadline): a raw client ignores
    that; the SDK tries the other replica, which cannot take it while the outage lasts, and stays;
    once the other is back first, the SDK's next try may move it there (the owner's lease did run
    out), without an error or a lost frame."""
    owner, owner_forward, owner_port = _through_forward(start_replica, index_url, "owner", "127.0.0.51")
    other, other_forward, other_port = _through_forward(start_replica, index_url, "other", "127.0.0.52")
    sdk = Client(f"ipv4:{owner.address},{other.address}", timeout=30, channel_options=BALANCED)
    raw = RawSession(owner.address, open_message(new_model())) if client == "raw" else None
    session = _open_on(owner, sdk) if raw is None else None
    k, worst = 0, 0.0

    def stream_for(seconds: float) -> None:
        nonlocal k, worst
        until = time.monotonic() + seconds
        while time.monotonic() < until:
            started = time.monotonic()
            if raw is not None:
                raw.send(k)
            else:
                assert session is not None
                session.send_frame(frame(k))
            worst = max(worst, time.monotonic() - started)
            k += 1
            time.sleep(0.02)

    try:
        stream_for(0.5)
        owner_forward.close()
        other_forward.close()
        stream_for(OUTAGE)
        during = worst
        other_forward = TcpForward(listen=("127.0.0.1", other_port), target=("127.0.0.1", 5432))
        stream_for(0.3)  # the other replica answers again, the owner not yet
        owner_forward = TcpForward(listen=("127.0.0.1", owner_port), target=("127.0.0.1", 5432))
        stream_for(2 * TTL)
        if raw is not None:
            ticks, session_id, stayed = raw.close().summary.ticks, raw.opened.session_id, bool(raw.moves)
        else:
            assert session is not None
            ticks, session_id = session.close().ticks, session.opened.session_id
            stayed = len(session.resumptions) <= 1  # and none while no replica could take it: `during`
    finally:
        sdk.close()
        owner_forward.close()
        other_forward.close()
    row = session_row(index_url, session_id)
    moved = [] if session is None else session.resumptions
    print(
        f"{client}: {k} frames answered, the slowest in {1e3 * during:.1f} ms during a {OUTAGE:g} s "
        f"outage of PostgreSQL for both replicas ({1e3 * worst:.1f} ms in all; moves after it: "
        f"{[(r.from_seq, round(r.took, 2)) for r in moved]}); stored as {row and row['status']} with "
        f"{ticks} ticks"
    )
    assert during < 0.1
    assert stayed
    assert row is not None and row["status"] == "COMPLETE"
    holder = owner if (owner.data / str(row["location"])).exists() else other  # the SDK's may have moved
    assert stored_seqs(holder, str(row["location"])) == list(range(k))
    assert "nobody resumed it" not in other.log.read_text()


def test_a_replica_cut_off_from_postgresql_alone_hands_its_session_to_a_healthy_one(
    netns_host: NetnsHost, start_replica: Callable[..., Replica], index_url: str, tmp_path: Path
) -> None:
    """The owner, on a host of its own, loses PostgreSQL (its forward stops) while its client
    streams through the SDK to `ipv4:owner,healthy`; the healthy replica reaches PostgreSQL. The
    owner's leases pass their renew deadline, it tells the session to move, the SDK opens it on the
    healthy replica while the owner still answers, and re-sends what was not durable: one session,
    no error, every answered frame stored, before anyone could have claimed it as an orphan."""
    folder = tmp_path / "shared-folder"
    forward = TcpForward(listen=(netns_host.host_ip, 5432), target=("127.0.0.1", 5432))
    across = index_url.replace("127.0.0.1:5432", f"{netns_host.host_ip}:5432")
    try:
        with Replica.start(
            "cut",
            host=netns_host.peer_ip,
            port=50051,
            data=folder,
            index_url=across,
            prefix=netns_host.prefix,
            extra=["--insecure", *SHORT],
        ) as cut:
            healthy = start_replica("healthy", "127.0.0.53", data=folder, extra=SHORT)
            target = f"ipv4:{cut.address},{healthy.address}"
            with Client(target, timeout=30, channel_options=BALANCED) as client:
                session = _open_on(cut, client)
                seqs = [session.send_frame(frame(k)).seq for k in range(25)]
                forward.close()
                cut_at = time.monotonic()
                k = 25
                while not session.resumptions and time.monotonic() - cut_at < 4 * TTL + RESUME:
                    seqs.append(session.send_frame(frame(k)).seq)
                    k += 1
                    time.sleep(0.02)
                moved_after = time.monotonic() - cut_at
                seqs += [session.send_frame(frame(j)).seq for j in range(k, k + 25)]
                summary = session.close()
    finally:
        forward.close()
    print(
        f"moved {moved_after:.2f} s after the cut (TTL {TTL:g} s): {session.resumptions}; "
        f"{len(seqs)} frames answered, {summary.ticks} ticks stored"
    )
    assert seqs == list(range(len(seqs)))
    assert len(session.resumptions) == 1 and session.resumptions[0].cause.startswith("moving")
    assert moved_after < 2 * TTL + RESUME
    row = session_row(index_url, session.opened.session_id)
    assert row is not None and row["status"] == "COMPLETE"
    assert stored_seqs(healthy, str(row["location"])) == list(range(len(seqs)))


@pytest.mark.slow  # 16 s; runs with the slow tests (pytest -m slow), to keep CI under 20 minutes
def test_replicas_whose_clocks_are_a_minute_off_take_nothing_from_each_other(
    start_replica: Callable[..., Replica], index_url: str
) -> None:
    """Expiry is judged on PostgreSQL's clock: an owner whose clock is 60 s behind, and another
    replica whose clock is 60 s ahead (libfaketime), share a session's lease for twice its TTL and
    resume timeout; the other never takes it, and the owner is never fenced."""
    faketime = shutil.which("faketime")
    if faketime is None:
        pytest.skip("faketime is not installed (apt-get install -y faketime)")
    # A lease of 2 s: the clocks are 60 s off either way, and the replicas under libfaketime on a
    # loaded machine renew less promptly than the 1 s lease of the other tests allows.
    leases = ["--lease-ttl=2s", "--resume-timeout=2s"]
    behind = start_replica("behind", "127.0.0.54", extra=leases, prefix=[faketime, "-m", "-f", "-60s"])
    ahead = start_replica("ahead", "127.0.0.55", extra=leases, prefix=[faketime, "-m", "-f", "+60s"])
    session = RawSession(behind.address, open_message(new_model()))
    k = 0
    until = time.monotonic() + 2 * (2 + 2)
    while time.monotonic() < until:
        session.send(k)
        k += 1
        time.sleep(0.02)
    closed = session.close()
    row = session_row(index_url, session.opened.session_id)
    print(f"{k} frames over 8 s between clocks 120 s apart: {closed.summary.ticks} stored")
    assert row is not None and row["status"] == "COMPLETE"
    assert stored_seqs(behind, str(row["location"])) == list(range(k))
    assert "nobody resumed it" not in ahead.log.read_text()


@pytest.mark.slow  # 23 s; runs with the slow tests (pytest -m slow), to keep CI under 20 minutes
def test_the_async_sdk_hands_over_too(
    netns_host: NetnsHost, start_replica: Callable[..., Replica], index_url: str, tmp_path: Path
) -> None:
    """As the test above, with `AsyncClient`: its reader task tries the move while the stream
    answers on."""
    folder = tmp_path / "shared-folder"
    forward = TcpForward(listen=(netns_host.host_ip, 5432), target=("127.0.0.1", 5432))
    across = index_url.replace("127.0.0.1:5432", f"{netns_host.host_ip}:5432")
    try:
        with Replica.start(
            "cut",
            host=netns_host.peer_ip,
            port=50051,
            data=folder,
            index_url=across,
            prefix=netns_host.prefix,
            extra=["--insecure", *SHORT],
        ) as cut:
            healthy = start_replica("healthy", "127.0.0.56", data=folder, extra=SHORT)
            target = f"ipv4:{cut.address},{healthy.address}"
            seqs, session = asyncio.run(_stream_async(target, cut, forward))
    finally:
        forward.close()
    print(f"async: moved {session.resumptions}; {len(seqs)} frames answered")
    assert seqs == list(range(len(seqs)))
    assert len(session.resumptions) == 1 and session.resumptions[0].cause.startswith("moving")
    row = session_row(index_url, session.opened.session_id)
    assert row is not None and row["status"] == "COMPLETE"
    assert stored_seqs(healthy, str(row["location"])) == list(range(len(seqs)))


async def _stream_async(target: str, cut: Replica, forward: TcpForward) -> tuple[list[int], AsyncSession]:
    async with AsyncClient(target, timeout=30, channel_options=BALANCED) as client:
        for _ in range(10):
            session = await client.open_session(
                SessionOptions(inline_mjcf=new_model(), inline_name="pendulum_2_inline", dt=DT)
            )
            if cut.metrics().get("jitdyn_open_sessions", 0) == 1:
                break
            await session.close()
        seqs = [(await session.send_frame(frame(k))).seq for k in range(25)]
        forward.close()
        cut_at, k = time.monotonic(), 25
        while not session.resumptions and time.monotonic() - cut_at < 4 * TTL + RESUME:
            seqs.append((await session.send_frame(frame(k))).seq)
            k += 1
            await asyncio.sleep(0.02)
        seqs += [(await session.send_frame(frame(j))).seq for j in range(k, k + 25)]
        await session.close()
        return seqs, session
