"""Resume tokens: what lets a client continue its session on any replica that shares the index.

A token is the HMAC-SHA256 of the session id under the server secret, which replicas share
(--secret-file, or JITDYN_SECRET): any replica can check it, and nobody without it can make one.

    token = resume_token(secret, session_id)
    check_resume_token(secret, session_id, token)   # PermissionDenied when wrong
"""

from __future__ import annotations

import hashlib
import hmac
from typing import Final

from jitdyn.errors import PermissionDenied

__all__ = ["check_resume_token", "resume_token"]

# Keeps a resume token from ever equalling another HMAC of the same secret (a subject pseudonym).
_DOMAIN: Final = b"jitdyn.resume.v1\x00"


def resume_token(secret: bytes, session_id: str) -> str:
    """The token of `session_id` (hex)."""
    return hmac.new(secret, _DOMAIN + session_id.encode(), hashlib.sha256).hexdigest()


def check_resume_token(secret: bytes, session_id: str, token: str) -> None:
    """Raise PermissionDenied unless `token` is `session_id`'s (in constant time)."""
    if not hmac.compare_digest(resume_token(secret, session_id), token):
        raise PermissionDenied(f"open.resume.token is not the resume token of session {session_id!r}")
