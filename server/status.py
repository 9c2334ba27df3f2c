"""The one place where jitdyn's exceptions become gRPC statuses.

Servicer methods raise `jitdyn.errors` exceptions; `translate_errors` ends the RPC with the status
the exception names and its message. Anything else is a bug: it is logged with its traceback and
ends the RPC with INTERNAL, without leaking internals to the client.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Awaitable, Callable
from typing import Any, NoReturn, TypeVar

import grpc

from jitdyn.errors import JitdynError

__all__ = ["abort", "translate_errors"]

_log = logging.getLogger(__name__)

T = TypeVar("T")


async def abort(context: grpc.aio.ServicerContext, error: JitdynError) -> NoReturn:
    """End the RPC with the status and message of `error`."""
    await context.abort(error.code, str(error))
    raise AssertionError("unreachable: context.abort raises")  # pragma: no cover


def translate_errors(
    method: Callable[..., Awaitable[T]],
) -> Callable[..., Awaitable[T]]:
    """Decorate a unary aio servicer method so that project errors become their statuses."""

    @functools.wraps(method)
    async def wrapper(self: Any, request: Any, context: grpc.aio.ServicerContext) -> T:
        try:
            return await method(self, request, context)
        except JitdynError as error:
            await abort(context, error)
        except grpc.aio.AbortError:
            raise
        except Exception:
            _log.exception("internal error in %s", method.__qualname__)
            await context.abort(grpc.StatusCode.INTERNAL, "internal server error; see the server log")
            raise  # pragma: no cover

    return wrapper
