"""Resume tokens (server/runtime/resume.py) on their own: bound to a session, a tenant, a lease
epoch and an expiry, signed with a key of their own, and refused with one line that says what was
wrong and never repeats the token. The cluster tests (tests/cluster/test_resume_tokens.py) run
them through replicas."""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import secrets
import time

import pytest

from jitdyn.errors import PermissionDenied
from jitdyn.server.runtime.plan import Resume
from jitdyn.server.runtime.resume import ResumeTokens
from jitdyn.storage.anonymise import Anonymiser

SECRET = secrets.token_bytes(32)
SESSION = "6f1c1f9e-3c57-4a3c-9d43-0b7a2f3e9a10"


def refused(tokens: ResumeTokens, token: str, *, session_id: str = SESSION, tenant: str = "lab-a") -> str:
    """The one-line reason `token` is refused, checked never to repeat it."""
    with pytest.raises(PermissionDenied) as error:
        tokens.check(token, session_id=session_id, tenant=tenant)
    message = str(error.value)
    assert (not token or token not in message) and "\n" not in message
    return message


def test_a_token_names_its_epoch_to_the_session_and_tenant_it_was_issued_to() -> None:
    tokens = ResumeTokens(SECRET, ttl=600.0)
    token = tokens.issue(SESSION, tenant="lab-a", epoch=3)
    assert tokens.check(token, session_id=SESSION, tenant="lab-a") == 3
    # Any replica with the same secret checks it.
    assert ResumeTokens(SECRET, ttl=5.0).check(token, session_id=SESSION, tenant="lab-a") == 3


def test_another_session_or_tenant_is_refused_saying_which() -> None:
    tokens = ResumeTokens(SECRET, ttl=600.0)
    token = tokens.issue(SESSION, tenant="lab-a", epoch=1)
    assert "issued for another session" in refused(
        tokens, token, session_id="00000000-0000-4000-8000-000000000000"
    )
    message = refused(tokens, token, tenant="lab-b")
    assert "issued to another tenant" in message and "lab-a" not in message


def test_a_forged_or_altered_token_has_a_bad_signature() -> None:
    tokens = ResumeTokens(SECRET, ttl=600.0)
    token = tokens.issue(SESSION, tenant="lab-a", epoch=1)
    version, payload, mac = token.split(".")
    claims = json.loads(base64.urlsafe_b64decode(payload + "=" * (-len(payload) % 4)))
    claims["epoch"] = 99
    forged = base64.urlsafe_b64encode(json.dumps(claims).encode()).rstrip(b"=").decode()
    assert "bad signature" in refused(tokens, f"{version}.{forged}.{mac}")
    flipped = mac[:-1] + ("A" if mac[-1] != "A" else "B")
    assert "bad signature" in refused(tokens, f"{version}.{payload}.{flipped}")
    other = ResumeTokens(secrets.token_bytes(32), ttl=600.0).issue(SESSION, tenant="lab-a", epoch=1)
    assert "made with another server secret" in refused(tokens, other)
    for junk in ("0" * 64, "", "v1..", "v1.é.x", token.replace("v1.", "v2.")):
        assert "is not a resume token of this service" in refused(tokens, junk)


def test_a_token_expires_after_its_ttl() -> None:
    tokens = ResumeTokens(SECRET, ttl=0.05)
    token = tokens.issue(SESSION, tenant="lab-a", epoch=1)
    time.sleep(0.1)
    assert "expired at" in refused(tokens, token)


def test_the_token_key_is_neither_the_secret_nor_a_pseudonym_key() -> None:
    """The MAC is under a key derived for resume tokens alone: not the secret, which the old tokens
    used, nor any tenant's pseudonym key."""
    token = ResumeTokens(SECRET, ttl=600.0).issue(SESSION, tenant="", epoch=1)
    signed, _, mac = token.rpartition(".")
    anonymiser = Anonymiser(SECRET)
    for key in (SECRET, anonymiser.tenant_key(""), anonymiser.tenant_key("lab-a")):
        other = base64.urlsafe_b64encode(hmac.new(key, signed.encode(), hashlib.sha256).digest())
        assert other.rstrip(b"=").decode() != mac


def test_a_resume_request_s_repr_leaves_the_token_out() -> None:
    token = ResumeTokens(SECRET, ttl=600.0).issue(SESSION, tenant="lab-a", epoch=1)
    resume = Resume(session_id=SESSION, token=token)
    assert SESSION in repr(resume) and token not in repr(resume)
