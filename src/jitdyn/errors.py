"""One exception tree for jitdyn, shared by the server (which maps it to gRPC status codes in one
place, server/transport/status.py) and the client (which maps statuses back)::

    JitdynError
    ├── InvalidArgument      INVALID_ARGUMENT
    ├── NotFound             NOT_FOUND
    ├── FailedPrecondition   FAILED_PRECONDITION
    ├── ResourceExhausted    RESOURCE_EXHAUSTED
    ├── Unauthenticated      UNAUTHENTICATED
    ├── PermissionDenied     PERMISSION_DENIED
    ├── Unavailable          UNAVAILABLE
    └── NoAnswer             DEADLINE_EXCEEDED   (also a TimeoutError: nothing came back in time)
"""

from __future__ import annotations

import grpc

__all__ = [
    "FailedPrecondition",
    "InvalidArgument",
    "JitdynError",
    "NoAnswer",
    "NotFound",
    "PermissionDenied",
    "ResourceExhausted",
    "ResumeBufferFull",
    "SessionLost",
    "Unauthenticated",
    "Unavailable",
    "error_for_status",
]


class JitdynError(Exception):
    """Base of every error jitdyn raises on purpose; `code` is the gRPC status it travels as."""

    code: grpc.StatusCode = grpc.StatusCode.INTERNAL


class InvalidArgument(JitdynError, ValueError):
    code = grpc.StatusCode.INVALID_ARGUMENT


class NotFound(JitdynError, LookupError):
    code = grpc.StatusCode.NOT_FOUND


class FailedPrecondition(JitdynError):
    code = grpc.StatusCode.FAILED_PRECONDITION


class ResourceExhausted(JitdynError):
    code = grpc.StatusCode.RESOURCE_EXHAUSTED


class Unauthenticated(JitdynError):
    code = grpc.StatusCode.UNAUTHENTICATED


class PermissionDenied(JitdynError):
    code = grpc.StatusCode.PERMISSION_DENIED


class Unavailable(JitdynError):
    code = grpc.StatusCode.UNAVAILABLE


class SessionLost(Unavailable):
    """The SDK could not resume a session whose stream broke (every attempt failed, or the server
    refused the resume); `session_id` names it, `attempts` says how many resumes were tried."""

    def __init__(self, message: str, *, session_id: str = "", attempts: int = 0) -> None:
        super().__init__(message)
        self.session_id = session_id
        self.attempts = attempts


class ResumeBufferFull(ResourceExhausted):
    """More frames are unacknowledged (not yet durable off the server's host) than the SDK keeps
    for resuming; the frame was not sent. Wait for answers (their `durable_seq`) and send again, or
    raise the client's `max_unacknowledged`."""


class NoAnswer(JitdynError, TimeoutError):
    """The server did not answer within the caller's timeout (the client's wait, or a call's deadline)."""

    code = grpc.StatusCode.DEADLINE_EXCEEDED


_BY_CODE: dict[grpc.StatusCode, type[JitdynError]] = {
    cls.code: cls
    for cls in (
        InvalidArgument,
        NotFound,
        FailedPrecondition,
        ResourceExhausted,
        Unauthenticated,
        PermissionDenied,
        Unavailable,
        NoAnswer,
    )
}


def error_for_status(code: grpc.StatusCode, message: str) -> JitdynError:
    """The exception a client raises for a status the server ended an RPC with."""
    error = _BY_CODE.get(code, JitdynError)(message)
    if type(error) is JitdynError:
        error.code = code
    return error
