"""What an operator of replicas sees on /metrics when sessions move and storage falters, scraped
from real `jitdyn serve` replicas sharing the run's PostgreSQL: a resume counted where it landed and
a fence where the session was taken from; a session nobody resumed counted by the replica that
stored it; commit windows PostgreSQL did not take (a replica's connection to it cut by closing its
forward); and a finished session's Parquet waiting in the folder while the data root (moto's S3)
is down, and gone from the count once it is back."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import grpc
import pytest
from _cluster import MotoS3, Replica, TcpForward, free_port, wait_for
from _raw import RawSession, new_model, open_message, resume_message, session_row
from test_data_root import s3, s3_env

pytestmark = pytest.mark.postgres

FAST = ["--lease-ttl=1s", "--resume-timeout=1s"]


def _metric(replica: Replica, name: str) -> float:
    return replica.metrics().get(name, 0.0)


def test_resumes_fences_and_claims_are_counted_where_they_happen(
    start_replica: Callable[..., Replica], index_url: str, tmp_path: Path
) -> None:
    # One data folder: an inline model registered by one replica loads on the others (test_durable).
    folder = tmp_path / "shared-folder"
    old, new, doomed = (
        start_replica(name, host, data=folder, extra=FAST)
        for name, host in (("old", "127.0.0.61"), ("new", "127.0.0.62"), ("doomed", "127.0.0.63"))
    )
    mjcf = new_model()
    session = RawSession(old.address, open_message(mjcf))
    for k in range(20):
        session.send(k)
    time.sleep(0.3)
    resumed = RawSession(new.address, resume_message(mjcf, session.opened))
    with pytest.raises(grpc.RpcError):  # the old stream's next commit is refused by epoch
        for k in range(20, 200):
            session.send(k)
            time.sleep(0.01)
    resumed.close()
    orphan = RawSession(doomed.address, open_message(mjcf))
    for k in range(10):
        orphan.send(k)
    doomed.kill()
    wait_for(
        lambda: (session_row(index_url, orphan.opened.session_id) or {}).get("status") == "RECOVERED",
        timeout=30,
        what="no live replica stored the dead replica's session",
    )
    # The fence reaches the counter within a second (the committer's counts are copied each second).
    wait_for(lambda: _metric(old, "jitdyn_sessions_fenced_total") == 1, timeout=5, what="no fence counted")
    counts = {
        r.name: {
            kind: _metric(r, f"jitdyn_sessions_{kind}_total") for kind in ("resumed", "fenced", "claimed")
        }
        for r in (old, new)
    }
    print(counts)
    assert counts["old"]["resumed"] == 0 and counts["new"]["resumed"] == 1
    assert counts["old"]["fenced"] == 1 and counts["new"]["fenced"] == 0
    assert counts["old"]["claimed"] + counts["new"]["claimed"] == 1


# 13 s: runs with the slow tests (pytest -m slow), to keep CI under 20 minutes.
@pytest.mark.slow
def test_commit_errors_and_files_awaiting_upload_are_counted(
    start_replica: Callable[..., Replica], index_url: str, tmp_path: Path
) -> None:
    port = free_port()
    forward = TcpForward(listen=("127.0.0.1", port), target=("127.0.0.1", 5432))
    across = index_url.replace("127.0.0.1:5432", f"127.0.0.1:{port}")
    bucket = "jitdyn-metrics"
    store = MotoS3.start(workdir=tmp_path / "moto")
    try:
        s3(store).create_dir(bucket)
        replica = start_replica(
            "counted",
            "127.0.0.64",
            index_url=across,
            extra=[f"--data-root=s3://{bucket}", *FAST],
            env=s3_env(store),
        )
        assert _metric(replica, "jitdyn_commit_errors_total") == 0
        session = RawSession(replica.address, open_message(new_model()))
        for k in range(10):
            session.send(k)
        forward.close()  # PostgreSQL no longer answers this replica: its windows wait, retried
        for k in range(10, 40):
            session.send(k)  # answered all the same: answering needs no database
            time.sleep(0.02)
        wait_for(
            lambda: _metric(replica, "jitdyn_commit_errors_total") >= 1,
            timeout=5,
            what="no commit error counted while PostgreSQL did not answer",
        )
        errors = _metric(replica, "jitdyn_commit_errors_total")
        forward = TcpForward(listen=("127.0.0.1", port), target=("127.0.0.1", 5432))
        store.close()  # the data root is down when the session closes: its Parquet waits
        closed = session.close()
        assert not closed.summary.location.startswith("s3://")
        wait_for(
            lambda: _metric(replica, "jitdyn_files_awaiting_upload") == 1,
            timeout=15,
            what="the file kept in the folder was not counted",
        )
        with MotoS3.start(workdir=tmp_path / "moto-again", port=store.port) as back:
            s3(back).create_dir(bucket)
            wait_for(
                lambda: _metric(replica, "jitdyn_files_awaiting_upload") == 0,
                timeout=20,
                what="the published file was still counted",
            )
    finally:
        store.close()
        forward.close()
    print(f"{errors:g} commit windows not taken while PostgreSQL was cut")
