"""The cases of how sessions end and what is kept: a deadline and a cancel release the session
(stored ABANDONED), a closed one is stored with its summary (session.proto), and API keys
(UNAUTHENTICATED, a tenant's sessions unseen by another) as the README's security section says.
"""

from __future__ import annotations

import time
from typing import Final

import grpc

from jitdyn.compliance.models import PENDULUM
from jitdyn.compliance.suite import DT, Context, Skipped, case, check, measured
from jitdyn.compliance.wire import CaseFailed, Ended
from jitdyn.v1 import dynamics_pb2, model_registry_pb2, session_pb2

__all__: list[str] = []

Code = grpc.StatusCode
# How long a server may take to store a session whose stream ended without `close` (s).
_STORED_WITHIN: Final = 30.0


def _stored(ctx: Context, session_id: str, *, key: str | None = "") -> session_pb2.Session:
    """The session once it is no longer OPEN, polled for up to _STORED_WITHIN."""
    until = time.monotonic() + _STORED_WITHIN
    while True:
        request = session_pb2.GetSessionRequest(session_id=session_id)
        session: session_pb2.Session = ctx.wire.call(ctx.wire.sessions.GetSession, request, key=key).session
        if session.status != session_pb2.SESSION_STATUS_OPEN or time.monotonic() > until:
            return session
        time.sleep(0.2)


def _status_name(session: session_pb2.Session) -> str:
    return session_pb2.SessionStatus.Name(session.status).removeprefix("SESSION_STATUS_")


@case("limits.deadline", "a stream past its deadline ends DEADLINE_EXCEEDED; its session is stored ABANDONED")
def _(ctx: Context) -> str:
    with ctx.wire.stream(deadline=3.0) as stream:
        opened = ctx.open(stream, model_id=ctx.model(PENDULUM).id, dt=DT)
        measured(stream, 0)
        ctx.status(stream.expect_end(timeout=10.0), Code.DEADLINE_EXCEEDED)
    session = _stored(ctx, opened.session_id)
    check(
        _status_name(session) == "ABANDONED", f"the session is stored {_status_name(session)}, not ABANDONED"
    )
    check(session.summary.ticks == 1, f"1 tick was answered; the stored summary says {session.summary.ticks}")
    return "3 s deadline"


@case("limits.cancel", "a cancelled stream ends CANCELLED; its session is stored ABANDONED with what it got")
def _(ctx: Context) -> str:
    with ctx.wire.stream() as stream:
        opened = ctx.open(stream, model_id=ctx.model(PENDULUM).id, dt=DT)
        for seq in range(2):
            measured(stream, seq)
        stream.cancel()
        ctx.status(stream.expect_end(), Code.CANCELLED)
    session = _stored(ctx, opened.session_id)
    check(
        _status_name(session) == "ABANDONED", f"the session is stored {_status_name(session)}, not ABANDONED"
    )
    check(
        session.summary.frames == 2, f"2 frames were sent; the stored summary says {session.summary.frames}"
    )
    return "after 2 frames"


@case(
    "sessions.stored",
    "a closed session is stored COMPLETE with the summary `closed` gave, and ListSessions lists it",
)
def _(ctx: Context) -> str:
    with ctx.wire.stream() as stream:
        opened = ctx.open(stream, model_id=ctx.model(PENDULUM).id, dt=DT)
        for seq in range(3):
            measured(stream, seq)
        closed = ctx.close(stream)
    session = _stored(ctx, opened.session_id)
    check(_status_name(session) == "COMPLETE", f"a closed session is stored {_status_name(session)}")
    got, sent = session.summary, closed
    for counted in ("ticks", "frames", "measured", "predicted", "corrected", "rejected"):
        check(
            getattr(got, counted) == getattr(sent, counted),
            f"stored {counted} {getattr(got, counted)}, closed said {getattr(sent, counted)}",
        )
    check(bool(session.location), "a stored session has no location")
    check(session.model_id == ctx.model(PENDULUM).id, f"stored model_id {session.model_id}")
    listed = ctx.wire.call(
        ctx.wire.sessions.ListSessions, session_pb2.ListSessionsRequest(model_id=session.model_id)
    )
    check(
        opened.session_id in [s.session_id for s in listed.sessions],
        "ListSessions(model_id) leaves the session out",
    )
    unknown = session_pb2.GetSessionRequest(session_id="00000000-0000-4000-8000-000000000000")
    ctx.status(ctx.wire.status_of(ctx.wire.sessions.GetSession, unknown), Code.NOT_FOUND)
    too_many = session_pb2.ListSessionsRequest(page_size=1001)
    ctx.status(ctx.wire.status_of(ctx.wire.sessions.ListSessions, too_many), Code.INVALID_ARGUMENT)
    return f"session {opened.session_id[:8]}"


# -- auth ----------------------------------------------------------------------------------------------


def _needs_key(ctx: Context) -> str:
    if not ctx.wire.target.api_key:
        raise Skipped("no --api-key given: the server is taken to run without API keys")
    return ctx.wire.target.api_key


@case("auth.keys", "with API keys, a call without a key, or with a wrong one, is UNAUTHENTICATED")
def _(ctx: Context) -> str:
    key = _needs_key(ctx)
    request = model_registry_pb2.ListModelsRequest(page_size=1)
    for name, other in (("no key", None), ("a wrong key", key[::-1] + "-wrong")):
        ended = ctx.wire.status_of(ctx.wire.registry.ListModels, request, key=other)
        try:
            ctx.status(ended, Code.UNAUTHENTICATED)
        except CaseFailed as failure:
            raise CaseFailed(f"ListModels with {name}: {failure}") from None
    with ctx.wire.stream(key=None) as stream:
        stream.send(open=dynamics_pb2.OpenSession(model_id=ctx.model(PENDULUM).id, dt=DT))
        ctx.status(stream.expect_end(), Code.UNAUTHENTICATED)
    ctx.status(ctx.wire.status_of(ctx.wire.registry.ListModels, request), Code.OK)
    return "unary and stream"


@case("auth.tenants", "a tenant does not see another tenant's sessions: GetSession is NOT_FOUND")
def _(ctx: Context) -> str:
    _needs_key(ctx)
    if not ctx.other_key:
        raise Skipped("no --other-api-key given (a key of another tenant)")
    with ctx.wire.stream() as stream:
        opened = ctx.open(stream, model_id=ctx.model(PENDULUM).id, dt=DT)
        measured(stream, 0)
        ctx.close(stream)
    request = session_pb2.GetSessionRequest(session_id=opened.session_id)
    ended: Ended = ctx.wire.status_of(ctx.wire.sessions.GetSession, request, key=ctx.other_key)
    ctx.status(ended, Code.NOT_FOUND)
    listed = ctx.wire.call(
        ctx.wire.sessions.ListSessions, session_pb2.ListSessionsRequest(), key=ctx.other_key
    )
    check(
        opened.session_id not in [s.session_id for s in listed.sessions], "another tenant lists the session"
    )
    return "GetSession and ListSessions"
