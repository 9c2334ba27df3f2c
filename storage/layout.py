"""Where a session's bytes live under a server's data folder, and how files are made durable there.

<data folder>/logs/<session id>.arrows                                 while the session runs
<data folder>/frames/model=<name>/date=<YYYY-MM-DD>/<session id>.parquet once it has ended

With a data root (storage/root.py), the Parquet file is published there under the same relative
path, and leaves the data folder.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterable
from pathlib import Path, PurePosixPath

__all__ = [
    "FRAMES_DIR",
    "LOG_DIR",
    "frames_location",
    "fsync_dir",
    "log_location",
    "make_dirs",
    "prepare_data_root",
    "session_of",
    "write_durably",
]

LOG_DIR = "logs"
FRAMES_DIR = "frames"


def log_location(session_id: str) -> str:
    """The session's append-only log, relative to the data root."""
    return str(PurePosixPath(LOG_DIR) / f"{session_id}.arrows")


def frames_location(*, model_name: str, date: str, session_id: str, epoch: int | None = None) -> str:
    """The session's Parquet file, relative to the data root (Hive partitions model and date).
    A session of the shared tier names the epoch it was stored under (`<id>.e<epoch>.parquet`):
    a stale finisher's upload never overwrites the new owner's."""
    name = f"{session_id}.parquet" if epoch is None else f"{session_id}.e{epoch}.parquet"
    return str(PurePosixPath(FRAMES_DIR) / f"model={model_name}" / f"date={date}" / name)


def session_of(file_name: str) -> str:
    """The session id of a Parquet file's name (`<id>.parquet` or `<id>.e<epoch>.parquet`)."""
    return file_name.split(".", 1)[0]


def fsync_dir(path: Path) -> None:
    """Make the entries of a folder (a created, renamed or deleted file) durable."""
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_durably(target: Path, chunks: Iterable[bytes]) -> None:
    """Write `chunks` as the file `target`, whole or not at all: through a temporary file beside it
    (0600, the server's user's only whatever the umask), fsynced, renamed over `target`, and the
    rename made durable in the folder."""
    temporary = target.with_name(f".{target.name}.{uuid.uuid4().hex}.tmp")
    try:
        with os.fdopen(os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600), "wb") as file:
            for chunk in chunks:
                file.write(chunk)
            file.flush()
            os.fsync(file.fileno())
        os.replace(temporary, target)
    finally:
        temporary.unlink(missing_ok=True)
    fsync_dir(target.parent)


def make_dirs(root: Path, relative: str) -> Path:
    """Create the folders of `relative` under `root`, each new one made durable in its parent."""
    current = root
    current.mkdir(mode=0o700, parents=True, exist_ok=True)
    for part in PurePosixPath(relative).parts:
        child = current / part
        if not child.is_dir():
            child.mkdir(mode=0o700, exist_ok=True)
            fsync_dir(current)
        current = child
    return current


def prepare_data_root(data_root: Path) -> Path:
    """The data folder, made ready to serve from and private: created 0700 when missing (and tightened
    to 0700 when group or others could enter it), new files 0600 from now on in this process (the
    umask covers what SQLite and the libraries create), and proved writable by writing a file.

    Raises FailedPrecondition, in one line that says why, when the folder cannot be made or written.
    """
    from jitdyn.errors import FailedPrecondition

    os.umask(0o077)
    root = data_root.expanduser().absolute()
    try:
        root.mkdir(mode=0o700, parents=True, exist_ok=True)
        if root.stat().st_mode & 0o077:
            root.chmod(0o700)
        probe = root / f".write-test-{os.getpid()}"
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            os.write(fd, b"jitdyn")
            os.fsync(fd)
        finally:
            os.close(fd)
            probe.unlink(missing_ok=True)
    except OSError as error:
        raise FailedPrecondition(
            f"the data folder {root} cannot be written ({error.strerror or error}); give --data a folder "
            "this user can write"
        ) from None
    return root.resolve()
