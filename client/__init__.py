"""jitdyn's Python client: the SDK, simulated research objects, network emulation, experiments.

    from client import Client, SessionOptions, FrameData
    from client import AsyncClient      # the same over asyncio (grpc.aio)
"""

from client.aio import AsyncClient, AsyncSession
from client.sdk import (
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
