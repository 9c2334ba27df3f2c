"""Anonymisation before anything is written: subject ids become keyed pseudonyms, and only
allow-listed, short subject attributes are kept.

    secret = load_or_create_secret(secret_file=None, env=os.environ, data_root=data_root)
    anonymiser = Anonymiser(secret)
    pseudonym = anonymiser.pseudonym("patient-4711")        # 64 hex digits, stable per secret
    kept, dropped = anonymiser.filter_attributes({"sex": "F", "name": "..."})  # dropped == ["name"]

The pseudonym is HMAC-SHA256 keyed with a server secret kept apart from the data (a 0600 key file
outside the data root, or the environment), so that the data alone cannot be matched back to ids
by hashing candidate ids. Nothing else about the client (address, host name) is ever stored.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import secrets
import stat
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Final

from jitdyn.errors import FailedPrecondition, InvalidArgument
from jitdyn.storage.layout import fsync_dir

__all__ = [
    "DEFAULT_ALLOWED",
    "DEFAULT_ALLOWED_ATTRIBUTES",
    "MAX_ATTRIBUTE_LENGTH",
    "MAX_SUBJECT_ID_LENGTH",
    "SECRET_BYTES",
    "Anonymiser",
    "default_secret_file",
    "load_or_create_secret",
]

# Coarse attributes biomechanics needs to interpret a session, none identifying alone:
#   sex        "F", "M", ...
#   age_band   "40-49" (a band, never a birth date or an exact age)
#   height_m   "1.82"       mass_kg  "74"
#   side       "left" / "right" (dominant or affected side)
#   limb       "arm", "leg", "hand", ...
#   condition  a short category, e.g. "ACL-reconstruction", "healthy"
DEFAULT_ALLOWED_ATTRIBUTES: Final = frozenset(
    {"sex", "age_band", "height_m", "mass_kg", "side", "limb", "condition"}
)
DEFAULT_ALLOWED: Final = DEFAULT_ALLOWED_ATTRIBUTES
# Longer values are dropped, not cut: a long value is free text, and free text can name a person.
MAX_ATTRIBUTE_LENGTH: Final = 32
MAX_SUBJECT_ID_LENGTH: Final = 256
SECRET_BYTES: Final = 32
ENV_SECRET: Final = "JITDYN_SECRET"
ENV_SECRET_FILE: Final = "JITDYN_SECRET_FILE"


def default_secret_file(env: Mapping[str, str]) -> Path:
    """`$XDG_CONFIG_HOME/jitdyn/secret.key`, else `~/.config/jitdyn/secret.key`."""
    config_home = env.get("XDG_CONFIG_HOME")
    base = Path(config_home) if config_home else Path(env.get("HOME") or Path.home()) / ".config"
    return base / "jitdyn" / "secret.key"


def _parse_secret(text: str, *, origin: str) -> bytes:
    try:
        secret = bytes.fromhex(text.strip())
    except ValueError as exc:
        raise InvalidArgument(f"{origin} must hold the secret as hex digits: {exc}") from exc
    if len(secret) < SECRET_BYTES:
        raise InvalidArgument(
            f"{origin} must hold at least {SECRET_BYTES} bytes ({2 * SECRET_BYTES} hex digits), got {len(secret)}"
        )
    return secret


def _create_secret(path: Path) -> None:
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        return  # another process created it first; use theirs
    with os.fdopen(fd, "w") as f:
        f.write(secrets.token_bytes(SECRET_BYTES).hex() + "\n")
        f.flush()
        os.fsync(f.fileno())
    fsync_dir(path.parent)


def load_or_create_secret(
    *, secret_file: Path | None, env: Mapping[str, str], data_root: Path | None = None
) -> bytes:
    """The server's pseudonymisation key.

    `JITDYN_SECRET` in `env` (hex) wins. Otherwise the key file: `secret_file`, else
    `JITDYN_SECRET_FILE` in `env`, else `default_secret_file(env)`; created with 32 random bytes and
    mode 0600 when missing. Refused (FailedPrecondition) when the file is readable or writable by
    group or others, or lies inside `data_root`: a key stored with the data protects nothing.
    """
    if env.get(ENV_SECRET):
        return _parse_secret(env[ENV_SECRET], origin=f"environment variable {ENV_SECRET}")
    if secret_file is None:
        secret_file = Path(env[ENV_SECRET_FILE]) if env.get(ENV_SECRET_FILE) else default_secret_file(env)
    path = secret_file.expanduser().absolute()
    if data_root is not None:
        root = data_root.expanduser().resolve()
        if path.resolve().is_relative_to(root):
            raise FailedPrecondition(
                f"the secret file {path} is inside the data root {root}; keep the key apart from the "
                f"data: move it elsewhere (e.g. {default_secret_file(env)}) or set {ENV_SECRET}"
            )
    if not path.exists():
        _create_secret(path)
    mode = stat.S_IMODE(path.stat().st_mode)
    if mode & 0o077:
        raise FailedPrecondition(
            f"the secret file {path} is accessible by group or others (mode {mode:04o}); "
            f"run `chmod 600 {path}`"
        )
    return _parse_secret(path.read_text(), origin=f"the secret file {path}")


class Anonymiser:
    """Pseudonyms and attribute filtering with one secret and one allow-list."""

    def __init__(
        self,
        secret: bytes,
        allowed_attributes: Iterable[str] = DEFAULT_ALLOWED_ATTRIBUTES,
        *,
        max_attribute_length: int = MAX_ATTRIBUTE_LENGTH,
    ) -> None:
        if len(secret) < SECRET_BYTES:
            raise InvalidArgument(f"secret must have at least {SECRET_BYTES} bytes, got {len(secret)}")
        self._secret = secret
        self._allowed = frozenset(allowed_attributes)
        self._max_length = max_attribute_length

    @property
    def allowed_attributes(self) -> frozenset[str]:
        return self._allowed

    def pseudonym(self, subject_id: str) -> str:
        """HMAC-SHA256 of the id under the secret, as 64 hex digits; "" for no subject ("")."""
        if not subject_id:
            return ""
        if len(subject_id) > MAX_SUBJECT_ID_LENGTH:
            raise InvalidArgument(
                f"subject.id must have at most {MAX_SUBJECT_ID_LENGTH} characters, got {len(subject_id)}"
            )
        return hmac.new(self._secret, subject_id.encode("utf-8"), hashlib.sha256).hexdigest()

    def filter_attributes(self, attributes: Mapping[str, str]) -> tuple[dict[str, str], list[str]]:
        """(kept, dropped keys): kept are the allow-listed keys whose values have at most
        `max_attribute_length` characters; every other key is dropped, sorted."""
        kept: dict[str, str] = {}
        dropped: list[str] = []
        for key, value in attributes.items():
            if key in self._allowed and len(value) <= self._max_length:
                kept[key] = value
            else:
                dropped.append(key)
        return kept, sorted(dropped)
