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
from jitdyn.vocabulary import Source

__all__ = ["COUNTS", "Counts", "Summariser", "format_counts", "summarise"]


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


class Summariser:
    """`summarise` over a log read batch by batch: add each table of rows, then `result()`. Holds
    one byte per tick seen and a few numbers per degree of freedom, never the rows."""

    def __init__(self, *, dof_names: Sequence[str]) -> None:
        self._dof_names = list(dof_names)
        self._rows = 0
        self._results = 0
        self._seen = np.zeros(0, dtype=bool)
        self._frames = 0
        self._sources = dict.fromkeys(Source, 0)
        self._late = 0
        self._compute_sum = 0.0
        self._compute_count = 0
        self._compute_max: float | None = None
        self._duration: float | None = None
        self._lo: np.ndarray | None = None
        self._hi: np.ndarray | None = None
        self._ranges_valid = True
        self._ranged = 0

    def add(self, table: pa.Table) -> None:
        if table.num_rows == 0:
            return
        self._rows += table.num_rows
        results = table.filter(pc.equal(table["kind"], "result"))
        self._results += results.num_rows
        self._frames += _count(results["frame_received"]) + (table.num_rows - results.num_rows)
        for source in self._sources:
            self._sources[source] += _count(pc.equal(results["source"], source.value))
        self._late += _count(pc.greater(results["late_ticks"], 0))
        duration = pc.max(table["server_time"]).as_py()
        if duration is not None:
            self._duration = max(self._duration or duration, duration)
        if results.num_rows:
            seqs = results["seq"].to_numpy().astype(np.int64)
            if seqs.size and seqs.min() >= 0:
                top = int(seqs.max()) + 1
                if top > self._seen.size:
                    self._seen = np.concatenate([self._seen, np.zeros(top - self._seen.size, dtype=bool)])
                self._seen[seqs] = True
            compute = results["compute_us"]
            self._compute_sum += float(pc.sum(compute).as_py() or 0.0)
            self._compute_count += int(pc.count(compute).as_py() or 0)
            peak = pc.max(compute).as_py()
            if peak is not None:
                self._compute_max = max(self._compute_max or float(peak), float(peak))
            self._add_ranges(results["qfrc_inverse"])

    def _add_ranges(self, column: pa.ChunkedArray) -> None:
        present = pc.drop_null(column)
        if len(present) == 0 or not self._dof_names or not self._ranges_valid:
            return
        values = pc.list_flatten(present).to_numpy(zero_copy_only=False)
        if values.size != len(present) * len(self._dof_names):
            self._ranges_valid = False
            return
        matrix = values.reshape(len(present), len(self._dof_names))
        finite = np.where(np.isfinite(matrix), matrix, np.nan)
        lo = np.fmin.reduce(finite, axis=0)
        hi = np.fmax.reduce(finite, axis=0)
        self._lo = lo if self._lo is None else np.fmin(self._lo, lo)
        self._hi = hi if self._hi is None else np.fmax(self._hi, hi)
        self._ranged += len(present)

    def result(self) -> SessionSummaryInfo:
        if self._rows == 0:
            return SessionSummaryInfo()
        stats: dict[str, object] = {}
        lo, hi = self._lo, self._hi
        if (
            self._ranges_valid
            and lo is not None
            and hi is not None
            and not np.isnan(lo).any() | np.isnan(hi).any()
        ):
            stats["qfrc_inverse"] = {
                name: {"min": float(a), "max": float(b)}
                for name, a, b in zip(self._dof_names, lo, hi, strict=True)
            }
        return SessionSummaryInfo(
            ticks=int(self._seen.sum()),
            frames=self._frames,
            measured=self._sources[Source.MEASURED],
            predicted=self._sources[Source.PREDICTED],
            corrected=self._sources[Source.CORRECTED],
            rejected=self._rows - self._results,
            late=self._late,
            mean_compute_us=self._compute_sum / self._compute_count if self._compute_count else 0.0,
            max_compute_us=float(self._compute_max or 0.0),
            duration=float(self._duration or 0.0),
            stats=stats,
        )


def summarise(table: pa.Table, *, dof_names: Sequence[str]) -> SessionSummaryInfo:
    """Counts and timings of the rows of a session's log or Parquet file, and the range of
    `qfrc_inverse` per degree of freedom under stats["qfrc_inverse"]."""
    summariser = Summariser(dof_names=dof_names)
    summariser.add(table)
    return summariser.result()
