"""What a session runs on: a checked frame (`FrameIn`) and why a frame was not used (`Rejection`).
The transport builds them from the wire (`transport/frame_check.py`); the runtime never sees protobuf.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from jitdyn.vocabulary import RejectReason

__all__ = ["CHANNELS", "FrameIn", "Rejection"]

# Frame fields in the order of the contract; ctrl and sensordata are channels too.
CHANNELS = ("qpos", "qvel", "qacc", "ctrl", "sensordata")


@dataclass(frozen=True, slots=True)
class FrameIn:
    """A checked frame. Arrays are read-only; a channel the session does not measure is None."""

    seq: int
    t: float
    qpos: np.ndarray  # (nq,)
    qvel: np.ndarray | None  # (nv,)
    qacc: np.ndarray | None  # (nv,)
    ctrl: np.ndarray | None  # (nu,)
    sensordata: np.ndarray | None  # (nsensordata,)
    received: float  # server time of arrival (s)


@dataclass(frozen=True, slots=True)
class Rejection:
    """Why a frame or skip was not used."""

    seq: int
    reason: RejectReason
    message: str
    # A frame that passed its checks but came too late to be used: stored with the rejection, so
    # that no measurement a client sent is lost.
    frame: FrameIn | None = None
