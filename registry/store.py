"""Where registered models live on disk: one zip per content id, <data root>/models/<hex id>.zip,
holding "model.xml" and "assets/<name>" for each asset. Written atomically (temporary file, fsync,
rename); read into memory and never extracted, so no stored asset name ever becomes a server path.
"""

from __future__ import annotations

import io
import os
import uuid
import zipfile
from collections.abc import Mapping
from pathlib import Path

__all__ = ["blob_path", "read_blob", "write_blob"]

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


def write_blob(data_root: Path, model_id: str, mjcf: str, assets: Mapping[str, bytes]) -> str:
    """Store the model's MJCF and assets unless already stored; return the zip's relative path."""
    relative = blob_path(model_id)
    final = data_root / relative
    if final.exists():
        return relative  # content-addressed: the same id is the same content
    final.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    temporary = final.with_name(f".{final.name}.{uuid.uuid4().hex}.tmp")
    try:
        # Readable by the server's user only, whatever the umask (DESIGN: Security and limits).
        with os.fdopen(os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600), "wb") as file:
            with zipfile.ZipFile(file, "w") as archive:
                archive.writestr(_entry(_MJCF), mjcf.encode("utf-8"))
                for name in sorted(assets):
                    archive.writestr(_entry(_ASSETS + name), bytes(assets[name]))
            file.flush()
            os.fsync(file.fileno())
        os.replace(temporary, final)
    finally:
        temporary.unlink(missing_ok=True)
    directory = os.open(final.parent, os.O_RDONLY)
    try:
        os.fsync(directory)  # the rename itself survives a crash
    finally:
        os.close(directory)
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
