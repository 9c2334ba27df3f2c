"""Publishing a finished session's Parquet from this server's data folder to the data root, and
publishing again what could not be published when the session ended.

    location = publish_frames(root, data=data, relative=relative)   # URI, or `relative` if it failed
    index.finish(session_id, ..., location=location)
    drop_local_copy(data=data, relative=relative, location=location)
    publish_pending(root, data=data, index=index)   # in the background, every few seconds

The index never names a file that is not there: it holds the URI only once the upload is whole,
and the local copy is deleted only after the index holds the URI. A publish that fails keeps the
session in the data folder under its relative location (readable on this host, as without a root),
and, with a shared index, its rows in PostgreSQL until the root holds it (storage/shared.py).
"""

from __future__ import annotations

import logging
from pathlib import Path, PurePosixPath

from jitdyn.storage.failures import STORAGE_ERRORS
from jitdyn.storage.index import SessionIndex
from jitdyn.storage.layout import FRAMES_DIR, fsync_dir, session_of
from jitdyn.storage.root import DataRoot, is_uri
from jitdyn.vocabulary import SessionStatus

__all__ = ["awaiting_upload", "drop_local_copy", "publish_frames", "publish_pending", "settle_copies"]

_log = logging.getLogger(__name__)


def publish_frames(root: DataRoot | None, *, data: Path, relative: str) -> str:
    """The location the index is to hold for the Parquet at `data`/`relative`: its URI once copied
    to `root`; `relative` without a root, or when the copy failed (said in a warning; the file
    stays, and `publish_pending` tries again)."""
    if root is None:
        return relative
    try:
        return root.publish(data / relative, relative)
    except STORAGE_ERRORS as error:
        _log.warning(
            "%s could not be published to the data root %s (%s: %s); kept in the data folder, to be "
            "published again later",
            PurePosixPath(relative).name,
            root.uri,
            type(error).__name__,
            " ".join(str(error).split()),
        )
        return relative


def drop_local_copy(*, data: Path, relative: str, location: str) -> None:
    """Delete the data folder's copy once the index holds the data root's (`location` is a URI)."""
    if not is_uri(location):
        return
    path = data / relative
    try:
        path.unlink(missing_ok=True)
        fsync_dir(path.parent)
    except OSError as error:
        # The session is stored either way; `publish_pending` deletes the copy later.
        _log.warning("%s: the published copy could not be deleted from the data folder: %s", path.name, error)


def settle_copies(root: DataRoot | None, *, relative: str, location: str, won: bool) -> None:
    """Once the index has decided which upload of a session is its (`won`: this one at `relative`,
    published as `location`): the winner removes other epochs' copies from the root, a loser its
    own, so that a query over the root's files counts each session once."""
    if root is None or not is_uri(location):
        return
    try:
        if won:
            removed = root.drop_other_copies(relative)
            if removed:
                _log.warning("%s: removed stale copies from the data root: %s", relative, ", ".join(removed))
        else:
            root.delete(relative)
    except STORAGE_ERRORS as error:
        # Left for the next winner's sweep; the index names only the winner either way.
        _log.warning("%s: other copies could not be settled: %s", relative, error)


def awaiting_upload(data: Path) -> int:
    """How many finished sessions' Parquet files are in the data folder: with a data root, those it
    does not hold yet (a published file's local copy is deleted once the index names the root's)."""
    frames = data / FRAMES_DIR
    if not frames.is_dir():
        return 0
    return sum(1 for _ in frames.glob("model=*/date=*/*.parquet"))


def publish_pending(root: DataRoot, *, data: Path, index: SessionIndex) -> list[str]:
    """Publish every ended session whose Parquet is still only in `data` (its publish at the end
    failed, or the server stopped in between); delete copies already published. Returns the
    session ids published now. Stops at the first failure (the root is down: try again later)."""
    published: list[str] = []
    frames = data / FRAMES_DIR
    if not frames.is_dir():
        return published
    for path in sorted(frames.glob("model=*/date=*/*.parquet")):
        relative = path.relative_to(data).as_posix()
        session_id = session_of(path.name)
        stored = index.stored_location(session_id)
        if stored is None or stored[0] is SessionStatus.OPEN:
            continue  # not this index's, or being compacted right now
        _, location = stored
        if location == relative:
            location = root.publish(path, relative)
            if not index.move_location(session_id, old=relative, new=location):
                continue  # another process of this folder moved it meanwhile
            _log.warning("session %s: published to the data root now (%s)", session_id, location)
            settle_copies(root, relative=relative, location=location, won=True)
            published.append(session_id)
        if location == root.uri_of(relative) and root.exists(relative):
            drop_local_copy(data=data, relative=relative, location=location)
    return published
