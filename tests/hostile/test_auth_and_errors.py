"""Finding 8: authentication abuse, key files others can read, storage failures as clients and
operators see them."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import grpc
import pytest
from _hostile import Served, honest_session, logs, open_request, stored

from jitdyn.v1 import model_registry_pb2

KEY = "k" * 8 + "0123456789abcdef"
OTHER = "x" * 24


def _keys(tmp_path: Path, mode: int = 0o600) -> Path:
    path = tmp_path / "api-keys"
    path.write_text(f"{KEY} lab-a\n")
    path.chmod(mode)
    return path


def _list(served: Served, *keys: str) -> model_registry_pb2.ListModelsResponse:
    metadata = [("authorization", f"Bearer {key}") for key in keys]
    return served.registry.ListModels(model_registry_pb2.ListModelsRequest(), metadata=metadata, timeout=30)  # type: ignore[no-any-return]


def test_several_authorization_headers_are_unauthenticated(
    serve: Callable[..., Served], tmp_path: Path
) -> None:
    served = serve("--api-keys", str(_keys(tmp_path)))
    assert _list(served, KEY).models
    with pytest.raises(grpc.RpcError) as caught:
        _list(served, OTHER, KEY)  # a guess, and the real key in case the guess is wrong
    assert caught.value.code() == grpc.StatusCode.UNAUTHENTICATED
    assert "send one metadata `authorization: Bearer <key>`" in (caught.value.details() or "")


# 9 s: runs with the slow tests (pytest -m slow), to keep CI under 20 minutes.
@pytest.mark.slow
def test_repeated_failures_from_one_peer_are_slowed(serve: Callable[..., Served], tmp_path: Path) -> None:
    served = serve("--api-keys", str(_keys(tmp_path)))
    waits = []
    for guess in range(8):
        started = time.monotonic()
        with pytest.raises(grpc.RpcError) as caught:
            _list(served, f"guess-{guess:016d}")
        waits.append(time.monotonic() - started)
        assert caught.value.code() == grpc.StatusCode.UNAUTHENTICATED
    assert waits[0] < 0.5  # one mistake costs nothing noticeable
    assert waits[-1] >= 1.5, waits  # the eighth guess in a row waits seconds
    started = time.monotonic()
    assert _list(served, KEY).models  # the right key is never slowed
    assert time.monotonic() - started < 1.0


def _start_fails(tmp_path: Path, env: dict[str, str], *args: str) -> tuple[int, list[str]]:
    done = subprocess.run(
        [sys.executable, "-m", "jitdyn.cli", "serve", "--address", "127.0.0.1:0", "--processes", "1", *args],
        check=False,
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
        cwd=tmp_path,
    )
    return done.returncode, (done.stdout + done.stderr).splitlines()


@pytest.mark.parametrize("mode", [0o644, 0o640, 0o604])
def test_key_files_others_can_read_are_refused_at_start(
    tmp_path: Path, env: dict[str, str], mode: int
) -> None:
    keys = _keys(tmp_path, mode)
    code, lines = _start_fails(tmp_path, env, "--data", str(tmp_path / "data"), "--api-keys", str(keys))
    assert code == 1  # an error, not a usage mistake (exit 2)
    assert lines == [
        (
            f"jitdyn serve: FailedPrecondition: --api-keys {keys} is accessible by group or others "
            f"(mode {mode:04o}); run `chmod 600 {keys}`"
        )
    ]
    cert = tmp_path / "cert.pem"
    cert.write_text("not checked before the key's mode\n")
    code, lines = _start_fails(
        tmp_path, env, "--data", str(tmp_path / "data"), "--tls-cert", str(cert), "--tls-key", str(keys)
    )
    assert code == 1  # an error, not a usage mistake (exit 2)
    assert lines == [
        (
            f"jitdyn serve: FailedPrecondition: --tls-key {keys} is accessible by group or others "
            f"(mode {mode:04o}); run `chmod 600 {keys}`"
        )
    ]


_CHECK_AS_POD_USER = """
import sys
from pathlib import Path
from jitdyn.errors import FailedPrecondition
from jitdyn.key_files import check_private_file
for name in sys.argv[1:]:
    try:
        check_private_file(Path(name), setting="--api-keys")
        print("accepted")
    except FailedPrecondition as error:
        print(error)
"""


def test_key_files_owned_by_root_may_be_read_by_their_group_as_a_secret_volume_mounts_them() -> None:
    """PostgreSQL's rule, checked by a process that is not root (as a pod's is): a root-owned key
    readable by its group (a Secret volume's 0440 root:fsGroup) is accepted; others reading it, its
    group writing it, or an owner that is neither root nor the server's user are refused."""
    setpriv = shutil.which("setpriv")
    if os.geteuid() != 0 or setpriv is None:
        pytest.skip("checking as another user needs root and setpriv")
    with tempfile.TemporaryDirectory(prefix="jitdyn-keys-") as name:  # pytest's tmp_path is root's only
        folder = Path(name)
        folder.chmod(0o755)
        _check_as_pod_user(folder, setpriv)


def _check_as_pod_user(folder: Path, setpriv: str) -> None:
    cases = {0o440: "accepted", 0o640: "accepted", 0o400: "accepted", 0o444: "others", 0o460: "others"}
    files = []
    for mode in cases:
        path = folder / f"root-{mode:04o}"
        path.write_text("k")
        os.chown(path, 0, 10001)
        path.chmod(mode)
        files.append(path)
    foreign = folder / "foreign"
    foreign.write_text("k")
    os.chown(foreign, 10002, 10001)
    foreign.chmod(0o440)
    done = subprocess.run(
        [
            setpriv,
            "--reuid=10001",
            "--regid=10001",
            "--groups=10001",
            sys.executable,
            "-c",
            _CHECK_AS_POD_USER,
            *map(str, files),
            str(foreign),
        ],
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
    )
    lines = done.stdout.splitlines()
    for (mode, expected), path, line in zip(cases.items(), files, lines, strict=False):
        if expected == "accepted":
            assert line == "accepted", (oct(mode), line)
        else:
            assert line == (
                f"--api-keys {path} is owned by root and accessible by others or writable by its group "
                f"(mode {mode:04o}); a key file root owns may be read by its group only: 0440 or 0640"
            )
    assert lines[-1] == (
        f"--api-keys {foreign} is owned by uid 10002, neither this server's user (uid 10001) nor root; "
        f"run `chown 10001 {foreign}`"
    )


def test_a_data_folder_that_cannot_be_written_stops_serve_in_one_line(
    tmp_path: Path, env: dict[str, str]
) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    code, lines = _start_fails(tmp_path, env, "--data", str(blocker / "data"))
    assert code == 1  # an error, not a usage mistake (exit 2)
    assert len(lines) == 1, lines
    assert lines[0].startswith(
        f"jitdyn serve: FailedPrecondition: the data folder {blocker / 'data'} cannot be written ("
    )


def test_storage_failures_are_unavailable_without_server_paths(serve: Callable[..., Served]) -> None:
    served = serve()
    honest_session(served)
    # The logs folder becomes a file: every new session's log fails, as on a full or read-only disk.
    shutil.rmtree(served.data / "logs")
    (served.data / "logs").write_text("")
    for _ in range(3):
        with pytest.raises(grpc.RpcError) as caught:
            list(served.dynamics.StreamSession(iter([open_request()]), timeout=30))
        assert caught.value.code() == grpc.StatusCode.UNAVAILABLE
        details = caught.value.details() or ""
        assert "the server's storage failed (details are in the server log); try again later" in details
        assert str(served.data) not in details and "Errno" not in details and "/" not in details
    # The operator's log has the path; the failed opens left no row and no file.
    assert str(served.data / "logs") in served.text()
    assert stored(served, "OPEN") == [] and stored(served, "FAILED") == []
    (served.data / "logs").unlink()
    honest_session(served)
    assert logs(served) == []
    assert len(stored(served, "COMPLETE")) == 2
