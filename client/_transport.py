"""What the sync and the async transports share: the channel's options and retry policy, the
authorization metadata, the status-to-exception mapping and the end marker of a session's queues."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator, Sequence
from enum import Enum, auto
from typing import Any, Final

import grpc

from jitdyn.errors import InvalidArgument, JitdynError, error_for_status
from jitdyn.v1 import dynamics_pb2

__all__ = [
    "CHANNEL_OPTIONS",
    "END",
    "IDEMPOTENT_METHODS",
    "MAX_MESSAGE_BYTES",
    "RESUMABLE_CODES",
    "RETRY_POLICY",
    "End",
    "auth_metadata",
    "channel_options",
    "root_certificates",
    "status_error",
    "unbatched",
]

MAX_MESSAGE_BYTES = 128 * 1024 * 1024

# The unary calls that change nothing are retried by gRPC itself (its service-config retry policy)
# when the server is UNAVAILABLE: a restart, a deploy, a replica going away behind a balancer.
# RegisterModel is left out: it is content-addressed, but a retry after a lost answer would say
# `created` false for a model the first attempt created. Streams (sessions) are never retried.
IDEMPOTENT_METHODS: Final = (
    ("jitdyn.v1.ModelRegistryService", "GetModel"),
    ("jitdyn.v1.ModelRegistryService", "ListModels"),
    ("jitdyn.v1.SessionService", "ListSessions"),
    ("jitdyn.v1.SessionService", "GetSession"),
)
# 5 attempts with backoffs of about 0.25, 0.5, 1 and 2 s (gRPC randomises each): a server that is
# back within about 3.5 s is not noticed.
RETRY_POLICY: Final = {
    "maxAttempts": 5,
    "initialBackoff": "0.25s",
    "maxBackoff": "2s",
    "backoffMultiplier": 2,
    "retryableStatusCodes": ["UNAVAILABLE"],
}
_SERVICE_CONFIG: Final = json.dumps(
    {
        "methodConfig": [
            {
                "name": [{"service": service, "method": method} for service, method in IDEMPOTENT_METHODS],
                "retryPolicy": RETRY_POLICY,
            }
        ]
    }
)
CHANNEL_OPTIONS: Final = (
    ("grpc.max_receive_message_length", MAX_MESSAGE_BYTES),
    ("grpc.max_send_message_length", MAX_MESSAGE_BYTES),
    ("grpc.enable_retries", 1),
    ("grpc.service_config", _SERVICE_CONFIG),
)


# The statuses a broken session stream ends with that a resume can mend. UNAVAILABLE: the server
# went away, or is shutting down, or the connection dropped ("Stream removed"). CANCELLED: a
# balancer (HAProxy) resets the stream of a replica that died with RST_STREAM(CANCEL), error code 8,
# which gRPC maps to CANCELLED; a session the caller cancelled itself is never resumed.
RESUMABLE_CODES: Final = frozenset({grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.CANCELLED})


def channel_options(extra: Sequence[tuple[str, Any]] = ()) -> tuple[tuple[str, Any], ...]:
    """CHANNEL_OPTIONS with the caller's options added; the caller's win where both set one (e.g.
    ("grpc.lb_policy_name", "round_robin") for a target such as "ipv4:10.0.0.1:50051,10.0.0.2:50051"
    or a headless service's DNS name)."""
    names = {name for name, _ in extra}
    return (*(option for option in CHANNEL_OPTIONS if option[0] not in names), *extra)


class End(Enum):
    """The end of a session's request or response queue."""

    END = auto()


END: Final = End.END


def root_certificates(given: bytes | None, ca_file: str | os.PathLike[str] | None) -> bytes | None:
    """The PEM certificates a TLS channel trusts: `given`, or those of `ca_file` (the CA that
    signed the server's or the balancer's certificate); None for a plaintext channel.
    InvalidArgument, in one line, for both at once, or a `ca_file` that cannot be read or holds no
    PEM certificate."""
    if ca_file is None:
        return given
    if given is not None:
        raise InvalidArgument("give root_certificates or ca_file, not both")
    try:
        with open(ca_file, "rb") as file:
            data = file.read()
    except OSError as error:
        raise InvalidArgument(f"ca_file {os.fspath(ca_file)}: {error.strerror}") from None
    if b"-----BEGIN CERTIFICATE-----" not in data:
        raise InvalidArgument(
            f"ca_file {os.fspath(ca_file)}: holds no PEM certificate (-----BEGIN CERTIFICATE-----)"
        )
    return data


# What gRPC says of a TLS handshake that failed, and what it most often means.
_TLS_FAILURES: Final = (
    "CERTIFICATE_VERIFY_FAILED",
    "Tls handshake failed",
    "Ssl handshake failed",
    "WRONG_VERSION_NUMBER",
)
_TLS_HINT: Final = (
    "the TLS handshake with the server failed: if it serves TLS, trust the CA that signed its "
    "certificate (ca_file= or root_certificates=) and connect to the name the certificate is for; "
    "if it serves plaintext, give neither"
)


def status_error(error: grpc.RpcError) -> JitdynError:
    """The `jitdyn.errors` exception for the status an RPC ended with (sync or grpc.aio); a failed
    TLS handshake says what to check."""
    details = error.details() or ""
    if error.code() == grpc.StatusCode.UNAVAILABLE and any(f in details for f in _TLS_FAILURES):
        details = f"{_TLS_HINT} ({details})"
    return error_for_status(error.code(), details)


# Why an open can end in a bare stream reset: HAProxy before 3.2 turns a server's refusal of a
# stream the client still writes to into RST_STREAM(CANCEL), which drops the status
# (haproxy/haproxy#1219; docs/decisions/0121-refusals-through-a-balancer.md).
_RESET_AT_OPEN = (
    "the stream was reset before the server's answer to `open` arrived; through a balancer this "
    "is often a refusal whose reason the balancer dropped (HAProxy before 3.2 does): the server's "
    "log says why (`jitdyn serve -v` logs every refused open), or open the session on a replica directly"
)


def explain_open_error(error: JitdynError) -> JitdynError:
    """`error` as an open raises it: a bare stream reset says what it likely hides."""
    if error.code == grpc.StatusCode.CANCELLED and "RST_STREAM" in str(error):
        return error_for_status(grpc.StatusCode.CANCELLED, f"{error}: {_RESET_AT_OPEN}")
    return error


def auth_metadata(api_key: str | None) -> tuple[tuple[str, str], ...]:
    """The call metadata that carries `api_key`; none without one."""
    return (("authorization", f"Bearer {api_key}"),) if api_key else ()


def unbatched(
    response: dynamics_pb2.StreamSessionResponse,
) -> Iterator[dynamics_pb2.StreamSessionResponse]:
    """A server message as the messages it stands for: each result of a batch (`results`, which
    the SDK accepts at open) as if it had come alone, in order; any other message as it is."""
    if response.WhichOneof("payload") != "results":
        yield response
        return
    for result in response.results.results:
        yield dynamics_pb2.StreamSessionResponse(result=result)
