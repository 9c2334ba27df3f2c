"""jitdyn's Python SDK: register models, open sessions, stream frames, read results; sync and async.

    from jitdyn.client import Client, SessionOptions, FrameData
    from jitdyn.client import AsyncClient      # the same over asyncio (grpc.aio)

It may import jitdyn.v1, jitdyn.errors and jitdyn.registry (model packing); never the server
or the research harness.
"""

from jitdyn.client.aio import AsyncClient, AsyncSession
from jitdyn.client.sdk import (
    Client,
    FrameData,
    ModelRef,
    Opened,
    Rejection,
    Session,
    SessionOptions,
    Summary,
    SyncSample,
    TickResult,
)

__all__ = [
    "AsyncClient",
    "AsyncSession",
    "Client",
    "FrameData",
    "ModelRef",
    "Opened",
    "Rejection",
    "Session",
    "SessionOptions",
    "Summary",
    "SyncSample",
    "TickResult",
]
