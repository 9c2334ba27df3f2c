"""The content id of a model: what two registrations must share to be the same model.

    content_id(mjcf, assets) -> "sha256:9f86d0..."

The id is "sha256:" and the lowercase hex SHA-256 of this byte string (every integer an unsigned
64-bit big-endian length or count, so that no two different models frame to the same bytes):

    len(mjcf) mjcf n
    len(name_1) name_1 len(data_1) data_1
    ...
    len(name_n) name_n len(data_n) data_n

where mjcf is the MJCF text in UTF-8, n the number of assets, name_i the asset names in UTF-8, in
ascending order of those bytes, and data_i the assets' contents. Any language can recompute it.
"""

from __future__ import annotations

import hashlib
import re
import struct
from collections.abc import Mapping

from jitdyn.errors import InvalidArgument

__all__ = ["CONTENT_ID_PREFIX", "check_content_id", "content_id"]

CONTENT_ID_PREFIX = "sha256:"
_ID = re.compile(r"sha256:[0-9a-f]{64}")
_U64 = struct.Struct(">Q")


def content_id(mjcf: str, assets: Mapping[str, bytes]) -> str:
    """The content id of an MJCF text and its assets (see the module docstring for the framing)."""
    digest = hashlib.sha256()
    text = mjcf.encode("utf-8")
    digest.update(_U64.pack(len(text)))
    digest.update(text)
    digest.update(_U64.pack(len(assets)))
    for name, data in sorted(((name.encode("utf-8"), data) for name, data in assets.items())):
        digest.update(_U64.pack(len(name)))
        digest.update(name)
        digest.update(_U64.pack(len(data)))
        digest.update(data)
    return CONTENT_ID_PREFIX + digest.hexdigest()


def check_content_id(model_id: str, *, argument: str = "model_id") -> str:
    """Return `model_id` when it has the shape of a content id; InvalidArgument otherwise."""
    if not isinstance(model_id, str) or not _ID.fullmatch(model_id):
        raise InvalidArgument(
            f"{argument} must be 'sha256:' followed by 64 lowercase hex digits, got {model_id!r}"
        )
    return model_id
