"""Checking one incoming frame: checksum, shapes, finiteness. A bad frame becomes a `Rejection`
with a reason code and a message naming the field, what was expected and what arrived; it never
ends the session.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from jitdyn.checksum import vectors_checksum
from jitdyn.server.runtime.frames import CHANNELS, FrameIn, Rejection
from jitdyn.v1 import dynamics_pb2
from jitdyn.vocabulary import RejectReason

__all__ = ["check_frame"]

# The ufunc's own reduce: ndarray.all() goes through a Python wrapper in numpy, a third of the
# check's cost on a frame's few values.
_all_true = np.logical_and.reduce
_EMPTY = np.zeros(0)
_EMPTY.flags.writeable = False


def _array(values: Sequence[float]) -> np.ndarray:
    # np.fromiter reads a protobuf repeated field 5x faster than np.array (0.8 against 3.7 us).
    array = np.fromiter(values, dtype=np.float64, count=len(values))
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
    # Each channel becomes an array once; the checksum and every check below read those arrays.
    arrays: dict[str, np.ndarray | None] = {}
    for name in CHANNELS:
        values = getattr(frame, name)
        arrays[name] = _array(values) if len(values) else None
    if frame.HasField("checksum"):
        expected = vectors_checksum(seq, frame.t, [arrays[name] for name in CHANNELS])
        if expected != frame.checksum:
            return Rejection(
                seq,
                RejectReason.BAD_CHECKSUM,
                f"frame {seq}: checksum is 0x{frame.checksum:08x}, the frame's bytes give 0x{expected:08x}",
            )
    shape = _check_shapes(seq, arrays, sizes=sizes, measured=measured)
    if shape is not None:
        return shape
    if not math.isfinite(frame.t):
        return Rejection(seq, RejectReason.NOT_FINITE, f"frame {seq}: t must be finite, got {frame.t}")
    for name, array in arrays.items():
        if array is not None and not _all_true(np.isfinite(array)):
            index = int(np.flatnonzero(~np.isfinite(array))[0])
            return Rejection(
                seq,
                RejectReason.NOT_FINITE,
                f"frame {seq}: {name}[{index}] must be finite, got {array[index]}",
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


def _check_shapes(
    seq: int, arrays: dict[str, np.ndarray | None], *, sizes: dict[str, int], measured: frozenset[str]
) -> Rejection | None:
    """Every measured channel (and sensordata when sent) at its model length, the others empty; a
    measured channel of a model with no such values (nu = 0) becomes an empty array in `arrays`."""
    for name in CHANNELS:
        array = arrays[name]
        size = 0 if array is None else array.size
        if name in measured or (name == "sensordata" and size):
            if size != sizes[name]:
                return Rejection(
                    seq,
                    RejectReason.BAD_SHAPE,
                    f"frame {seq}: {name} must have {sizes[name]} values, got {size}",
                )
            if array is None:  # a measured channel of a model with no such values (nu = 0)
                arrays[name] = _EMPTY
        elif size:
            return Rejection(
                seq,
                RejectReason.BAD_SHAPE,
                f"frame {seq}: {name} must be empty, since the session does not measure it "
                f"(measured: {', '.join(sorted(measured))}), got {size} values",
            )
    return None
