"""One data root: two replicas, each with its own data folder, publish their finished sessions'
Parquet to one S3 bucket (moto_server), and the PostgreSQL index holds each file's URI; `jitdyn
sessions list | show | export | query` run from a third machine (an empty folder, only the index
URL and the S3 settings) see both sessions, DuckDB querying their frames on S3; a replica's folder
deleted after its session ended loses nothing; and a session that ends while the object store is
down waits in its replica's folder until the store answers, then moves to the root."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

import pyarrow.fs as pafs
import pyarrow.parquet as pq
import pytest
import sqlalchemy as sa
from _cluster import REPO, MotoS3, Replica, tool, wait_for
from _raw import PENDULUM, RawSession, open_message, session_row

pytestmark = pytest.mark.postgres


def s3_env(server: MotoS3) -> dict[str, str]:
    """The usual AWS settings, as an operator exports them (moto takes any keys)."""
    return {
        "AWS_ENDPOINT_URL": server.endpoint_url,
        "AWS_REGION": "us-east-1",
        "AWS_ACCESS_KEY_ID": "testing",
        "AWS_SECRET_ACCESS_KEY": "testing",
    }


def s3(server: MotoS3) -> pafs.S3FileSystem:
    return server.filesystem()


def one_session(replica: Replica, ticks: int) -> tuple[str, str]:
    """A LOCKSTEP session of `ticks` frames on `replica`, closed: its id and stored location."""
    session = RawSession(replica.address, open_message(PENDULUM))
    for k in range(ticks):
        session.send(k)
    closed = session.close()
    return session.opened.session_id, closed.summary.location


def sessions_cli(*args: str, cwd: Path, env: dict[str, str]) -> str:
    """`jitdyn sessions ARGS` as a user on another machine runs it: a folder of its own, and in its
    environment nothing of the replicas' but the index URL and the S3 settings."""
    result = subprocess.run(
        [tool("jitdyn"), "sessions", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    return result.stdout


# 12 s: runs with the slow tests (pytest -m slow), to keep CI under 20 minutes.
@pytest.mark.slow
def test_two_replicas_publish_to_one_bucket_that_a_third_machine_reads(
    start_replica: Callable[..., Replica], index_url: str, moto_s3: MotoS3, tmp_path: Path
) -> None:
    bucket = "jitdyn-cluster"
    s3(moto_s3).create_dir(bucket)
    root = f"s3://{bucket}/prod"
    env = s3_env(moto_s3)
    replicas = [
        start_replica(name, host, extra=[f"--data-root={root}"], env=env)
        for name, host in (("east", "127.0.0.41"), ("west", "127.0.0.42"))
    ]
    assert replicas[0].data != replicas[1].data
    stored = {}
    for replica, ticks in zip(replicas, (12, 17), strict=True):
        session_id, location = one_session(replica, ticks)
        assert location.startswith(f"{root}/frames/model=pendulum_2/date=")
        assert location.endswith(f"/{session_id}.e1.parquet")  # stored under its first epoch
        assert (session_row(index_url, session_id) or {})["location"] == location
        assert replica.stored_sessions() == []  # published, so not kept in the replica's folder
        stored[session_id] = ticks

    # The first replica's host is lost with its disk: its session is on the root regardless.
    replicas[0].kill()
    shutil.rmtree(replicas[0].data)

    machine = tmp_path / "third-machine"
    machine.mkdir()
    cli_env = {"PATH": os.environ["PATH"], "HOME": str(machine), **env}
    index = f"--index={index_url}"
    listing = sessions_cli(index, "list", cwd=machine, env=cli_env)
    for session_id in stored:
        assert session_id in listing and "COMPLETE" in listing
    for session_id, ticks in stored.items():
        shown = sessions_cli(index, "show", session_id, cwd=machine, env=cli_env)
        details = json.loads(shown[shown.index("{") :])
        assert details["location"].startswith(f"{root}/frames/")
        assert details["summary"]["ticks"] == ticks
        out = machine / f"{session_id}.csv"
        sessions_cli(index, "export", session_id, "--format=csv", f"--out={out}", cwd=machine, env=cli_env)
        assert len(out.read_text().splitlines()) == 1 + ticks  # a header, then one row per answer

    answer = sessions_cli(
        index,
        "query",
        "SELECT f.session_id, f.model, count(*) AS ticks, max(f.seq) AS last FROM frames f "
        "JOIN sessions s USING (session_id) WHERE s.status = 'COMPLETE' GROUP BY ALL ORDER BY ticks",
        "--format=json",
        cwd=machine,
        env=cli_env,
    )
    rows = [json.loads(line) for line in answer.splitlines()]
    print(f"DuckDB over {root} on moto_server, from a third machine: {rows}")
    assert [(r["session_id"], r["model"], r["ticks"], r["last"]) for r in rows] == [
        (session_id, "pendulum_2", ticks, ticks - 1) for session_id, ticks in stored.items()
    ]
    page = (REPO / "docs" / "operating" / "replicas.md").read_text(encoding="utf-8")
    example = re.search(r'jitdyn sessions --index \S+ query \\\n\s*"(SELECT[^"]+)"', page)
    assert example, "the manual's section on the data root shows a query on S3"
    answer = sessions_cli(index, "query", example.group(1), "--format=json", cwd=machine, env=cli_env)
    assert [json.loads(line) for line in answer.splitlines()] == [
        {"model": "pendulum_2", "sessions": 2, "answers": sum(stored.values())}
    ]
    assert sorted(machine.iterdir()) == sorted(machine.glob("*.csv"))  # nothing else was made there


def test_a_session_ended_while_the_store_is_down_moves_to_the_root_once_it_answers(
    start_replica: Callable[..., Replica], index_url: str, tmp_path: Path
) -> None:
    store = MotoS3.start(workdir=tmp_path / "moto")
    bucket = "jitdyn-outage"
    try:
        s3(store).create_dir(bucket)
        replica = start_replica(
            "lonely", "127.0.0.43", extra=[f"--data-root=s3://{bucket}"], env=s3_env(store)
        )
    finally:
        store.close()  # down from here on: nothing answers at its endpoint

    session_id, location = one_session(replica, 9)
    assert location == f"frames/model=pendulum_2/date={location.split('date=')[1]}"
    assert (session_row(index_url, session_id) or {})["location"] == location
    assert (replica.data / location).is_file()  # kept, and the index names the file that is there
    assert "kept in the data folder, to be published again later" in replica.log.read_text()

    with MotoS3.start(workdir=tmp_path / "moto-again", port=store.port) as back:
        s3(back).create_dir(bucket)  # moto keeps nothing across a restart
        wait_for(
            lambda: str((session_row(index_url, session_id) or {})["location"]).startswith("s3://"),
            timeout=20,
            what="the replica did not publish the waiting session",
        )
        uri = str((session_row(index_url, session_id) or {})["location"])
        assert uri == f"s3://{bucket}/{location}"
        # The index names the bucket first, then the local copy goes (storage/publish.py): a
        # crash in between leaves two copies, never none.
        wait_for(
            lambda: not (replica.data / location).exists(),
            timeout=10,
            what="the published session's local copy was not deleted",
        )
        table = pq.read_table(uri.removeprefix("s3://"), filesystem=s3(back), columns=["seq"])
        assert table.column("seq").to_pylist() == list(range(9))
    assert f"session {session_id}: published to the data root now" in replica.log.read_text()


def test_a_session_closed_while_the_store_is_down_survives_its_replica_and_its_folder(
    start_replica: Callable[..., Replica], index_url: str, tmp_path: Path
) -> None:
    """The session's only off-host copy is its rows in PostgreSQL until the data root holds its
    Parquet: its replica killed and its folder deleted before the store is back, the next replica
    publishes it from those rows."""
    fast = ["--lease-ttl=1s", "--resume-timeout=1s"]
    store = MotoS3.start(workdir=tmp_path / "moto")
    bucket = "jitdyn-evicted"
    try:
        s3(store).create_dir(bucket)
        doomed = start_replica(
            "evicted", "127.0.0.44", extra=[f"--data-root=s3://{bucket}", *fast], env=s3_env(store)
        )
    finally:
        store.close()
    session_id, location = one_session(doomed, 120)
    assert not location.startswith("s3://")  # kept in the folder: the store did not answer
    doomed.kill()
    shutil.rmtree(doomed.data)
    with MotoS3.start(workdir=tmp_path / "moto-again", port=store.port) as back:
        s3(back).create_dir(bucket)
        started = time.monotonic()
        successor = start_replica(
            "successor", "127.0.0.45", extra=[f"--data-root=s3://{bucket}", *fast], env=s3_env(back)
        )
        wait_for(
            lambda: str((session_row(index_url, session_id) or {})["location"]).startswith("s3://"),
            timeout=30,
            what="no replica published the session from the shared log",
        )
        took = time.monotonic() - started
        uri = str((session_row(index_url, session_id) or {})["location"])
        table = pq.read_table(uri.removeprefix("s3://"), filesystem=s3(back), columns=["kind", "seq"])
        seqs = sorted(
            s
            for k, s in zip(table["kind"].to_pylist(), table["seq"].to_pylist(), strict=True)
            if k == "result"
        )
    print(f"{len(seqs)} of 120 frames in S3, published by {successor.name} {took:.1f} s after it started")
    assert seqs == list(range(120))
    # Published under the epoch of the replica that published it (it held the session to do so).
    assert (
        location.endswith(".e1.parquet")
        and uri == f"s3://{bucket}/{location[: -len('e1.parquet')]}e2.parquet"
    )
    assert (session_row(index_url, session_id) or {})["status"] == "COMPLETE"
    assert _log_rows(index_url, session_id) == 0  # the rows went once the store held the file
    assert "published to the data root from the shared log" in successor.log.read_text()


def _log_rows(index_url: str, session_id: str) -> int:
    engine = sa.create_engine(index_url)
    try:
        with engine.connect() as conn:
            return int(
                conn.execute(
                    sa.text("SELECT count(*) FROM session_log WHERE session_id = :id"), {"id": session_id}
                ).scalar_one()
            )
    finally:
        engine.dispose()
