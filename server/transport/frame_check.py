"""Checking one incoming frame: checksum, shapes, finiteness. A bad frame becomes a `Rejection`
with a reason code and a message naming the field, what was expected and what arrived; it never
ends the session.
"""

from __future__ import annotations

import math

import numpy as np

from jitdyn.checksum import frame_checksum
from jitdyn.server.runtime.frames import CHANNELS, FrameIn, Rejection
from jitdyn.v1 import dynamics_pb2

__all__ = ["check_frame"]


def _array(values: object) -> np.ndarray:
    array = np.array(values, dtype=np.float64)
    array.flags.writeable = False
    return array


def check_frame(
    frame: dynamics_pb2.Frame,
    *,
    sizes: dict[str, int],
    measured: frozenset[str],
    received: float,
) -> FrameIn | Rejection:
    """Check `frame` against the session: `sizes` maps each channel to its model length, `measured`
    names the channels every frame must carry (ctrl among them in CONTROLLED; sensordata optional).
    """
    seq = frame.seq
    if frame.HasField("checksum"):
        expected = frame_checksum(
            seq=seq,
            t=frame.t,
            qpos=frame.qpos,
            qvel=frame.qvel,
            qacc=frame.qacc,
            ctrl=frame.ctrl,
            sensordata=frame.sensordata,
        )
        if expected != frame.checksum:
            return Rejection(
                seq,
                "BAD_CHECKSUM",
                f"frame {seq}: checksum is 0x{frame.checksum:08x}, the frame's bytes give 0x{expected:08x}",
            )
    arrays: dict[str, np.ndarray | None] = {}
    for name in CHANNELS:
        values = getattr(frame, name)
        size = len(values)
        if name in measured or (name == "sensordata" and size):
            if size != sizes[name]:
                return Rejection(
                    seq,
                    "BAD_SHAPE",
                    f"frame {seq}: {name} must have {sizes[name]} values, got {size}",
                )
            arrays[name] = _array(values)
        elif size:
            return Rejection(
                seq,
                "BAD_SHAPE",
                f"frame {seq}: {name} must be empty, since the session does not measure it "
                f"(measured: {', '.join(sorted(measured))}), got {size} values",
            )
        else:
            arrays[name] = None
    if not math.isfinite(frame.t):
        return Rejection(seq, "NOT_FINITE", f"frame {seq}: t must be finite, got {frame.t}")
    for name, array in arrays.items():
        if array is not None and not np.isfinite(array).all():
            index = int(np.flatnonzero(~np.isfinite(array))[0])
            return Rejection(
                seq, "NOT_FINITE", f"frame {seq}: {name}[{index}] must be finite, got {array[index]}"
            )
    qpos = arrays["qpos"]
    if qpos is None:  # qpos is always measured; kept for the type checker
        raise ValueError("qpos must be measured")
    return FrameIn(
        seq=seq,
        t=frame.t,
        qpos=qpos,
        qvel=arrays["qvel"],
        qacc=arrays["qacc"],
        ctrl=arrays["ctrl"],
        sensordata=arrays["sensordata"],
        received=received,
    )
