"""The frame checksum of the v1 contract: CRC32C of a frame's canonical little-endian bytes.

The layout is defined in proto/jitdyn/v1/dynamics.proto (Frame.checksum) so that any language can
compute it::

    crc = frame_checksum(seq=1, t=0.05, qpos=[0.1], qvel=[-0.2])
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING, Final, TypedDict

import google_crc32c
import numpy as np

if TYPE_CHECKING:
    from typing_extensions import Unpack

__all__ = ["CHANNEL_ORDER", "Channels", "canonical_bytes", "frame_checksum", "vectors_checksum"]


class Channels(TypedDict, total=False):
    """A frame's vectors by field name; a channel left out is empty."""

    qpos: Sequence[float] | np.ndarray
    qvel: Sequence[float] | np.ndarray
    qacc: Sequence[float] | np.ndarray
    ctrl: Sequence[float] | np.ndarray
    sensordata: Sequence[float] | np.ndarray


# The contract's order of the channels in the checksummed bytes.
CHANNEL_ORDER: Final = ("qpos", "qvel", "qacc", "ctrl", "sensordata")

_LE_F64 = np.dtype("<f8")
_HEAD = struct.Struct("<Qd")
_COUNT = struct.Struct("<I")
_NATIVE_LE = np.dtype(np.float64) == _LE_F64
_ZERO = _COUNT.pack(0)


def _packed(seq: int, t: float, channels: Iterable[np.ndarray | None]) -> bytes:
    """seq (u64), t (f64), then each 1-D float64 channel (None: empty) as u32 length + f64s."""
    parts = [_HEAD.pack(seq, t)]
    for values in channels:
        if values is None or values.size == 0:
            parts.append(_ZERO)
        else:
            parts.append(_COUNT.pack(values.size))
            parts.append(values.tobytes() if _NATIVE_LE else values.astype(_LE_F64).tobytes())
    return b"".join(parts)


def canonical_bytes(*, seq: int, t: float, **channels: Unpack[Channels]) -> bytes:
    """The bytes the checksum covers: seq (u64), t (f64), then each channel as u32 length + f64s."""
    unknown = sorted(set(channels) - set(CHANNEL_ORDER))
    if unknown:
        raise TypeError(f"channels must be among {CHANNEL_ORDER}, got {unknown}")
    arrays = (np.asarray(channels.get(name, ()), dtype=_LE_F64).ravel() for name in CHANNEL_ORDER)
    return _packed(seq, t, arrays)


def vectors_checksum(seq: int, t: float, channels: Sequence[np.ndarray | None]) -> int:
    """`frame_checksum` of channels already converted to 1-D float64 arrays (None: empty), in
    CHANNEL_ORDER: the server's path, which converts each channel of a frame once and checks those
    same arrays (a quarter of the cost of converting the protobuf fields twice)."""
    return int(google_crc32c.value(_packed(seq, t, channels)))


def frame_checksum(*, seq: int, t: float, **channels: Unpack[Channels]) -> int:
    """CRC32C (Castagnoli) of `canonical_bytes`, as an unsigned 32-bit integer."""
    return int(google_crc32c.value(canonical_bytes(seq=seq, t=t, **channels)))
