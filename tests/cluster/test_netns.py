"""A replica on a host of its own (a network namespace, a veth pair, the shared PostgreSQL index
reached across it) answers, and once its link is cut it does not, though the process runs on: new
connections find no route (UNAVAILABLE at once) or silence (DEADLINE_EXCEEDED), and open ones go
quiet, as when a host drops off the network; and a replica cut off while its session is resumed
elsewhere cannot, once back, store that session or touch its row (fencing by the lease's epoch)."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import grpc
import pytest
from _cluster import NetnsHost, Replica, wait_for
from _raw import RawSession, new_model, open_message, resume_message, session_row
from grpc_health.v1 import health_pb2, health_pb2_grpc
from test_durable import FAST, stored_seqs

pytestmark = pytest.mark.postgres

SESSION_SERVICE = "jitdyn.v1.DynamicsService"


def _health(address: str, *, timeout: float) -> int:
    with grpc.insecure_channel(address) as channel:
        stub = health_pb2_grpc.HealthStub(channel)
        return stub.Check(health_pb2.HealthCheckRequest(service=SESSION_SERVICE), timeout=timeout).status


def test_a_replica_in_its_own_namespace_answers_until_its_link_is_cut(
    netns_host: NetnsHost, index_url: str, tmp_path: Path
) -> None:
    index_across = index_url.replace("127.0.0.1:5432", netns_host.forward(5432))
    # Not a loopback address: jitdyn serve then wants TLS and API keys, or --insecure.
    with Replica.start(
        "cut",
        host=netns_host.peer_ip,
        port=50051,
        data=tmp_path / "cut",
        index_url=index_across,
        prefix=netns_host.prefix,
        extra=["--insecure"],
    ) as replica:
        assert _health(replica.address, timeout=5) == health_pb2.HealthCheckResponse.SERVING

        netns_host.cut()
        started = time.monotonic()
        with pytest.raises(grpc.RpcError) as silent:
            _health(replica.address, timeout=1.0)
        waited = time.monotonic() - started
        print(f"after the cut: {silent.value.code().name} after {waited:.2f} s")
        assert silent.value.code() in (grpc.StatusCode.DEADLINE_EXCEEDED, grpc.StatusCode.UNAVAILABLE)

        netns_host.restore()
        assert _health(replica.address, timeout=5) == health_pb2.HealthCheckResponse.SERVING


def test_a_replica_cut_off_and_back_cannot_write_to_the_session_taken_from_it(
    netns_host: NetnsHost, start_replica: Callable[..., Replica], index_url: str, tmp_path: Path
) -> None:
    """Fencing across a real cut: the session's owner drops off the network (its process runs on),
    the client resumes it on a live replica, and when the owner's link comes back its stream is
    dropped: the stale owner must not store the session nor touch its index row. One session, one
    record, continuous, written by the replica that took it over."""
    index_across = index_url.replace("127.0.0.1:5432", netns_host.forward(5432))
    with Replica.start(
        "cut",
        host=netns_host.peer_ip,
        port=50051,
        data=tmp_path / "cut",
        index_url=index_across,
        prefix=netns_host.prefix,
        extra=["--insecure", *FAST],
    ) as old:
        new = start_replica("new", "127.0.0.18", extra=FAST)
        mjcf = new_model()
        session = RawSession(old.address, open_message(mjcf))
        for k in range(20):
            session.send(k)
        time.sleep(0.3)  # every answer so far committed

        netns_host.cut()
        resumed = RawSession(new.address, resume_message(mjcf, session.opened))
        start = resumed.opened.resume_from_seq
        assert start == 20, start
        for k in range(start, start + 10):
            resumed.send(k)

        netns_host.restore()
        session.drop()  # the stale owner now learns its client is gone and ends its side
        wait_for(
            lambda: "taken over" in old.log.read_text(),
            timeout=15,
            what="the stale owner did not log that its session was taken over",
        )
        closed = resumed.close()
        assert closed.summary.ticks == 30, closed.summary  # the whole session, not its last part

    row = session_row(index_url, resumed.opened.session_id)
    assert row is not None and row["status"] == "COMPLETE", row
    assert stored_seqs(new, str(row["location"])) == list(range(30))
    assert not list((tmp_path / "cut").rglob(f"{resumed.opened.session_id}.parquet"))
