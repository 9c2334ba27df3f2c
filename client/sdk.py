"""The sync SDK under its older module name, for code that imports `jitdyn.client.sdk`; new code
imports the same names from `jitdyn.client`."""

from jitdyn.client._client import Client, Session
from jitdyn.client._models import (
    FrameData,
    ModelRef,
    Opened,
    Rejection,
    SessionOptions,
    Summary,
    SyncSample,
    TickResult,
)
from jitdyn.client._transport import IDEMPOTENT_METHODS, MAX_MESSAGE_BYTES, RETRY_POLICY

__all__ = [
    "IDEMPOTENT_METHODS",
    "MAX_MESSAGE_BYTES",
    "RETRY_POLICY",
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
