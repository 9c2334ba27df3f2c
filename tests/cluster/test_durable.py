"""Durable off the host, and sessions that outlive their replica (server side): with a shared
PostgreSQL index, every frame a result acknowledges (`durable_seq`) is in the shared tier, so a
replica killed with -9 whose folder is deleted loses none; a live replica stores a session nobody
resumes as RECOVERED; a resume on another replica continues the same session (one id, one record),
and the replica it was taken from can write nothing more to it (fencing by epoch)."""

from __future__ import annotations

import os
import shutil
import signal
import time
from collections.abc import Callable
from pathlib import Path

import grpc
import pyarrow.parquet as pq
import pytest
from _cluster import Replica, wait_for
from _raw import RawSession, new_model, open_message, resume_message, session_row

pytestmark = pytest.mark.postgres

# Short, so that the tests are: a replica silent for LEASE is taken for dead, and a session nobody
# resumes within RESUME after that is stored by a live replica.
LEASE, RESUME = "1s", "1s"
FAST = [f"--lease-ttl={LEASE}", f"--resume-timeout={RESUME}"]


def pair(
    start_replica: Callable[..., Replica], tmp_path: Path, names: tuple[str, str], hosts: tuple[str, str]
) -> tuple[Replica, Replica]:
    """Two replicas for a resume. They share one data folder only because model content is not
    in the shared tier yet (an inline model registered by one does not load on the other); their
    session logs are the shared tier's either way."""
    folder = tmp_path / "shared-folder"
    return tuple(  # type: ignore[return-value]
        start_replica(name, host, data=folder, extra=FAST) for name, host in zip(names, hosts, strict=True)
    )


def stored_seqs(replica: Replica, location: str) -> list[int]:
    table = pq.read_table(replica.data / location, columns=["kind", "seq"])
    return sorted(
        s for k, s in zip(table["kind"].to_pylist(), table["seq"].to_pylist(), strict=True) if k == "result"
    )


def test_killed_replica_with_its_folder_gone_loses_no_acknowledged_frame(
    start_replica: Callable[..., Replica], index_url: str
) -> None:
    doomed = start_replica("doomed", "127.0.0.11", extra=FAST)
    live = start_replica("live", "127.0.0.12", extra=FAST)
    session = RawSession(doomed.address, open_message(new_model()))
    acknowledged = -1
    for k in range(60):
        result = session.send(k)
        if result.HasField("durable_seq"):
            acknowledged = max(acknowledged, result.durable_seq)
    session_id = session.opened.session_id
    assert session.opened.resume_token, "a replica with a shared index makes sessions resumable"
    doomed.kill()
    shutil.rmtree(doomed.data)
    started = time.monotonic()
    wait_for(
        lambda: (session_row(index_url, session_id) or {}).get("status") == "RECOVERED",
        timeout=30,
        what="the live replica did not store the session as RECOVERED",
    )
    row = session_row(index_url, session_id)
    assert row is not None
    seqs = stored_seqs(live, str(row["location"]))
    print(
        f"acknowledged up to {acknowledged} of 60 answered; stored by the live replica "
        f"{time.monotonic() - started:.1f} s after the kill: ticks {seqs[0]}..{seqs[-1]} ({len(seqs)} rows)"
    )
    assert acknowledged >= 0
    assert seqs == list(range(len(seqs))) and seqs[-1] >= acknowledged


def test_a_resume_on_another_replica_continues_the_same_session(
    start_replica: Callable[..., Replica], index_url: str, tmp_path: Path
) -> None:
    first, second = pair(start_replica, tmp_path, ("first", "second"), ("127.0.0.13", "127.0.0.14"))
    mjcf = new_model()
    session = RawSession(first.address, open_message(mjcf))
    acknowledged = max(
        (r.durable_seq for r in (session.send(k) for k in range(40)) if r.HasField("durable_seq")), default=-1
    )
    first.kill()

    with pytest.raises(grpc.RpcError) as wrong:
        RawSession(second.address, resume_message(mjcf, session.opened, token="0" * 64))
    assert wrong.value.code() == grpc.StatusCode.PERMISSION_DENIED
    unknown = type(session.opened)(session_id="00000000-0000-4000-8000-000000000000", resume_token="x")
    with pytest.raises(grpc.RpcError) as missing:
        RawSession(second.address, resume_message(mjcf, unknown, token=session.opened.resume_token))
    assert missing.value.code() in (grpc.StatusCode.PERMISSION_DENIED, grpc.StatusCode.NOT_FOUND)

    started = time.monotonic()
    resumed = RawSession(second.address, resume_message(mjcf, session.opened))
    took = time.monotonic() - started
    opened = resumed.opened
    assert opened.session_id == session.opened.session_id
    # Every acknowledged tick is stored; so may be a few more, committed after the last answer
    # that the client read (the store commits what it holds before the kill, 38 of 40 in one CI run).
    assert opened.HasField("resume_from_seq") and acknowledged + 1 <= opened.resume_from_seq <= 40
    assert opened.resume_reason
    results = [resumed.send(k) for k in range(opened.resume_from_seq, 80)]
    assert results[0].reinitialised and results[0].seq == opened.resume_from_seq
    resumed.close()
    row = session_row(index_url, opened.session_id)
    assert row is not None and row["status"] == "COMPLETE"
    seqs = stored_seqs(second, str(row["location"]))
    print(
        f"resumed in {1e3 * took:.0f} ms from tick {opened.resume_from_seq}: stored ticks 0..{seqs[-1]}, one session"
    )
    assert seqs == list(range(80))


def test_the_replica_a_session_was_taken_from_cannot_write_to_it(
    start_replica: Callable[..., Replica], index_url: str, tmp_path: Path
) -> None:
    old, new = pair(start_replica, tmp_path, ("old", "new"), ("127.0.0.15", "127.0.0.16"))
    mjcf = new_model()
    session = RawSession(old.address, open_message(mjcf))
    for k in range(20):
        session.send(k)
    time.sleep(0.3)  # every answer so far committed
    resumed = RawSession(new.address, resume_message(mjcf, session.opened))
    # The old stream, still open (its replica never learnt of the resume), goes on writing: its
    # rows are refused by epoch, and the stream ends.
    with pytest.raises(grpc.RpcError) as fenced:
        for k in range(20, 200):
            session.send(k)
            time.sleep(0.01)
    print(f"the old stream ended: {fenced.value.code().name}: {fenced.value.details()}")
    # UNAVAILABLE: a status the SDK resumes (its session lives on with the stream that took it).
    assert fenced.value.code() == grpc.StatusCode.UNAVAILABLE
    assert "taken over" in (fenced.value.details() or "")
    start = resumed.opened.resume_from_seq
    for k in range(start, start + 10):
        resumed.send(k)
    resumed.close()
    row = session_row(index_url, resumed.opened.session_id)
    assert row is not None
    assert stored_seqs(new, str(row["location"])) == list(range(start + 10))


def test_sigterm_drains_a_replica_its_sessions_move_and_it_exits(
    start_replica: Callable[..., Replica], index_url: str, tmp_path: Path
) -> None:
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    leaving, staying = pair(start_replica, tmp_path, ("leaving", "staying"), ("127.0.0.17", "127.0.0.18"))
    mjcf = new_model()
    session = RawSession(leaving.address, open_message(mjcf))
    for k in range(30):
        session.send(k)
    signalled = time.monotonic()
    os.killpg(leaving.process.pid, signal.SIGTERM)
    notice = session.next()
    assert notice.WhichOneof("payload") == "moving", notice
    told = time.monotonic() - signalled
    with grpc.insecure_channel(leaving.address) as channel:
        health = health_pb2_grpc.HealthStub(channel).Check(
            health_pb2.HealthCheckRequest(service="jitdyn.v1.DynamicsService"), timeout=5
        )
    assert health.status == health_pb2.HealthCheckResponse.NOT_SERVING
    resumed = RawSession(staying.address, resume_message(mjcf, session.opened))
    session.drop()
    assert resumed.opened.resume_from_seq == notice.moving.durable_seq + 1
    leaving.process.wait(timeout=15)
    exited = time.monotonic() - signalled
    for k in range(resumed.opened.resume_from_seq, 50):
        resumed.send(k)
    resumed.close()
    row = session_row(index_url, resumed.opened.session_id)
    assert row is not None and row["status"] == "COMPLETE"
    print(
        f"moving {1e3 * told:.0f} ms after SIGTERM (durable_seq {notice.moving.durable_seq}); the replica "
        f"exited {exited:.1f} s after it; stored ticks 0..49 on the other"
    )
    assert stored_seqs(staying, str(row["location"])) == list(range(50))
