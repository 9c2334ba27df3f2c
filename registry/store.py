"""Where registered models live: one zip per content id, holding "model.xml" and "assets/<name>"
for each asset. The shared copy is a row of the index's `model_blobs` table, which every replica
sharing the index reads; each server caches it in its own data folder at
<data root>/models/<hex id>.zip (docs/decisions/0100-model-content-in-the-index.md). The local file
is written atomically (temporary file, fsync, rename); both are read into memory and never
extracted, so no stored asset name ever becomes a server path.
"""

from __future__ import annotations

import io
import zipfile
from collections.abc import Mapping
from pathlib import Path

import sqlalchemy as sa

from jitdyn.errors import FailedPrecondition
from jitdyn.storage.index import SessionRow
from jitdyn.storage.layout import write_durably
from jitdyn.storage.schema import model_blobs

__all__ = ["blob_path", "fetch_blob", "publish_blob", "read_blob", "session_model", "write_blob"]

_MJCF = "model.xml"
_ASSETS = "assets/"
# A fixed timestamp makes the zip of the same content the same bytes.
_EPOCH = (1980, 1, 1, 0, 0, 0)


def blob_path(model_id: str) -> str:
    """The zip of `model_id` ("sha256:<hex>"), relative to the data root."""
    return f"models/{model_id.split(':', 1)[1]}.zip"


def _entry(name: str) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name, date_time=_EPOCH)
    info.compress_type = zipfile.ZIP_DEFLATED
    info.external_attr = 0o644 << 16
    return info


def _zip(mjcf: str, assets: Mapping[str, bytes]) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr(_entry(_MJCF), mjcf.encode("utf-8"))
        for name in sorted(assets):
            archive.writestr(_entry(_ASSETS + name), bytes(assets[name]))
    return buffer.getvalue()


def _write_local(data_root: Path, relative: str, data: bytes) -> None:
    """Write the zip `data` at `relative` under the data root, atomically, unless already there."""
    final = data_root / relative
    if final.exists():
        return  # content-addressed: the same id is the same content
    final.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    write_durably(final, [data])


def publish_blob(engine: sa.Engine, model_id: str, data: bytes) -> None:
    """Store the zip `data` of `model_id` in the index unless it is there already."""
    with engine.connect() as connection:
        present = connection.execute(sa.select(model_blobs.c.id).where(model_blobs.c.id == model_id)).first()
    if present is not None:
        return
    try:
        with engine.begin() as connection:
            connection.execute(sa.insert(model_blobs).values(id=model_id, zip=data))
    except sa.exc.IntegrityError:
        pass  # another replica stored the same content first: the same id is the same bytes


def fetch_blob(engine: sa.Engine, data_root: Path, model_id: str) -> str | None:
    """Copy the zip of `model_id` from the index into the local cache; its relative path, or None
    when the index does not hold it."""
    with engine.connect() as connection:
        data = connection.execute(
            sa.select(model_blobs.c.zip).where(model_blobs.c.id == model_id)
        ).scalar_one_or_none()
    if data is None:
        return None
    relative = blob_path(model_id)
    _write_local(data_root, relative, bytes(data))
    return relative


def write_blob(
    data_root: Path,
    model_id: str,
    mjcf: str,
    assets: Mapping[str, bytes],
    *,
    engine: sa.Engine | None = None,
) -> str:
    """Store the model's MJCF and assets in the local cache and, given `engine`, in the index, each
    unless already stored; return the zip's path relative to the data root."""
    relative = blob_path(model_id)
    data = _zip(mjcf, assets)
    if engine is not None:
        publish_blob(engine, model_id, data)
    _write_local(data_root, relative, data)
    return relative


def read_blob(data_root: Path, relative: str) -> tuple[str, dict[str, bytes]]:
    """The MJCF and assets stored at `relative` (a path `write_blob` returned), read into memory."""
    with zipfile.ZipFile(io.BytesIO((data_root / relative).read_bytes())) as archive:
        mjcf = archive.read(_MJCF).decode("utf-8")
        assets = {
            name[len(_ASSETS) :]: archive.read(name)
            for name in archive.namelist()
            if name.startswith(_ASSETS)
        }
    return mjcf, assets


def session_model(engine: sa.Engine, data_root: Path, row: SessionRow) -> tuple[str, dict[str, bytes]]:
    """The MJCF and assets of a stored session's model: the data folder's copy, else the index's
    (cached in the data folder on the way). FailedPrecondition when neither holds it."""
    try:
        return read_blob(data_root, blob_path(row.model_id))
    except FileNotFoundError:
        pass
    fetched = fetch_blob(engine, data_root, row.model_id)
    if fetched is None:
        raise FailedPrecondition(
            f"the model of session {row.session_id} ({row.model_name} v{row.model_version}, {row.model_id}) "
            f"is neither in the index nor in {data_root.resolve()}"
        )
    return read_blob(data_root, fetched)
