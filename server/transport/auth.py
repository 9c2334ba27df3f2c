"""Who is calling: API keys and the tenant of an RPC.

On the default loopback bind without API keys every caller is the default tenant "". With an API key
file (`jitdyn serve --api-keys F`: one `KEY TENANT` pair per line, `#` comments) every RPC but the
health and reflection services must carry `authorization: Bearer KEY`; the interceptor records the
key's tenant for the RPC, and every servicer reads it with `tenant_of`.
"""

from __future__ import annotations

import asyncio
import contextvars
import hashlib
import hmac
import re
import time
from collections.abc import Awaitable, Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

import grpc

from jitdyn.errors import InvalidArgument
from jitdyn.key_files import check_private_file, refuse_placeholder

__all__ = [
    "DEFAULT_TENANT",
    "ApiKeyInterceptor",
    "FailurePenalty",
    "check_private_file",
    "current_tenant",
    "load_api_keys",
    "tenant_of",
]

DEFAULT_TENANT = ""

current_tenant: contextvars.ContextVar[str] = contextvars.ContextVar("jitdyn_tenant", default=DEFAULT_TENANT)

_TENANT = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
_OPEN_SERVICES = ("/grpc.health.v1.Health/", "/grpc.reflection.")

_Request = TypeVar("_Request")
_Response = TypeVar("_Response")


def tenant_of(context: grpc.aio.ServicerContext[_Request, _Response]) -> str:
    """The tenant the current RPC runs for."""
    del context  # the interceptor has set the context variable for this RPC's task
    return current_tenant.get()


def _digest(key: str) -> bytes:
    return hashlib.sha256(key.encode()).digest()


def load_api_keys(path: Path) -> dict[bytes, str]:
    """SHA-256 of each key -> its tenant, from a `KEY TENANT` file. Keys of fewer than 16 characters,
    bad tenant names, repeated keys and secret.yaml's placeholder are refused with the line they are on;
    a file others could read is refused (jitdyn.key_files)."""
    keys: dict[bytes, str] = {}
    check_private_file(path, setting="--api-keys")
    try:
        lines = path.read_text().splitlines()
    except OSError as error:
        raise InvalidArgument(f"--api-keys {str(path)!r} cannot be read: {error.strerror}") from None
    for number, line in enumerate(lines, 1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        parts = text.split()
        if len(parts) != 2:
            raise InvalidArgument(
                f"--api-keys {path}:{number}: expected `KEY TENANT`, got {len(parts)} fields"
            )
        key, tenant = parts
        refuse_placeholder(key, setting=f"--api-keys {path}:{number}: the key")
        if len(key) < 16:
            raise InvalidArgument(
                f"--api-keys {path}:{number}: a key must have at least 16 characters, got {len(key)}"
            )
        if not _TENANT.fullmatch(tenant):
            raise InvalidArgument(
                f"--api-keys {path}:{number}: tenant must be 1-64 of [A-Za-z0-9_.-], got {tenant!r}"
            )
        digest = _digest(key)
        if digest in keys:
            raise InvalidArgument(
                f"--api-keys {path}:{number}: this key is already given to tenant {keys[digest]!r}"
            )
        keys[digest] = tenant
    if not keys:
        raise InvalidArgument(f"--api-keys {path} has no keys")
    return keys


def _tenant_for(metadata: Sequence[tuple[str, str | bytes]] | None, keys: Mapping[bytes, str]) -> str | None:
    """The tenant of the one `authorization: Bearer KEY` header; None for no header, several
    (each would be another guess at a key in the same RPC) or an unknown key."""
    values = [value for name, value in metadata or () if name == "authorization"]
    if len(values) != 1:
        return None
    (value,) = values
    if not (isinstance(value, str) and value.startswith("Bearer ")):
        return None
    digest = _digest(value[len("Bearer ") :].strip())
    found = None
    for known, tenant in keys.items():
        if hmac.compare_digest(known, digest):
            found = tenant
    return found


class FailurePenalty:
    """Slows down a peer that keeps failing authentication: each failure within `window` seconds of
    the previous one doubles the wait before its answer, from `first` up to `cap` seconds, so
    guessing keys costs time while one mistyped key costs nothing noticeable. Peers are hosts
    (the port of each connection is left out); at most `max_peers` are remembered."""

    def __init__(
        self, *, first: float = 0.05, cap: float = 2.0, window: float = 60.0, max_peers: int = 10_000
    ) -> None:
        self._first = first
        self._cap = cap
        self._window = window
        self._max_peers = max_peers
        self._failures: dict[str, tuple[int, float]] = {}

    @staticmethod
    def host(peer: str) -> str:
        """ "ipv4:10.0.0.7:53211" -> "ipv4:10.0.0.7"; "ipv6:[::1]:53211" -> "ipv6:[::1]"."""
        return peer.rsplit(":", 1)[0] if peer.count(":") >= 2 else peer

    def failed(self, peer: str) -> float:
        """Count a failure of `peer`; the seconds to wait before answering it."""
        now = time.monotonic()
        host = self.host(peer)
        count, last = self._failures.pop(host, (0, now))
        count = count + 1 if now - last < self._window else 1
        if len(self._failures) >= self._max_peers:
            self._failures.pop(next(iter(self._failures)))  # the least recently failing
        self._failures[host] = (count, now)
        return min(self._cap, self._first * 2.0 ** (count - 1)) if count > 1 else 0.0


# The grpc stubs type a handler's behaviours as synchronous; under grpc.aio they return awaitables
# or async iterators, so they are taken and given back untyped.
def _with_tenant(behavior: Callable[..., Any], tenant: str, streaming_response: bool) -> Callable[..., Any]:
    if streaming_response:

        async def stream(request: Any, context: grpc.aio.ServicerContext[Any, Any]) -> Any:
            current_tenant.set(tenant)
            result = behavior(request, context)
            if hasattr(result, "__aiter__"):
                async for response in result:
                    yield response
            else:
                await result

        return stream

    async def unary(request: Any, context: grpc.aio.ServicerContext[Any, Any]) -> Any:
        current_tenant.set(tenant)
        return await behavior(request, context)

    return unary


class ApiKeyInterceptor(grpc.aio.ServerInterceptor):
    """Requires a known API key on every RPC but health and reflection; sets the RPC's tenant."""

    def __init__(self, keys: Mapping[bytes, str], *, penalty: FailurePenalty | None = None) -> None:
        self._keys = dict(keys)
        self._penalty = penalty or FailurePenalty()

    async def intercept_service(
        self,
        continuation: Callable[
            [grpc.HandlerCallDetails], Awaitable[grpc.RpcMethodHandler[_Request, _Response] | None]
        ],
        details: grpc.HandlerCallDetails,
    ) -> grpc.RpcMethodHandler[_Request, _Response] | None:
        handler = await continuation(details)
        if handler is None or details.method.startswith(_OPEN_SERVICES):
            return handler
        tenant = _tenant_for(details.invocation_metadata, self._keys)
        if tenant is None:

            async def refuse(request: object, context: grpc.aio.ServicerContext[_Request, _Response]) -> None:
                await asyncio.sleep(self._penalty.failed(context.peer()))
                await context.abort(
                    grpc.StatusCode.UNAUTHENTICATED,
                    "this server needs an API key: send one metadata `authorization: Bearer <key>`",
                )

            if handler.request_streaming and handler.response_streaming:
                return grpc.stream_stream_rpc_method_handler(refuse)
            return grpc.unary_unary_rpc_method_handler(refuse)
        if handler.request_streaming and handler.response_streaming and handler.stream_stream is not None:
            return grpc.stream_stream_rpc_method_handler(
                _with_tenant(handler.stream_stream, tenant, streaming_response=False),
                request_deserializer=handler.request_deserializer,
                response_serializer=handler.response_serializer,
            )
        if handler.unary_unary is not None:
            return grpc.unary_unary_rpc_method_handler(
                _with_tenant(handler.unary_unary, tenant, streaming_response=False),
                request_deserializer=handler.request_deserializer,
                response_serializer=handler.response_serializer,
            )
        return handler
