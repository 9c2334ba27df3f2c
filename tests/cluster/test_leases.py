"""Leases that keep both promises, real time and nothing lost, with a short TTL so that each case
runs in seconds: PostgreSQL cut off from every replica for longer than a lease and its resume
timeout, and back at a different moment for each, takes no session from its live owner; expiry is
judged on PostgreSQL's clock."""

from __future__ import annotations

import time
from collections.abc import Callable

import pytest
from _cluster import Replica, TcpForward, free_port
from _raw import RawSession, new_model, open_message, session_row
from test_durable import stored_seqs

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


def test_postgresql_down_for_every_replica_takes_no_session_from_its_live_owner(
    start_replica: Callable[..., Replica], index_url: str
) -> None:
    """The owner and another replica lose PostgreSQL together for longer than a lease and its
    resume timeout; the other gets it back first (the outage ended there first). The session goes
    on answering on its owner throughout, is not claimed by the other, and is stored whole."""
    owner, owner_forward, owner_port = _through_forward(start_replica, index_url, "owner", "127.0.0.51")
    other, other_forward, other_port = _through_forward(start_replica, index_url, "other", "127.0.0.52")
    session = RawSession(owner.address, open_message(new_model()))
    k, worst = 0, 0.0

    def stream_for(seconds: float) -> None:
        nonlocal k, worst
        until = time.monotonic() + seconds
        while time.monotonic() < until:
            started = time.monotonic()
            session.send(k)
            worst = max(worst, time.monotonic() - started)
            k += 1
            time.sleep(0.02)

    try:
        stream_for(0.5)
        owner_forward.close()
        other_forward.close()
        stream_for(OUTAGE)
        other_forward = TcpForward(listen=("127.0.0.1", other_port), target=("127.0.0.1", 5432))
        stream_for(0.3)  # the other replica answers again, the owner not yet
        owner_forward = TcpForward(listen=("127.0.0.1", owner_port), target=("127.0.0.1", 5432))
        stream_for(2 * TTL)
        closed = session.close()
    finally:
        owner_forward.close()
        other_forward.close()
    row = session_row(index_url, session.opened.session_id)
    print(
        f"{k} frames answered, the slowest in {1e3 * worst:.1f} ms, through a {OUTAGE:g} s outage of "
        f"PostgreSQL for both replicas; stored as {row and row['status']} with {closed.summary.ticks} ticks"
    )
    assert worst < 0.1
    assert row is not None and row["status"] == "COMPLETE"
    assert stored_seqs(owner, str(row["location"])) == list(range(k))
    assert "nobody resumed it" not in other.log.read_text()
