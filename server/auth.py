"""Who is calling: the tenant of an RPC.

On the default loopback bind without API keys every caller is the default tenant "". With an API
key file (`jitdyn serve --api-keys F`, one `key tenant` pair per line) the interceptor in
server/app.py checks `authorization: Bearer <key>` and records the key's tenant for the RPC.
"""

from __future__ import annotations

import contextvars

import grpc

__all__ = ["DEFAULT_TENANT", "tenant_of", "current_tenant"]

DEFAULT_TENANT = ""

current_tenant: contextvars.ContextVar[str] = contextvars.ContextVar("jitdyn_tenant", default=DEFAULT_TENANT)


def tenant_of(context: grpc.aio.ServicerContext) -> str:
    """The tenant the current RPC runs for."""
    del context  # the interceptor has set the context variable for this RPC's task
    return current_tenant.get()
