"""Finding 8: authentication abuse, key files others can read, storage failures as clients and
operators see them."""

from __future__ import annotations

import shutil
import subprocess
import sys
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
