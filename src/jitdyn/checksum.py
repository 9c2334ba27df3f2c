"""The frame checksum of the v1 contract: CRC32C of a frame's canonical little-endian bytes.

The layout is defined in proto/jitdyn/v1/dynamics.proto (Frame.checksum) so that any language can
compute it::

    crc = frame_checksum(seq=1, t=0.05, qpos=[0.1], qvel=[-0.2])
"""

from __future__ import annotations

import struct
from collections.abc import Sequence

import google_crc32c
import numpy as np

__all__ = ["canonical_bytes", "frame_checksum", "vectors_checksum"]

_LE_F64 = np.dtype("<f8")


def canonical_bytes(
    *,
    seq: int,
    t: float,
    qpos: Sequence[float] | np.ndarray = (),
    qvel: Sequence[float] | np.ndarray = (),
    qacc: Sequence[float] | np.ndarray = (),
    ctrl: Sequence[float] | np.ndarray = (),
    sensordata: Sequence[float] | np.ndarray = (),
) -> bytes:
    """The bytes the checksum covers: seq (u64), t (f64), then each channel as u32 length + f64s."""
    parts = [struct.pack("<Qd", seq, t)]
    for channel in (qpos, qvel, qacc, ctrl, sensordata):
        values = np.asarray(channel, dtype=_LE_F64).ravel()
        parts.append(struct.pack("<I", values.size))
        parts.append(values.tobytes())
    return b"".join(parts)


_HEAD = struct.Struct("<Qd")
_COUNT = struct.Struct("<I")
_NATIVE_LE = np.dtype(np.float64) == _LE_F64
_ZERO = _COUNT.pack(0)


def vectors_checksum(seq: int, t: float, channels: Sequence[np.ndarray | None]) -> int:
    """`frame_checksum` of channels already converted to 1-D float64 arrays (None: empty), in the
    contract's order qpos, qvel, qacc, ctrl, sensordata: the server's path, which converts each
    channel of a frame once and checks those same arrays (a quarter of the cost of converting the
    protobuf fields twice)."""
    parts = [_HEAD.pack(seq, t)]
    for values in channels:
        if values is None or values.size == 0:
            parts.append(_ZERO)
        else:
            parts.append(_COUNT.pack(values.size))
            parts.append(values.tobytes() if _NATIVE_LE else values.astype(_LE_F64).tobytes())
    return int(google_crc32c.value(b"".join(parts)))


def frame_checksum(
    *,
    seq: int,
    t: float,
    qpos: Sequence[float] | np.ndarray = (),
    qvel: Sequence[float] | np.ndarray = (),
    qacc: Sequence[float] | np.ndarray = (),
    ctrl: Sequence[float] | np.ndarray = (),
    sensordata: Sequence[float] | np.ndarray = (),
) -> int:
    """CRC32C (Castagnoli) of `canonical_bytes`, as an unsigned 32-bit integer."""
    data = canonical_bytes(seq=seq, t=t, qpos=qpos, qvel=qvel, qacc=qacc, ctrl=ctrl, sensordata=sensordata)
    return int(google_crc32c.value(data))
