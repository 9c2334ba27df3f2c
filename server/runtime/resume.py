"""Resume tokens: what lets a client continue its session on any replica that shares the index.

A token names the session, the tenant it was opened by, the lease epoch of the stream that handed
it out, and when it expires, and carries an HMAC-SHA256 of all four. Its key is derived from the
server secret that replicas share (--secret-file, or JITDYN_SECRET) for resume tokens alone, so
that it is never the key of a subject pseudonym: any replica can check a token, nobody without the
secret can make or alter one, and none outlives --resume-token-ttl unless its stream renews it.

    tokens = ResumeTokens(secret, ttl=600.0)
    token = tokens.issue(session_id, tenant="lab-a", epoch=3)
    epoch = tokens.check(token, session_id=session_id, tenant="lab-a")  # PermissionDenied when wrong

Whether the epoch is still good is the shared tier's to say (SharedTier.take_over): a token older
than the newest one presented for its session is stale. Why: docs/decisions/0164-bound-resume-tokens.md.
A token is a credential: it never goes into a log line, an error message or a repr.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import hmac
import json
import time
from datetime import UTC, datetime
from typing import Final

from jitdyn.errors import PermissionDenied

__all__ = ["ResumeTokens"]

# The label the token key is derived with: the pseudonym keys (storage/anonymise.py) are HMACs of
# the same secret under a label of their own, so no token key is ever a pseudonym key.
_KEY_LABEL: Final = b"jitdyn resume token key v1\x00"
_VERSION: Final = "v1"


def _encode(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode("ascii")


def _decode(text: str) -> bytes:
    return base64.urlsafe_b64decode(text + "=" * (-len(text) % 4))


class ResumeTokens:
    """Issues and checks the resume tokens of one server: `ttl` seconds from issue to expiry."""

    def __init__(self, secret: bytes, *, ttl: float) -> None:
        self._key = hmac.new(secret, _KEY_LABEL, hashlib.sha256).digest()
        self._ttl = ttl

    @property
    def ttl(self) -> float:
        return self._ttl

    def _mac(self, signed: str) -> str:
        return _encode(hmac.new(self._key, signed.encode("ascii"), hashlib.sha256).digest())

    def issue(self, session_id: str, *, tenant: str, epoch: int) -> str:
        """A token for `session_id` of `tenant` under lease `epoch`, expiring `ttl` s from now."""
        claims = {
            "sid": session_id,
            "tenant": tenant,
            "epoch": epoch,
            "exp": round(time.time() + self._ttl, 3),
        }
        signed = f"{_VERSION}.{_encode(json.dumps(claims, separators=(',', ':'), sort_keys=True).encode())}"
        return f"{signed}.{self._mac(signed)}"

    def check(self, token: str, *, session_id: str, tenant: str) -> int:
        """The lease epoch `token` was issued under, once its signature (compared in constant
        time), session, tenant and expiry are right; PermissionDenied saying which is not."""
        where = f"open.resume.token of session {session_id!r}"
        version, _, rest = token.partition(".")
        payload, _, mac = rest.partition(".")
        if version != _VERSION or not payload or not mac or not payload.isascii():
            raise PermissionDenied(f"{where} is not a resume token of this service")
        if not hmac.compare_digest(self._mac(f"{version}.{payload}").encode("ascii"), mac.encode("utf-8")):
            raise PermissionDenied(
                f"{where} has a bad signature: it was altered, or made with another server secret"
            )
        try:
            claims = json.loads(_decode(payload))
            issued_for, issued_to = str(claims["sid"]), str(claims["tenant"])
            epoch, expires = int(claims["epoch"]), float(claims["exp"])
        except (binascii.Error, ValueError, TypeError, KeyError):  # pragma: no cover - signed by us
            raise PermissionDenied(f"{where} is not a resume token of this service") from None
        if issued_for != session_id:
            raise PermissionDenied(f"{where} was issued for another session")
        if issued_to != tenant:
            raise PermissionDenied(
                f"{where} was issued to another tenant; resume with the API key that opened it"
            )
        now = time.time()
        if now > expires:
            at = datetime.fromtimestamp(expires, UTC).isoformat(timespec="seconds")
            raise PermissionDenied(
                f"{where} expired at {at} ({now - expires:.1f} s ago; tokens last --resume-token-ttl "
                "from the last answer that renewed them)"
            )
        return epoch
