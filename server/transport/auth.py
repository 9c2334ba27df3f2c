"""Who is calling: API keys and the tenant of an RPC.

On the default loopback bind without API keys every caller is the default tenant "". With an API key
file (`jitdyn serve --api-keys F`: one `KEY TENANT` pair per line, `#` comments) every RPC but the
health and reflection services must carry `authorization: Bearer KEY`; the interceptor records the
key's tenant for the RPC, and every servicer reads it with `tenant_of`.
"""

from __future__ import annotations

import contextvars
import hashlib
import hmac
import re
from collections.abc import Awaitable, Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

import grpc

from jitdyn.errors import InvalidArgument

__all__ = ["DEFAULT_TENANT", "ApiKeyInterceptor", "current_tenant", "load_api_keys", "tenant_of"]

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
    bad tenant names and repeated keys are refused with the line they are on."""
    keys: dict[bytes, str] = {}
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
    for name, value in metadata or ():
        if name == "authorization" and isinstance(value, str) and value.startswith("Bearer "):
            digest = _digest(value[len("Bearer ") :].strip())
            for known, tenant in keys.items():
                if hmac.compare_digest(known, digest):
                    return tenant
    return None


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

    def __init__(self, keys: Mapping[bytes, str]) -> None:
        self._keys = dict(keys)

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
                await context.abort(
                    grpc.StatusCode.UNAUTHENTICATED,
                    "this server needs an API key: send metadata `authorization: Bearer <key>`",
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
