"""Reading an MJCF file and exactly the files it names, for `jitdyn models register FILE.xml`.

The registry's own resolver (registry.references) decides which files MuJoCo would read, so the
client sends what the server will look for and nothing else; a reference that leaves the asset
folder is refused here, before anything is sent.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from pathlib import Path

from jitdyn.errors import InvalidArgument
from jitdyn.registry.limits import DEFAULT_LIMITS
from jitdyn.registry.references import check_model

__all__ = ["read_model_files"]


class _FolderAssets(Mapping[str, bytes]):
    """The files under `root`, read when the resolver asks for them; remembers those it read."""

    def __init__(self, root: Path) -> None:
        self._root = root.resolve()
        self.read: dict[str, bytes] = {}

    def __contains__(self, name: object) -> bool:
        if not isinstance(name, str):
            return False
        if name in self.read:
            return True
        path = (self._root / name).resolve()
        if not (path.is_relative_to(self._root) and path.is_file()):
            return False
        self.read[name] = path.read_bytes()
        return True

    def __getitem__(self, name: str) -> bytes:
        if name in self:
            return self.read[name]
        raise KeyError(name)

    def __iter__(self) -> Iterator[str]:
        return iter(self.read)

    def __len__(self) -> int:
        return len(self.read)


def read_model_files(mjcf_path: Path, *, asset_dir: Path | None = None) -> tuple[str, dict[str, bytes]]:
    """The MJCF text of `mjcf_path` and the files it names, relative to `asset_dir` (default: the
    MJCF's folder), keyed by the names the MJCF uses."""
    try:
        mjcf = mjcf_path.read_text(encoding="utf-8")
    except OSError as error:
        raise InvalidArgument(f"cannot read the MJCF {str(mjcf_path)!r}: {error.strerror}") from None
    root = asset_dir if asset_dir is not None else mjcf_path.parent
    if not root.is_dir():
        raise InvalidArgument(f"--asset-dir must be a folder, got {str(root)!r}")
    assets = _FolderAssets(root)
    check_model(mjcf, assets, max_documents=DEFAULT_LIMITS.max_assets)
    return mjcf, dict(assets.read)
