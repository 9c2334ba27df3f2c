"""The data root (storage/root.py, storage/publish.py): URIs normalised or refused in one line, a
shared folder and an S3 bucket on a real S3-speaking server (moto_server) written and read through
pyarrow.fs, and a session whose publish fails kept in the data folder until the root answers."""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable, Iterator
from pathlib import Path, PurePosixPath
from typing import Any

import pyarrow.dataset as pads
import pyarrow.fs as pafs
import pyarrow.parquet as pq
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "cluster"))

from _cluster import MotoS3, Unavailable, free_port

from jitdyn.errors import FailedPrecondition, InvalidArgument
from jitdyn.errors import Unavailable as UnavailableError
from jitdyn.storage.commit import GroupCommitter
from jitdyn.storage.export import export_session
from jitdyn.storage.index import SessionIndex
from jitdyn.storage.publish import publish_pending
from jitdyn.storage.query import run_query
from jitdyn.storage.recorder import SessionRecorder
from jitdyn.storage.records import SessionHeader
from jitdyn.storage.root import normalise_root_uri, open_data_root, open_location, resolve_data_root
from jitdyn.storage.shared import Fenced, SharedTier

from .conftest import build_header, build_records, postgres_index

BUCKET = "jitdyn-root"


@pytest.fixture(scope="module")
def moto(tmp_path_factory: pytest.TempPathFactory) -> Iterator[MotoS3]:
    try:
        server = MotoS3.start(workdir=tmp_path_factory.mktemp("moto"))
    except Unavailable as reason:
        pytest.skip(f"{reason} (pip install 'moto[server]', in the dev extra)")
    with server:
        s3 = server.filesystem()
        s3.create_dir(BUCKET)
        yield server


def s3_env(endpoint_url: str) -> dict[str, str]:
    """The usual AWS settings, as an operator exports them."""
    return {
        "AWS_ENDPOINT_URL": endpoint_url,
        "AWS_REGION": "us-east-1",
        "AWS_ACCESS_KEY_ID": "testing",
        "AWS_SECRET_ACCESS_KEY": "testing",
    }


@pytest.mark.parametrize(
    ("given", "expected"),
    [
        ("s3://bucket/some/prefix/", "s3://bucket/some/prefix"),
        ("s3://bucket", "s3://bucket"),
        ("S3://bucket//a//b", "s3://bucket/a/b"),
        ("file:///srv/jitdyn/", "file:///srv/jitdyn"),
        ("file://localhost/srv/jitdyn", "file:///srv/jitdyn"),
        ("/srv/jitdyn/", "file:///srv/jitdyn"),
    ],
)
def test_uris_are_normalised(given: str, expected: str) -> None:
    assert normalise_root_uri(given) == expected


def test_a_relative_path_is_made_absolute(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    assert normalise_root_uri("shared") == f"file://{tmp_path}/shared"


@pytest.mark.parametrize(
    ("given", "message"),
    [
        (
            "gs://bucket/p",
            (
                "--data-root scheme 'gs' is not supported; use s3://bucket/prefix, file:///path or a "
                "path, got 'gs://bucket/p'"
            ),
        ),
        ("s3://", "--data-root 's3://' names no bucket; write s3://BUCKET/PREFIX"),
        ("s3:///prefix", "--data-root 's3:///prefix' names no bucket; write s3://BUCKET/PREFIX"),
        (
            "s3://key:secret@bucket/p",
            (
                "--data-root 's3://key:secret@bucket/p': the bucket must be a plain name (keys and "
                "endpoint come from the AWS_* environment variables)"
            ),
        ),
        (
            "s3://bucket/p?endpoint_override=x",
            (
                "--data-root takes no ?query or #fragment (the S3 endpoint comes from "
                "AWS_ENDPOINT_URL), got 's3://bucket/p?endpoint_override=x'"
            ),
        ),
        (
            "file://nas/share",
            "--data-root 'file://nas/share' names a host; a file URI is file:///ABSOLUTE/PATH",
        ),
        (" ", "--data-root must be a URI (s3://bucket/prefix, file:///path) or a path, got ''"),
    ],
)
def test_bad_uris_are_refused_in_one_line(given: str, message: str) -> None:
    with pytest.raises(InvalidArgument) as raised:
        normalise_root_uri(given)
    assert str(raised.value) == message


def test_a_shared_folder_is_published_to_and_read_back(tmp_path: Path) -> None:
    shared = tmp_path / "shared"
    shared.mkdir()
    root = open_data_root(f"file://{shared}", environ={})
    source = tmp_path / "x.parquet"
    source.write_bytes(b"PAR1 not really")
    relative = "frames/model=m/date=2026-11-25/x.parquet"

    uri = root.publish(source, relative)

    assert uri == f"file://{shared}/{relative}"
    assert (shared / relative).read_bytes() == b"PAR1 not really"
    assert (shared / relative).stat().st_mode & 0o777 == 0o600
    assert [p.name for p in (shared / relative).parent.iterdir()] == ["x.parquet"]  # no temporary left
    filesystem, path = open_location(uri, data=tmp_path / "elsewhere", environ={})
    with filesystem.open_input_stream(path) as stream:
        assert stream.read() == b"PAR1 not really"
    assert list(shared.iterdir()) == [shared / "frames"]  # the write probe is gone


def test_a_missing_shared_folder_is_refused(tmp_path: Path) -> None:
    with pytest.raises(FailedPrecondition) as raised:
        open_data_root(str(tmp_path / "not-mounted"), environ={})
    assert str(raised.value) == (
        f"the data root file://{tmp_path}/not-mounted is not a folder; create it, or mount the shared "
        "folder there"
    )


def test_a_bucket_is_published_to_and_read_back(moto: MotoS3, tmp_path: Path) -> None:
    env = s3_env(moto.endpoint_url)
    root = open_data_root(f"s3://{BUCKET}/prod/", environ=env)
    assert (root.uri, root.base, root.local) == (f"s3://{BUCKET}/prod", f"{BUCKET}/prod", False)
    source = tmp_path / "y.parquet"
    source.write_bytes(bytes(range(256)) * 5000)  # beyond one copy chunk
    relative = "frames/model=m/date=2026-11-25/y.parquet"

    uri = root.publish(source, relative)

    assert uri == f"s3://{BUCKET}/prod/{relative}"
    assert root.exists(relative) and not root.exists("frames/absent.parquet")
    filesystem, path = open_location(uri, data=tmp_path, environ=env)
    assert path == f"{BUCKET}/prod/{relative}"
    with filesystem.open_input_stream(path) as stream:
        assert stream.read() == source.read_bytes()


def test_a_missing_bucket_is_refused(moto: MotoS3) -> None:
    with pytest.raises(FailedPrecondition) as raised:
        open_data_root("s3://no-such-bucket/p", environ=s3_env(moto.endpoint_url))
    assert str(raised.value) == (
        "the data root s3://no-such-bucket/p: bucket 'no-such-bucket' does not exist at the S3 endpoint; "
        "create it first (jitdyn creates no buckets)"
    )


def test_an_unreachable_endpoint_is_unavailable_with_its_reason() -> None:
    env = s3_env(f"http://127.0.0.1:{free_port()}")  # nobody listens there
    with pytest.raises(UnavailableError) as raised:
        open_data_root(f"s3://{BUCKET}/p", environ=env)
    message = str(raised.value)
    assert message.startswith(f"the data root s3://{BUCKET}/p cannot be reached: ")
    assert "\n" not in message and "Traceback" not in message
    assert "connect" in message.lower()  # the reason, as the S3 client gave it


def test_a_bad_endpoint_setting_is_refused() -> None:
    with pytest.raises(InvalidArgument) as raised:
        open_data_root(f"s3://{BUCKET}", environ={"AWS_ENDPOINT_URL": "ftp://127.0.0.1:1"})
    assert str(raised.value) == "AWS_ENDPOINT_URL must be http(s)://HOST[:PORT], got 'ftp://127.0.0.1:1'"


def test_stored_locations_resolve(tmp_path: Path) -> None:
    filesystem, path = open_location("frames/model=m/date=d/z.parquet", data=tmp_path, environ={})
    assert isinstance(filesystem, pafs.LocalFileSystem)
    assert path == f"{tmp_path}/frames/model=m/date=d/z.parquet"
    with pytest.raises(InvalidArgument) as raised:
        open_location("gs://b/z.parquet", data=tmp_path, environ={})
    assert str(raised.value) == "the stored location 'gs://b/z.parquet' is not on a file or s3 data root"


def test_a_failed_publish_keeps_the_session_and_a_later_one_moves_it(
    moto: MotoS3,
    data_root: Path,
    index: SessionIndex,
    make_header: Callable[..., SessionHeader],
    make_records: Any,
    caplog: pytest.LogCaptureFixture,
) -> None:
    live = open_data_root(f"s3://{BUCKET}/retry", environ=s3_env(moto.endpoint_url))
    # The same root while its endpoint is down: nobody listens where the S3 client is sent.
    dead = resolve_data_root(live.uri, environ=s3_env(f"http://127.0.0.1:{free_port()}"))
    header = make_header()
    records = make_records(30)

    with (
        caplog.at_level(logging.WARNING, logger="jitdyn.storage.publish"),
        SessionRecorder(data_root=data_root, index=index, header=header, root=dead) as recorder,
    ):
        for record in records:
            recorder.append(record)
        location = recorder.close()

    relative = f"frames/model=pendulum_3/date=2026-11-21/{header.session_id}.parquet"
    assert location == relative  # kept here: the index points at the file that is there
    assert index.get(header.session_id, tenant="").location == relative
    assert pq.read_table(data_root / relative).num_rows == len(records)
    assert any("kept in the data folder, to be published again later" in r.message for r in caplog.records)

    with pytest.raises(OSError):  # still down: the loop that calls it says so and tries again
        publish_pending(dead, data=data_root, index=index)
    assert (data_root / relative).is_file()

    assert publish_pending(live, data=data_root, index=index) == [header.session_id]
    row = index.get(header.session_id, tenant="")
    assert row.location == f"s3://{BUCKET}/retry/{relative}"
    assert not (data_root / relative).exists()
    filesystem, path = open_location(row.location, data=data_root, environ=s3_env(moto.endpoint_url))
    assert pq.read_table(path, filesystem=filesystem).num_rows == len(records)
    assert publish_pending(live, data=data_root, index=index) == []  # nothing left


def test_a_session_published_at_close_leaves_no_local_copy(
    moto: MotoS3,
    data_root: Path,
    index: SessionIndex,
    make_header: Callable[..., SessionHeader],
    make_records: Any,
) -> None:
    env = s3_env(moto.endpoint_url)
    root = open_data_root(f"s3://{BUCKET}/close", environ=env)
    header = make_header()
    records = make_records(12)
    with SessionRecorder(data_root=data_root, index=index, header=header, root=root) as recorder:
        for record in records:
            recorder.append(record)
        location = recorder.close()

    assert (
        location == f"s3://{BUCKET}/close/frames/model=pendulum_3/date=2026-11-21/{header.session_id}.parquet"
    )
    assert index.get(header.session_id, tenant="").location == location
    assert list((data_root / "frames").rglob("*.parquet")) == []
    filesystem, path = open_location(location, data=data_root, environ=env)
    assert pq.read_table(path, filesystem=filesystem).num_rows == len(records)


@pytest.fixture(params=["s3", "file"])
def root_and_env(request: pytest.FixtureRequest, tmp_path: Path) -> tuple[str, dict[str, str]]:
    """A data root, on moto's S3 or in a shared folder, and the environment that reaches it."""
    if request.param == "file":
        (tmp_path / "shared").mkdir()
        return str(tmp_path / "shared"), {}
    moto = request.getfixturevalue("moto")
    return f"s3://{BUCKET}/{request.node.name}", s3_env(moto.endpoint_url)


def test_query_and_export_read_the_data_root_from_an_empty_folder(
    root_and_env: tuple[str, dict[str, str]],
    data_root: Path,
    index: SessionIndex,
    make_header: Callable[..., SessionHeader],
    make_records: Any,
    tmp_path: Path,
) -> None:
    uri, env = root_and_env
    root = open_data_root(uri, environ=env)
    stored: dict[str, int] = {}
    for n, model in enumerate(("pendulum_3", "arm")):
        header = make_header(model_name=model)
        records = make_records(10 + n, seed=n)
        with SessionRecorder(data_root=data_root, index=index, header=header, root=root) as recorder:
            for record in records:
                recorder.append(record)
            assert recorder.close().startswith(root.uri + "/frames/")
        stored[header.session_id] = len(records)
    elsewhere = tmp_path / "another-machine"
    elsewhere.mkdir()

    table = run_query(
        "SELECT session_id, model, date, count(*) AS n FROM frames JOIN sessions USING (session_id) "
        "GROUP BY ALL ORDER BY model",
        data_root=elsewhere,
        engine=index.engine,
        environ=env,
    )

    assert [(r["model"], str(r["date"]), r["n"]) for r in table.to_pylist()] == [
        ("arm", "2026-11-21", stored[table["session_id"][0].as_py()]),
        ("pendulum_3", "2026-11-21", stored[table["session_id"][1].as_py()]),
    ]
    session_id = next(iter(stored))
    out = export_session(
        session_id, data_root=elsewhere, engine=index.engine, fmt="csv", out=elsewhere, environ=env
    )
    assert out == elsewhere / f"{session_id}.csv"
    assert len(out.read_text().splitlines()) == 1 + stored[session_id]


def test_readers_name_an_unreachable_root_in_one_line(
    moto: MotoS3,
    data_root: Path,
    index: SessionIndex,
    make_header: Callable[..., SessionHeader],
    make_records: Any,
    tmp_path: Path,
) -> None:
    root = open_data_root(f"s3://{BUCKET}/readers", environ=s3_env(moto.endpoint_url))
    header = make_header()
    with SessionRecorder(data_root=data_root, index=index, header=header, root=root) as recorder:
        for record in make_records(5):
            recorder.append(record)
        recorder.close()
    down = s3_env(f"http://127.0.0.1:{free_port()}")

    with pytest.raises(UnavailableError) as exported:
        export_session(
            header.session_id, data_root=tmp_path, engine=index.engine, fmt="csv", out=tmp_path, environ=down
        )
    with pytest.raises(UnavailableError) as queried:
        run_query("SELECT count(*) FROM frames", data_root=tmp_path, engine=index.engine, environ=down)

    assert str(exported.value).startswith(f"the Parquet file of session {header.session_id} cannot be read: ")
    assert str(queried.value).startswith(f"the data root holding {BUCKET}/readers/frames cannot be read: ")
    for error in (exported.value, queried.value):
        assert "\n" not in str(error) and "connect" in str(error).lower()


@pytest.mark.postgres
def test_a_stale_finisher_leaves_the_new_owners_object_alone(moto: MotoS3, tmp_path: Path) -> None:
    """Objects are fenced by the epoch in their key: a session taken over (epoch 2) and closed by
    its new owner, then closed late by its old holder (epoch 1, whose upload lands after): the index
    names the epoch-2 object, the late one is removed, and the data root's files hold the session
    once."""
    env = s3_env(moto.endpoint_url)
    root = open_data_root(f"s3://{BUCKET}/fenced", environ=env)
    header, records = build_header(), build_records(20)
    with postgres_index() as engine:
        index = SessionIndex(engine)
        old_tier = SharedTier(engine, owner="stale", lease_ttl=30)
        new_tier = SharedTier(engine, owner="owner", lease_ttl=30)
        with GroupCommitter(shared=old_tier) as old_commits, GroupCommitter(shared=new_tier) as new_commits:
            stale = SessionRecorder(
                data_root=tmp_path / "a",
                index=index,
                header=header,
                committer=old_commits,
                shared=old_tier,
                root=root,
            )
            for record in records[:10]:
                stale.append(record)
            stale.flush(timeout=10)
            taken = new_tier.take_over(header.session_id, tenant="", token_epoch=1)
            owner = SessionRecorder(
                data_root=tmp_path / "b",
                index=index,
                header=header,
                committer=new_commits,
                shared=new_tier,
                resumed=taken,
                root=root,
            )
            for record in records[10:]:
                owner.append(record)
            location = owner.close()
            with pytest.raises(Fenced):
                stale.close()
        indexed = index.get(header.session_id, tenant="").location
    s3 = moto.filesystem()
    folder = f"{BUCKET}/fenced/frames/model=pendulum_3/date=2026-11-21"
    names = [PurePosixPath(i.path).name for i in s3.get_file_info(pafs.FileSelector(folder))]
    dataset = pads.dataset(f"{BUCKET}/fenced/frames", filesystem=s3, format="parquet", partitioning="hive")
    table = dataset.to_table(columns=["session_id", "seq"])
    print(f"the data root holds {names}; the index names {indexed.rsplit('/', 1)[1]}")
    assert location == indexed == f"s3://{BUCKET}/fenced/frames/model=pendulum_3/date=2026-11-21/{names[0]}"
    assert names == [f"{header.session_id}.e2.parquet"]
    assert table.column("seq").to_pylist() == [r.seq for r in records]
