"""A stored session tick by tick: what was answered when each tick was due, what its frame said,
what a late frame corrected, and the frames that were rejected. Read from a session's rows (the
Parquet table of storage.columns), for the plot and any other reader that follows a session in time.

    metadata, table = read_stored(row, data_root=root, environ=os.environ, purpose="plot")
    timeline = session_timeline(table)
    timeline.t[timeline.gap]            # the ticks no frame ever arrived for
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import pyarrow.compute as pc

from jitdyn.storage.columns import list_matrix
from jitdyn.vocabulary import Source

__all__ = ["TIMELINE_COLUMNS", "Rejections", "Timeline", "session_timeline"]

Floats = npt.NDArray[np.float64]

# The columns session_timeline reads: a reader may load only these.
TIMELINE_COLUMNS: Final = (
    "kind",
    "seq",
    "source",
    "t",
    "frame_received",
    "frame_delay",
    "nis",
    "compute_us",
    "receive_to_send_us",
    "reject_reason",
    "frame_qpos",
    "qpos",
    "qfrc_inverse",
)


@dataclass(frozen=True)
class Rejections:
    """The m rejected frames, in the order the server answered them."""

    seq: npt.NDArray[np.int64]  # (m,)
    t: Floats  # (m,) the tick's time, s
    reason: npt.NDArray[np.str_]  # (m,) RejectReason values
    frame_qpos: Floats  # (m, nq), NaN where the rejection kept no frame (a frame too late keeps it)
    frame_delay: Floats  # (m,) s, NaN where none was stored


@dataclass(frozen=True)
class Timeline:
    """The n ticks answered, in seq order. `answered_*` is the answer sent when the tick was due;
    `corrected_*` its replacement once a late frame was replayed (NaN for ticks never corrected);
    `frame_*` the tick's own frame, whenever it came (NaN for a gap). Times in seconds on the
    client clock; durations in microseconds as stored."""

    seq: npt.NDArray[np.int64]  # (n,)
    t: Floats  # (n,)
    source: npt.NDArray[np.str_]  # (n,) Source value of the answer sent when due
    corrected: npt.NDArray[np.bool_]  # (n,)
    framed: npt.NDArray[np.bool_]  # (n,) a frame was used for the tick, on time or late
    answered_qpos: Floats  # (n, nq)
    corrected_qpos: Floats  # (n, nq)
    frame_qpos: Floats  # (n, nq)
    answered_qfrc: Floats  # (n, nv), NaN when inverse dynamics was not asked for
    corrected_qfrc: Floats  # (n, nv)
    frame_delay: Floats  # (n,) REALTIME: the frame's arrival after its tick, s; NaN without one
    compute_us: Floats  # (n,) of the answer sent when due
    receive_to_send_us: Floats  # (n,) of the answer sent when due
    nis: Floats  # (n,) of the latest answer; NaN where none was stored
    rejections: Rejections

    @property
    def gap(self) -> npt.NDArray[np.bool_]:
        """(n,) ticks no frame was ever used for: answered by prediction alone."""
        return ~self.framed


def _floats(column: pa.ChunkedArray) -> Floats:
    return np.asarray(column.to_numpy(zero_copy_only=False), dtype=np.float64)


def _matrix(table: pa.Table, name: str, rows: int) -> Floats:
    matrix = list_matrix(table[name]) if name in table.column_names else None
    return np.full((rows, 0), np.nan) if matrix is None else matrix


def _widen(matrix: Floats, width: int) -> Floats:
    """`matrix` with `width` columns, NaN-filled: a column no row filled has width 0."""
    if matrix.shape[1] == width:
        return matrix
    return np.full((matrix.shape[0], width), np.nan)


def _rejections(table: pa.Table, nq: int) -> Rejections:
    rows = table.filter(pc.equal(table["kind"], "rejected"))
    return Rejections(
        seq=rows["seq"].to_numpy().astype(np.int64),
        t=_floats(rows["t"]),
        reason=np.asarray(rows["reject_reason"].to_pylist(), dtype=np.str_),
        frame_qpos=_widen(_matrix(rows, "frame_qpos", rows.num_rows), nq),
        frame_delay=_floats(rows["frame_delay"]),
    )


def session_timeline(table: pa.Table) -> Timeline:
    """The session's rows (TIMELINE_COLUMNS at least) as a Timeline: for each tick its first
    result (the answer when due) and its last CORRECTED result (a correction comes after what it
    corrects)."""
    results = table.filter(pc.equal(table["kind"], "result"))
    seqs = results["seq"].to_numpy().astype(np.int64)
    ticks, first = np.unique(seqs, return_index=True)
    n = len(ticks)
    source = np.asarray(results["source"].to_pylist(), dtype=np.str_)
    late_rows = np.flatnonzero(source == Source.CORRECTED.value)
    late_at = np.searchsorted(ticks, seqs[late_rows])  # a later correction of a tick wins
    corrected = np.zeros(n, dtype=bool)
    corrected[late_at] = True
    on_time_frame = results["frame_received"].to_numpy(zero_copy_only=False)[first].astype(bool)

    qpos = _matrix(results, "qpos", results.num_rows)
    frame_qpos = _widen(_matrix(results, "frame_qpos", results.num_rows), qpos.shape[1])
    qfrc = _matrix(results, "qfrc_inverse", results.num_rows)
    delay, nis = _floats(results["frame_delay"]), _floats(results["nis"])

    def answered(values: Floats) -> Floats:
        return values[first]

    def replaced(values: Floats) -> Floats:
        out = np.full((n, *values.shape[1:]), np.nan)
        out[late_at] = values[late_rows]
        return out

    def framed_value(values: Floats) -> Floats:
        # The frame on time (MEASURED) or late (CORRECTED), whichever the tick had.
        shape = (n,) + (1,) * (values.ndim - 1)
        return np.where(on_time_frame.reshape(shape), values[first], replaced(values))

    return Timeline(
        seq=ticks,
        t=_floats(results["t"])[first],
        source=source[first],
        corrected=corrected,
        framed=on_time_frame | corrected,
        answered_qpos=answered(qpos),
        corrected_qpos=replaced(qpos),
        frame_qpos=framed_value(frame_qpos),
        answered_qfrc=answered(qfrc),
        corrected_qfrc=replaced(qfrc),
        frame_delay=framed_value(delay),
        compute_us=answered(_floats(results["compute_us"])),
        receive_to_send_us=answered(_floats(results["receive_to_send_us"])),
        nis=np.where(corrected, replaced(nis), answered(nis)),
        rejections=_rejections(table, qpos.shape[1]),
    )
