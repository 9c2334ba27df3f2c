"""A session's summary computed from its stored rows: what recovery writes to the index for a
session that never reached `close`, and what `close` writes when the runtime gives none. Also the
one way a summary's counts are shown (`format_counts`): `jitdyn sessions list/show` and the demo
print them with it, so that they agree.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Final, Protocol

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from jitdyn.storage.records import SessionSummaryInfo

__all__ = ["COUNTS", "Counts", "format_counts", "summarise"]


class Counts(Protocol):
    """A session summary's counts: the index's SessionSummaryInfo and the SDK's Summary both are."""

    @property
    def ticks(self) -> int: ...
    @property
    def measured(self) -> int: ...
    @property
    def predicted(self) -> int: ...
    @property
    def corrected(self) -> int: ...
    @property
    def rejected(self) -> int: ...
    @property
    def late(self) -> int: ...


# (label, field, width), in the order shown. `ticks` counts distinct ticks answered; a tick answered
# PREDICTED and later CORRECTED counts once in ticks, and once in each of predicted and corrected.
COUNTS: Final = (
    ("ticks", "ticks", 6),
    ("measured", "measured", 6),
    ("predicted", "predicted", 5),
    ("corrected", "corrected", 5),
    ("rejected", "rejected", 4),
    ("late", "late", 5),
)


def format_counts(summary: Counts) -> str:
    """'ticks    203  measured     40  predicted   163  ...', aligned for a column of sessions."""
    return "  ".join(f"{label} {getattr(summary, name):>{width}}" for label, name, width in COUNTS)


def _count(mask: pa.ChunkedArray | pa.Array) -> int:
    return int(pc.sum(pc.cast(mask, pa.int64())).as_py() or 0)


def _ranges(column: pa.ChunkedArray, dof_names: Sequence[str]) -> dict[str, dict[str, float]]:
    """min and max of each element of a list column whose present rows all have len(dof_names)."""
    present = pc.drop_null(column)
    if len(present) == 0 or not dof_names:
        return {}
    values = pc.list_flatten(present).to_numpy(zero_copy_only=False)
    if values.size != len(present) * len(dof_names):
        return {}
    matrix = values.reshape(len(present), len(dof_names))
    finite = np.where(np.isfinite(matrix), matrix, np.nan)
    if np.isnan(finite).all(axis=0).any():
        return {}
    lo, hi = np.nanmin(finite, axis=0), np.nanmax(finite, axis=0)
    return {name: {"min": float(a), "max": float(b)} for name, a, b in zip(dof_names, lo, hi, strict=True)}


def summarise(table: pa.Table, *, dof_names: Sequence[str]) -> SessionSummaryInfo:
    """Counts and timings of the rows of a session's log or Parquet file, and the range of
    `qfrc_inverse` per degree of freedom under stats["qfrc_inverse"]."""
    if table.num_rows == 0:
        return SessionSummaryInfo()
    is_result = pc.equal(table["kind"], "result")
    results = table.filter(is_result)
    source = results["source"]
    compute = results["compute_us"]
    stats: dict[str, object] = {}
    ranges = _ranges(results["qfrc_inverse"], dof_names)
    if ranges:
        stats["qfrc_inverse"] = ranges
    return SessionSummaryInfo(
        ticks=int(pc.count_distinct(results["seq"]).as_py()) if results.num_rows else 0,
        frames=_count(results["frame_received"]) + (table.num_rows - results.num_rows),
        measured=_count(pc.equal(source, "MEASURED")),
        predicted=_count(pc.equal(source, "PREDICTED")),
        corrected=_count(pc.equal(source, "CORRECTED")),
        rejected=table.num_rows - results.num_rows,
        late=_count(pc.greater(results["late_ticks"], 0)),
        mean_compute_us=float(pc.mean(compute).as_py() or 0.0) if results.num_rows else 0.0,
        max_compute_us=float(pc.max(compute).as_py() or 0.0) if results.num_rows else 0.0,
        duration=float(pc.max(table["server_time"]).as_py() or 0.0),
        stats=stats,
    )
