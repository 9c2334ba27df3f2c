"""Files and values that hold keys: who may read a key file, and refusing the placeholders of
deploy/kubernetes/secret.yaml before they protect anything.

    check_private_file(Path("/etc/jitdyn/api-keys"), setting="--api-keys")
    refuse_placeholder(os.environ.get("PGPASSWORD", ""), setting="environment variable PGPASSWORD")

A key file follows PostgreSQL's rule for its server key (be-secure-common.c): owned by the server's
user, it is private to that user (0600 or less); owned by root, its group may read it too (0640 or
less), which is how a Kubernetes Secret volume lays it out (root:fsGroup, defaultMode 0440). Why:
docs/decisions/0160-key-files-as-a-secret-volume-mounts-them.md.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import Final

from jitdyn.errors import FailedPrecondition, InvalidArgument

__all__ = [
    "PLACEHOLDER_PREFIX",
    "SECRET_ENVIRONMENT",
    "check_ca_file",
    "check_private_file",
    "refuse_placeholder",
]

# Every value deploy/kubernetes/secret.yaml ships starts with this ("replace-me",
# "replace-with-64-hex-digits", "replace-with-a-long-random-key").
PLACEHOLDER_PREFIX: Final = "replace-"
# The Secret's environment variables that a server reads (itself, or through libpq and the AWS SDK).
SECRET_ENVIRONMENT: Final = (
    "JITDYN_SECRET",
    "PGPASSWORD",
    "AWS_ACCESS_KEY_ID",
    "AWS_SECRET_ACCESS_KEY",
    "AWS_SESSION_TOKEN",
)

_OWN_FILE_FORBIDDEN: Final = stat.S_IRWXG | stat.S_IRWXO
_ROOT_FILE_FORBIDDEN: Final = stat.S_IWGRP | stat.S_IXGRP | stat.S_IRWXO


def check_private_file(path: Path, *, setting: str) -> None:
    """Refuse a key file others could read or change (FailedPrecondition, saying what fixes it).

    Owned by this process's user: no access for group or others. Owned by root: its group may read
    it, nobody else may. Owned by anyone else: refused (they could rewrite the key)."""
    try:
        status = path.stat()
    except OSError as error:
        raise InvalidArgument(f"{setting} {str(path)!r} cannot be read: {error.strerror}") from None
    mode = stat.S_IMODE(status.st_mode)
    user = os.geteuid()
    if status.st_uid == user:
        if mode & _OWN_FILE_FORBIDDEN:
            raise FailedPrecondition(
                f"{setting} {path} is accessible by group or others (mode {mode:04o}); run `chmod 600 {path}`"
            )
    elif status.st_uid == 0:
        if mode & _ROOT_FILE_FORBIDDEN:
            raise FailedPrecondition(
                f"{setting} {path} is owned by root and accessible by others or writable by its group "
                f"(mode {mode:04o}); a key file root owns may be read by its group only: 0440 or 0640"
            )
    else:
        raise FailedPrecondition(
            f"{setting} {path} is owned by uid {status.st_uid}, neither this server's user (uid {user}) "
            f"nor root; run `chown {user} {path}`"
        )


def refuse_placeholder(value: str, *, setting: str) -> None:
    """Refuse a value still holding a placeholder of deploy/kubernetes/secret.yaml."""
    if value.strip().lower().startswith(PLACEHOLDER_PREFIX):
        raise FailedPrecondition(
            f"{setting} is still the placeholder {value.strip()!r} of deploy/kubernetes/secret.yaml; "
            "set the real value in the Secret"
        )


def check_ca_file(path: Path, *, setting: str) -> None:
    """Refuse a file of CA certificates (what a TLS connection checks its server against) that
    cannot be read, still holds the placeholder of deploy/kubernetes/ca-secret.yaml, or holds no PEM
    certificate: one line each, before a connection fails with a library's longer story."""
    try:
        data = path.read_bytes()
    except OSError as error:
        raise InvalidArgument(f"{setting} {path} cannot be read: {error.strerror}") from None
    text = data.strip().decode(errors="replace")
    if text.lower().startswith(PLACEHOLDER_PREFIX):
        raise FailedPrecondition(
            f"{setting} {path} is still the placeholder {text!r} of deploy/kubernetes/ca-secret.yaml; "
            "set your CA's certificate (PEM) in the Secret"
        )
    if b"-----BEGIN CERTIFICATE-----" not in data:
        raise InvalidArgument(f"{setting} {path} holds no PEM certificate (-----BEGIN CERTIFICATE-----)")
