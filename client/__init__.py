"""jitdyn's Python client: the SDK, simulated research objects, network emulation, experiments.

    from client import Client, SessionOptions, FrameData
"""

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
