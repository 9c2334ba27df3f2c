"""The one place where jitdyn's exceptions become gRPC statuses.

Servicer methods raise `jitdyn.errors` exceptions; `translate_errors` ends the RPC with the status
the exception names and its message. Anything else is a bug: it is logged with its traceback and
ends the RPC with INTERNAL, without leaking internals to the client.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Awaitable, Callable
from typing import NoReturn, TypeVar

import grpc

from jitdyn.errors import JitdynError

__all__ = ["abort", "translate_errors"]

_log = logging.getLogger(__name__)

_Servicer = TypeVar("_Servicer")
_Request = TypeVar("_Request")
_Response = TypeVar("_Response")

# A unary aio servicer method: (self, request, context) -> awaitable response.
_UnaryMethod = Callable[
    [_Servicer, _Request, grpc.aio.ServicerContext[_Request, _Response]], Awaitable[_Response]
]


async def abort(context: grpc.aio.ServicerContext[_Request, _Response], error: JitdynError) -> NoReturn:
    """End the RPC with the status and message of `error`."""
    await context.abort(error.code, str(error))
    raise AssertionError("unreachable: context.abort raises")  # pragma: no cover


def translate_errors(
    method: _UnaryMethod[_Servicer, _Request, _Response],
) -> _UnaryMethod[_Servicer, _Request, _Response]:
    """Decorate a unary aio servicer method so that project errors become their statuses."""

    @functools.wraps(method)
    async def wrapper(
        self: _Servicer, request: _Request, context: grpc.aio.ServicerContext[_Request, _Response]
    ) -> _Response:
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
