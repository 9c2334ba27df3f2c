"""TLS at the edge: HAProxy with deploy/haproxy/haproxy.cfg as shipped (its frontend ends TLS,
`ssl crt ... alpn h2`) in front of the cleartext replicas, a CA and an edge certificate made here
with openssl. The sync and the asyncio SDK, trusting that CA (`ca_file=`), run sessions through
it to their close; a client trusting another CA, or none, gets no session, and an error that says
the TLS handshake failed."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from pathlib import Path

import pytest
from _cluster import Balancer, Replica, Unavailable, tool
from _tls import Authority
from test_balancer import TICKS, frames, options, run

from jitdyn.client import AsyncClient, Client, TickResult
from jitdyn.errors import InvalidArgument, JitdynError

pytestmark = pytest.mark.postgres


@pytest.fixture()
def pki(tmp_path: Path) -> Authority:
    return Authority.make(tmp_path / "pki")


@pytest.fixture()
def tls_balancer(replicas: list[Replica], pki: Authority, tmp_path: Path) -> Iterator[Balancer]:
    """HAProxy ending TLS with a certificate for 127.0.0.1 signed by `pki`, over the run's replicas."""
    try:
        tool("haproxy")
    except Unavailable as reason:
        pytest.skip(f"{reason} (apt-get install -y haproxy)")
    edge = pki.issue("edge", hosts=["127.0.0.1", "localhost"])
    with Balancer.start(replicas, workdir=tmp_path / "haproxy-tls", cert=edge.pem) as balancer:
        yield balancer


async def _async_session(address: str, ca: Path) -> tuple[int, int]:
    async with AsyncClient(address, ca_file=ca, timeout=30) as client:
        session = await client.open_session(options())
        answers = [await session.send_frame(frame) for frame in frames()]
        summary = await session.close()
    assert all(isinstance(a, TickResult) for a in answers), answers
    return len(answers), summary.frames


def test_the_sdk_trusting_the_edges_ca_runs_sessions_through_haproxy_ending_tls(
    tls_balancer: Balancer, pki: Authority
) -> None:
    with (
        Client(tls_balancer.address, ca_file=pki.ca, timeout=30) as client,
        client.open_session(options()) as session,
    ):
        answers = run(session)
        summary = session.close()
    async_answers, async_frames = asyncio.run(_async_session(tls_balancer.address, pki.ca))
    print(
        f"through TLS: {len(answers)} answers, {summary.frames} frames stored; asyncio {async_answers}, {async_frames}"
    )
    assert len(answers) == TICKS and summary.frames == TICKS
    assert async_answers == TICKS and async_frames == TICKS


@pytest.mark.parametrize("trust", ["another CA", "plaintext"])
def test_a_client_that_does_not_trust_the_edge_gets_no_session_and_a_clear_error(
    tls_balancer: Balancer, tmp_path: Path, trust: str
) -> None:
    ca_file = Authority.make(tmp_path / "other", name="another CA").ca if trust == "another CA" else None
    with (
        Client(tls_balancer.address, ca_file=ca_file, timeout=5, resume=False) as client,
        pytest.raises(JitdynError) as refused,
    ):
        client.open_session(options())
    message = str(refused.value)
    print(f"{trust}: {type(refused.value).__name__}: {message}")
    if trust == "another CA":
        assert "TLS handshake" in message and "CERTIFICATE_VERIFY_FAILED" in message, message
    assert "\n" not in message


def test_a_ca_file_that_is_not_there_or_not_pem_is_refused_in_one_line(tmp_path: Path) -> None:
    missing = tmp_path / "missing-ca.crt"
    with pytest.raises(InvalidArgument, match=r"^ca_file .*missing-ca\.crt: No such file or directory$"):
        Client("127.0.0.1:1", ca_file=missing)
    garbage = tmp_path / "not-pem.crt"
    garbage.write_text("hello\n")
    with pytest.raises(InvalidArgument, match=r"not-pem\.crt: holds no PEM certificate"):
        asyncio.run(_async_refused(garbage))


async def _async_refused(ca: Path) -> None:
    AsyncClient("127.0.0.1:1", ca_file=ca)
