"""Bound resume tokens through real replicas: a token is the session's, its
tenant's and its lease epoch's, and expires; a forged, altered, other tenant's, expired or stale
token is refused PERMISSION_DENIED with a line that names what was wrong and never repeats the
token; each resume's `opened` hands the SDK the next token, so a session resumes twice in a row
(sync and asyncio); no token shows in `Opened`'s repr or in a replica's log."""

from __future__ import annotations

import asyncio
import re
import time
from collections.abc import Callable
from pathlib import Path

import grpc
import pytest
import sqlalchemy as sa
from _cluster import Balancer, Replica, behind_haproxy, session_owner
from _raw import RawSession, new_model, open_message, resume_message, session_row

from jitdyn.client import AsyncClient, AsyncSession, Client, FrameData, SessionOptions, Summary
from jitdyn.server.runtime.resume import ResumeTokens
from jitdyn.v1 import dynamics_pb2

pytestmark = pytest.mark.postgres

FAST = ["--lease-ttl=1s", "--resume-timeout=5s"]
HOSTS = ("127.0.0.31", "127.0.0.32", "127.0.0.33")
DT = 0.05
KEY_A, KEY_B = "a" * 32, "b" * 32
# Whatever a replica would print of a token: its version, claims and signature.
TOKEN_SHAPE = re.compile(r"v1\.[A-Za-z0-9_-]{16,}\.[A-Za-z0-9_-]{43}")


def frame(k: int) -> FrameData:
    return FrameData(seq=k, t=k * DT, qpos=[0.3 * (k % 7), 0.1], qvel=[0.0, 0.0])


def options(mjcf: str) -> SessionOptions:
    return SessionOptions(inline_mjcf=mjcf, inline_name="pendulum_2_inline", dt=DT)


owner = session_owner


def lease(index_url: str, session_id: str) -> tuple[int, int]:
    """(epoch, token_epoch) of the session's lease: the epoch it is held under, and that of the
    newest resume token presented for it."""
    engine = sa.create_engine(index_url)
    try:
        with engine.connect() as conn:
            row = conn.execute(
                sa.text("SELECT epoch, token_epoch FROM session_leases WHERE session_id = :id"),
                {"id": session_id},
            ).one()
        return int(row.epoch), int(row.token_epoch)
    finally:
        engine.dispose()


def refused(address: str, message: dynamics_pb2.OpenSession, *, api_key: str | None = None) -> str:
    """The details of a resume refused PERMISSION_DENIED, checked to hold no token."""
    with pytest.raises(grpc.RpcError) as error:
        RawSession(address, message, api_key=api_key)
    assert error.value.code() == grpc.StatusCode.PERMISSION_DENIED, error.value
    details = error.value.details() or ""
    assert not TOKEN_SHAPE.search(details), details
    print(f"refused: {details}")
    return details


def no_token_logged(replicas: list[Replica], *tokens: str) -> None:
    for replica in replicas:
        log = replica.log.read_text()
        assert not TOKEN_SHAPE.search(log), f"{replica.name} logged a resume token"
        assert not any(token and token in log for token in tokens), f"{replica.name} logged a token"


def test_a_session_resumes_twice_in_a_row_on_the_newest_token_and_an_older_one_is_stale(
    start_replica: Callable[..., Replica],
    start_balancer: Callable[..., Balancer],
    index_url: str,
    tmp_path: Path,
) -> None:
    replicas, balancer = behind_haproxy(
        start_replica, start_balancer, tmp_path / "shared-folder", HOSTS, extra=FAST
    )
    with Client(balancer.address, timeout=30) as client:
        session = client.open_session(options(new_model()))
        first_token, session_id = session.opened.resume_token, session.opened.session_id
        assert first_token and first_token not in repr(session.opened)
        assert lease(index_url, session_id) == (1, 0)
        seqs = [session.send_frame(frame(k)).seq for k in range(20)]
        owner(replicas).kill()
        seqs += [session.send_frame(frame(k)).seq for k in range(20, 40)]
        assert lease(index_url, session_id) == (2, 1), "the first resume presented the epoch-1 token"
        owner(replicas).kill()
        seqs += [session.send_frame(frame(k)).seq for k in range(40, 60)]
        assert lease(index_url, session_id) == (3, 2), "the second resume presented the epoch-2 token"
        # The token of the first `opened` has been passed by a newer one: stale, even though it
        # has not expired; the session goes on undisturbed.
        last = owner(replicas)
        stale = dynamics_pb2.SessionOpened(session_id=session_id, resume_token=first_token)
        details = refused(last.address, resume_message(new_model(), stale))
        assert "is stale" in details and "epoch 1" in details
        seqs += [session.send_frame(frame(k)).seq for k in range(60, 70)]
        summary = session.close()
    assert seqs == list(range(70)) and summary.resumes == 2
    row = session_row(index_url, session_id)
    assert row is not None and row["status"] == "COMPLETE"
    no_token_logged(replicas, first_token)


def test_an_async_session_resumes_twice_in_a_row_on_the_newest_token(
    start_replica: Callable[..., Replica],
    start_balancer: Callable[..., Balancer],
    index_url: str,
    tmp_path: Path,
) -> None:
    replicas, balancer = behind_haproxy(
        start_replica, start_balancer, tmp_path / "shared-folder", HOSTS, extra=FAST
    )

    async def run() -> tuple[list[int], AsyncSession, Summary, list[tuple[int, int]]]:
        async with AsyncClient(balancer.address, timeout=30) as client:
            session = await client.open_session(options(new_model()))
            assert session.opened.resume_token not in repr(session.opened)
            leases = []
            seqs = [(await session.send_frame(frame(k))).seq for k in range(20)]
            for upto in (40, 60):
                await asyncio.to_thread(lambda: owner(replicas).kill())
                seqs += [(await session.send_frame(frame(k))).seq for k in range(upto - 20, upto)]
                leases.append(lease(index_url, session.opened.session_id))
            return seqs, session, await session.close(), leases

    seqs, session, summary, leases = asyncio.run(run())
    assert seqs == list(range(60)) and summary.resumes == 2
    assert leases == [(2, 1), (3, 2)], "each resume presented the token the one before handed out"
    row = session_row(index_url, session.opened.session_id)
    assert row is not None and row["status"] == "COMPLETE"
    no_token_logged(replicas, session.opened.resume_token)


def test_forged_altered_other_tenant_s_and_expired_tokens_are_refused_saying_why(
    start_replica: Callable[..., Replica], index_url: str, tmp_path: Path
) -> None:
    """Two replicas with two tenants' API keys and tokens that last 2 s. The stream renews its
    client's token on a result every second; the renewed token resumes the session after the
    first one has expired."""
    keys = tmp_path / "api-keys"
    keys.write_text(f"{KEY_A} tenant-a\n{KEY_B} tenant-b\n")
    keys.chmod(0o600)
    extra = [*FAST, "--resume-token-ttl=2s", f"--api-keys={keys}"]
    folder = tmp_path / "shared-folder"
    first, second = (
        start_replica(f"t{n}", host, data=folder, extra=extra) for n, host in enumerate(HOSTS[:2])
    )
    mjcf = new_model()
    session = RawSession(first.address, open_message(mjcf), api_key=KEY_A)
    opened_at = time.monotonic()  # the first token was issued before: it expires within 2 s of this
    opened = session.opened
    token = opened.resume_token
    for k in range(5):
        session.send(k)

    version, payload, mac = token.split(".")
    flipped = mac[:-1] + ("A" if mac[-1] != "A" else "B")
    forgeries = {
        "bad signature": f"{version}.{payload}.{flipped}",
        "made with another server secret": ResumeTokens(bytes(32), ttl=600).issue(
            opened.session_id, tenant="tenant-a", epoch=1
        ),
        "is not a resume token of this service": "0" * 64,
    }
    for reason, forged in forgeries.items():
        details = refused(second.address, resume_message(mjcf, opened, token=forged), api_key=KEY_A)
        assert reason in details and forged not in details
    details = refused(second.address, resume_message(mjcf, opened), api_key=KEY_B)
    assert "issued to another tenant" in details and "tenant-a" not in details

    renewed, k = "", 5
    while time.monotonic() - opened_at < 2.3:
        result = session.send(k)
        renewed = result.resume_token or renewed
        k += 1
        time.sleep(0.05)
    assert renewed and renewed != token, "the stream renewed the token on a result"
    details = refused(second.address, resume_message(mjcf, opened), api_key=KEY_A)
    assert "expired" in details

    resumed = RawSession(second.address, resume_message(mjcf, opened, token=renewed), api_key=KEY_A)
    session.drop()
    start = resumed.opened.resume_from_seq
    assert resumed.opened.resume_token not in (token, renewed)
    for seq in range(start, k + 5):
        resumed.send(seq)
    resumed.close()
    row = session_row(index_url, opened.session_id)
    assert row is not None and row["status"] == "COMPLETE"
    no_token_logged([first, second], token, renewed, *forgeries.values())
