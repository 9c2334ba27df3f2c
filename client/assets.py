"""Reading an MJCF file and exactly the files it names, for `jitdyn models register FILE.xml`.

The registry's own resolver (registry.references) decides which files MuJoCo would read, so the
client sends what the server will look for and nothing else; a reference that leaves the asset
folder is refused here, before anything is sent.
"""

from __future__ import annotations

import re
from collections.abc import Iterator, Mapping
from pathlib import Path

from jitdyn.errors import InvalidArgument
from jitdyn.registry.limits import DEFAULT_LIMITS
from jitdyn.registry.references import MissingAsset, check_model

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


# An XML declaration's encoding: <?xml version="1.0" encoding="ISO-8859-1"?>.
_DECLARED = re.compile(rb"""^(?:\xef\xbb\xbf)?\s*<\?xml[^>]*?\sencoding\s*=\s*["']([A-Za-z0-9._-]+)["']""")


def _xml_text(content: bytes, path: Path) -> str:
    """The text of an MJCF file, decoded as its XML declaration says (UTF-8 when it says nothing,
    as XML's default). Raises InvalidArgument, in one line, for a file that is not XML text."""
    declared = _DECLARED.match(content)
    encoding = declared.group(1).decode("ascii") if declared else "utf-8-sig"
    try:
        text = content.decode(encoding)
    except LookupError:
        raise InvalidArgument(
            f"{str(path)!r} declares the encoding {encoding!r}, which Python does not know; save it as UTF-8"
        ) from None
    except UnicodeDecodeError as error:
        where = f"byte 0x{content[error.start]:02x} at offset {error.start}"
        said = f"{encoding} text, as its XML declaration says" if declared else "UTF-8 text"
        unsaid = "" if declared else ", and no XML declaration names its encoding: an MJCF file is XML text"
        raise InvalidArgument(f"{str(path)!r} is not {said} ({where}){unsaid}") from None
    if not text.lstrip().startswith("<"):
        raise InvalidArgument(f"{str(path)!r} is not an MJCF (XML) file: it does not start with '<'")
    return text.removeprefix("\ufeff")


def read_model_files(mjcf_path: Path, *, asset_dir: Path | None = None) -> tuple[str, dict[str, bytes]]:
    """The MJCF text of `mjcf_path` and the files it names, relative to `asset_dir` (default: the
    MJCF's folder), keyed by the names the MJCF uses."""
    try:
        mjcf = _xml_text(mjcf_path.read_bytes(), mjcf_path)
    except OSError as error:
        raise InvalidArgument(f"cannot read the MJCF {str(mjcf_path)!r}: {error.strerror}") from None
    root = asset_dir if asset_dir is not None else mjcf_path.parent
    if not root.is_dir():
        raise InvalidArgument(f"--asset-dir must be a folder, got {str(root)!r}")
    assets = _FolderAssets(root)
    try:
        check_model(mjcf, assets, max_documents=DEFAULT_LIMITS.max_assets)
    except MissingAsset as error:
        folder = "--asset-dir" if asset_dir is not None else "the MJCF's folder"
        raise InvalidArgument(
            f"{error.referrer} names the file {error.name!r}, which is not in {folder} {str(root.resolve())!r} "
            f"(looked for {str(root.resolve() / error.name)!r}); give the folder that holds the model's "
            "files with --asset-dir DIR"
        ) from None
    return mjcf, dict(assets.read)
