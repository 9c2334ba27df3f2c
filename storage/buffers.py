"""A session's commit window as preallocated columns in Arrow's own layout. On the tick's thread a
row's scalars are stored into their columns (`append_result`: a tick's result from its values;
`append`: a `TickRecord`) and its vectors are held by reference; `batch` gives the commit thread
the window as a slice of one Arrow batch that views the columns, built once, after copying each
vector column's rows into its block with one numpy copy. A window costs neither a per-record
object nor a conversion before it is serialised.

    rows = WindowRows(lengths=expected_lengths(header))
    rows.append_result(values)  # a tick's result (a ResultRow), no TickRecord built
    rows.append(record)         # rejected frames, tools; InvalidArgument names a misfit column
    batch = rows.batch()        # the commit thread; valid until the next `append` or `clear`
    rows.clear()                # once the batch is serialised: the rows are written again

Numbers are numpy arrays (stored through memoryviews); a vector column is one (capacity, width)
float64 block, the values of a list column whose offsets are `k * width`; booleans and validity are
bitmaps (bytearrays); strings are offsets and UTF-8 bytes. The vectors of a column are packed, a
row without one a null of no values: the batch is the one `columns.records_to_batch` converts from
the same records. The columns grow by doubling, and the batch viewing them is then built again; so
is it when a vector column's width is first known. Why the vectors are copied by the commit
thread and not by the tick: docs/decisions/0221-the-columns-pay-at-a-servers-load.md.
"""

from __future__ import annotations

import operator
from collections.abc import Callable
from typing import Any, Final, TypeAlias

import numpy as np
import numpy.typing as npt
import pyarrow as pa

from jitdyn.errors import InvalidArgument
from jitdyn.storage.columns import ARRAY_FIELDS, FLOAT_LIST, LOG_SCHEMA, SCALAR_FIELDS
from jitdyn.storage.records import TickRecord

__all__ = ["INITIAL_ROWS", "ResultRow", "WindowRows"]

# Rows allocated at first; doubled whenever a window needs more. A 20 Hz session's window holds one
# to a few rows, and a burst of replays (CORRECTED answers) a few more.
INITIAL_ROWS: Final = 16

# A tick's result as `WindowRows.append_result` takes it: (seq, source, t, server_time, frame_t,
# late_ticks, frame_delay, nis, reinitialised, late_compute, compute_us, receive_to_send_us,
# vectors). frame_t is None when no frame arrived (frame_received False); vectors are the 15 array
# columns' values in ARRAY_FIELDS order, each a 1-D float64 array or None. A plain tuple, built
# once by the tick and handed down unpacked only here.
ResultRow: TypeAlias = tuple[
    int,
    str,
    float,
    float,
    float | None,
    int,
    float | None,
    float | None,
    bool,
    bool,
    int,
    int,
    tuple[npt.NDArray[np.float64] | None, ...],
]

_F64: Final = np.dtype(np.float64)
_NONE_ONLY: Final = {type(None)}
# Strings up to _WORD characters are encoded once, up to _WORDS of them a column.
_WORD: Final = 32
_WORDS: Final = 64
_NUMBERS: Final[dict[pa.DataType, type[np.generic]]] = {
    pa.int64(): np.int64,
    pa.int32(): np.int32,
    pa.float64(): np.float64,
}


def _view(values: Any) -> Any:
    """A memoryview of a column's buffer, for the row's stores (about half of numpy's item assignment,
    cold). Typed Any: it stores floats too, which typeshed's memoryview does not allow."""
    return memoryview(values)


def _bitmap(capacity: int) -> bytearray:
    return bytearray((capacity + 7) // 8)


def _set_bit(bits: bytearray, row: int, value: bool) -> None:
    if value:
        bits[row >> 3] |= 1 << (row & 7)
    else:
        bits[row >> 3] &= ~(1 << (row & 7)) & 0xFF


def _copy_bits(new: bytearray, old: bytearray) -> bytearray:
    new[: len(old)] = old
    return new


class _Scalars:
    """A number or boolean column, with its validity bitmap when it is nullable."""

    __slots__ = ("field", "get", "valid", "values", "view")

    def __init__(self, field: pa.Field, capacity: int) -> None:
        self.field = field
        self.get: Callable[[TickRecord], Any] = operator.attrgetter(field.name)
        self.values: npt.NDArray[Any] | bytearray = (
            _bitmap(capacity) if field.type == pa.bool_() else np.zeros(capacity, dtype=_NUMBERS[field.type])
        )
        # A number's store through a memoryview costs about half of numpy's item assignment, cold.
        self.view = _view(self.values)
        self.valid = _bitmap(capacity) if field.nullable else None

    def write(self, row: int, value: Any) -> None:
        if self.valid is not None:
            _set_bit(self.valid, row, value is not None)
            if value is None:
                # No earlier row's value stays behind a null.
                value = False if isinstance(self.values, bytearray) else 0
        if isinstance(self.values, bytearray):
            if not isinstance(value, bool | np.bool_):
                raise InvalidArgument(f"{self.field.name} must be a bool, got {value!r}")
            _set_bit(self.values, row, bool(value))
            return
        try:
            self.values[row] = value
        except (TypeError, ValueError, OverflowError):
            raise InvalidArgument(f"{self.field.name} must be {self.field.type}, got {value!r}") from None

    def grow(self, capacity: int) -> None:
        if isinstance(self.values, bytearray):
            self.values = _copy_bits(_bitmap(capacity), self.values)
        else:
            self.values = np.resize(self.values, capacity)
        self.view = _view(self.values)
        if self.valid is not None:
            self.valid = _copy_bits(_bitmap(capacity), self.valid)

    def array(self, capacity: int) -> pa.Array:
        validity = None if self.valid is None else pa.py_buffer(self.valid)
        # null_count -1: counted by whoever reads a slice, never cached for the whole column.
        return pa.Array.from_buffers(
            self.field.type, capacity, [validity, pa.py_buffer(self.values)], null_count=-1
        )


class _Texts:
    """A string column: offsets and UTF-8 bytes."""

    __slots__ = ("data", "encoded", "end", "field", "get", "offsets", "view")

    def __init__(self, field: pa.Field, capacity: int) -> None:
        self.field = field
        self.get: Callable[[TickRecord], Any] = operator.attrgetter(field.name)
        self.offsets = np.zeros(capacity + 1, dtype=np.int32)
        self.view = _view(self.offsets)  # the row's stores, as _Scalars.view
        self.data = bytearray(64 * capacity)
        self.end = 0  # offsets[rows]: where the next row's bytes go
        # The few words a column holds (kinds, sources, reasons), encoded once.
        self.encoded: dict[str, bytes] = {}

    def write(self, row: int, value: Any) -> bool:
        """Store `value` in `row`; True when its bytes needed a larger buffer (the batch viewing
        the old one is stale)."""
        if not isinstance(value, str):
            raise InvalidArgument(f"{self.field.name} must be a str, got {value!r}")
        encoded = self.encoded.get(value)
        if encoded is None:
            encoded = value.encode()
            if len(value) <= _WORD and len(self.encoded) < _WORDS:
                self.encoded[value] = encoded
        start = self.end
        end = start + len(encoded)
        grown = end > len(self.data)
        if grown:
            data = bytearray(max(2 * len(self.data), end))
            data[:start] = self.data[:start]
            self.data = data
        if encoded:
            self.data[start:end] = encoded
        self.offsets[row + 1] = end
        self.end = end
        return grown

    def rewind(self, row: int) -> None:
        """Write `row` again (a failed append left it half written)."""
        self.end = int(self.offsets[row])

    def grow(self, capacity: int) -> None:
        offsets = np.zeros(capacity + 1, dtype=np.int32)
        offsets[: len(self.offsets)] = self.offsets
        self.offsets = offsets
        self.view = _view(offsets)

    def array(self, capacity: int) -> pa.Array:
        return pa.Array.from_buffers(
            self.field.type, capacity, [None, pa.py_buffer(self.offsets), pa.py_buffer(self.data)]
        )


class _Vectors:
    """A vector column: its vectors packed in a (capacity, width) float64 block, the list column's
    values, with offsets and a validity bitmap; a row without a vector is a null of no values, as
    `pa.array` lays it out. `expected` is the width every vector must have (None: the first one's,
    for a column whose width is not fixed by the model: the covariance diagonal, the filter state,
    the forecast weights).

    A column is mostly the same in every row of a window: present (`dense` True), or absent
    (False). Its offsets and validity are then laid out for every row, and `fill` costs one copy of
    the window's vectors, or nothing; a window that mixes them is written row by row (`dense`
    None).

    Such a column changes width only with the estimator; a window in which it does keeps this
    column's vectors as a list, converted as the records' own arrays."""

    __slots__ = (
        "block",
        "capacity",
        "count",
        "dense",
        "expected",
        "get",
        "listed",
        "name",
        "offsets",
        "shape",
        "valid",
        "width",
    )

    def __init__(self, name: str, capacity: int, expected: int | None) -> None:
        self.name = name
        self.capacity = capacity
        self.get: Callable[[TickRecord], Any] = operator.attrgetter(name)
        self.expected = expected
        self.shape: tuple[int] | None = None
        self.width = 0
        self.block: npt.NDArray[np.float64] | None = None
        self.offsets = np.zeros(capacity + 1, dtype=np.int32)
        self.count = 0  # vectors in the block this window (while `dense` is None)
        self.valid = _bitmap(capacity)
        self.dense: bool | None = False
        self.listed: list[npt.NDArray[np.float64] | None] | None = None
        if expected is not None:
            self._allocate(expected)

    def _allocate(self, width: int) -> None:
        self.shape = (width,)
        self.width = width
        self.block = np.zeros((self.capacity, width))

    def _pattern(self, dense: bool) -> None:
        """Lay out offsets and validity for rows that all hold a vector (`dense`) or none."""
        if dense:
            self.offsets[:] = np.arange(self.capacity + 1, dtype=np.int32) * np.int32(self.width)
            self.valid[:] = b"\xff" * len(self.valid)
        else:
            self.offsets[:] = 0
            self.valid[:] = bytes(len(self.valid))
        self.dense = dense

    def write(self, row: int, value: Any) -> bool:
        """Store `value` (a 1-D vector, or None) in `row`; InvalidArgument on a wrong width. True
        when the block was allocated anew (the batch viewing the old one is stale)."""
        if self.dense is not None:
            # Row by row from here: the pattern holds for the rows before this one.
            self.count = row if self.dense else 0
            self.dense = None
        if value is None:
            _set_bit(self.valid, row, False)
            self.offsets[row + 1] = self.offsets[row]
            if self.listed is not None:
                self.listed.append(None)
            return False
        if not (isinstance(value, np.ndarray) and value.dtype is _F64):
            value = np.asarray(value, dtype=np.float64)
        allocated = False
        if value.shape != self.shape:
            if value.ndim != 1:
                raise InvalidArgument(
                    f"{self.name} must hold 1-D vectors, got an array of shape {value.shape}"
                )
            if self.expected is not None:
                raise InvalidArgument(
                    f"{self.name} must have {self.expected} values in every record, got {len(value)}"
                )
            if self.count == 0:  # the window's first vector sets the block's width
                self._allocate(len(value))
                allocated = True
            elif self.listed is None:
                self.listed = self._as_list(row)
        if self.listed is not None:
            self.listed.append(value.copy())
        else:
            assert self.block is not None
            self.block[self.count] = value
            self.count += 1
        self.offsets[row + 1] = self.count * len(value) if self.listed is None else 0
        _set_bit(self.valid, row, True)
        return allocated

    def _as_list(self, rows: int) -> list[npt.NDArray[np.float64] | None]:
        assert self.block is not None
        listed: list[npt.NDArray[np.float64] | None] = []
        packed = 0
        for k in range(rows):
            if self.valid[k >> 3] & (1 << (k & 7)):
                listed.append(self.block[packed].copy())
                packed += 1
            else:
                listed.append(None)
        return listed

    def check(self, value: Any) -> npt.NDArray[np.float64] | None:
        """`value` as this column holds it (a 1-D float64 vector, or None); InvalidArgument when it
        does not fit."""
        if value is None:
            return None
        try:
            vector = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise InvalidArgument(f"{self.name} must hold vectors of numbers, got {value!r}") from None
        if vector.ndim != 1:
            raise InvalidArgument(f"{self.name} must hold 1-D vectors, got an array of shape {vector.shape}")
        if self.expected is not None and len(vector) != self.expected:
            raise InvalidArgument(
                f"{self.name} must have {self.expected} values in every record, got {len(vector)}"
            )
        return vector

    def fill(self, values: tuple[Any, ...]) -> bool:
        """Copy a window's vectors (one a row, None where a row has none) into the column: one
        numpy copy when every row has one of the block's width, nothing when no row has one, else
        row by row. InvalidArgument names the column a vector does not fit. True when the block
        was allocated anew (the batch viewing the old one is stale)."""
        n = len(values)
        stale = False
        if values[0] is not None:
            try:
                # One copy into the block's first n rows: every row has a vector (len(None) raises),
                # 1-D (concatenate's check) and of one width (the set's), n widths in all (out's).
                widths = set(map(len, values))
                width = widths.pop() if len(widths) == 1 else None
                if width is not None and (self.expected is None or width == self.expected):
                    stale = width != self.width or self.block is None
                    if stale:
                        self._allocate(width)  # the window's first vectors set the block's width
                    assert self.block is not None
                    np.concatenate(values, out=self.block.reshape(-1)[: n * width])
                    if stale or self.dense is not True:
                        self._pattern(True)
                    return stale
            except (TypeError, ValueError):
                pass  # a row without one, or a vector that does not fit: row by row says which
        elif set(map(type, values)) == _NONE_ONLY:
            if self.dense is not False:
                self._pattern(False)
            return False
        # Row by row from no vectors: no offset is left of an earlier window's pattern, whose
        # width may not be this block's (Arrow checks the last offset against the values).
        self._pattern(False)
        self.dense = None
        self.count = 0
        self.listed = None
        for row, value in enumerate(values):
            try:
                stale |= self.write(row, value)
            except InvalidArgument:
                raise
            except (TypeError, ValueError) as exc:
                raise InvalidArgument(f"{self.name} must hold vectors of numbers: {exc}") from None
        return stale

    def grow(self, capacity: int) -> None:
        self.capacity = capacity
        old_offsets, old_valid = self.offsets, self.valid
        self.offsets = np.zeros(capacity + 1, dtype=np.int32)
        self.valid = _bitmap(capacity)
        if self.dense is None:
            self.offsets[: len(old_offsets)] = old_offsets
            self.valid[: len(old_valid)] = old_valid
        else:
            self._pattern(self.dense)
        if self.block is not None and self.shape is not None:
            old = self.block
            self._allocate(self.shape[0])
            assert self.block is not None
            self.block[: len(old)] = old

    def array(self, capacity: int) -> pa.Array:
        if self.block is None:
            return pa.nulls(capacity, FLOAT_LIST)
        values = pa.Array.from_buffers(pa.float64(), self.block.size, [None, pa.py_buffer(self.block)])
        return pa.Array.from_buffers(
            FLOAT_LIST,
            capacity,
            [pa.py_buffer(self.valid), pa.py_buffer(self.offsets)],
            null_count=-1,
            children=[values],
        )

    def clear(self) -> None:
        """Forget the window's vectors."""
        self.count = 0
        self.listed = None


def _by_name(vectors: tuple[npt.NDArray[np.float64] | None, ...]) -> dict[str, Any]:
    return dict(zip(ARRAY_FIELDS, vectors, strict=True))


def _result_record(values: ResultRow) -> TickRecord:
    """A result's scalars as a record, for the checked path (its vectors are held apart)."""
    seq, source, t, server_time, frame_t, late_ticks, frame_delay, nis, reinit, late, compute, sent, _ = (
        values
    )
    return TickRecord(
        kind="result",
        seq=seq,
        source=source,
        t=t,
        server_time=server_time,
        frame_received=frame_t is not None,
        frame_t=frame_t,
        late_ticks=late_ticks,
        frame_delay=frame_delay,
        nis=nis,
        reinitialised=reinit,
        late_compute=late,
        compute_us=compute,
        receive_to_send_us=sent,
    )


class _Named:
    """The scalar columns by name, for `WindowRows.append_result`'s straight-line row."""

    __slots__ = (
        "compute_us",
        "empty",
        "frame_delay",
        "frame_received",
        "frame_t",
        "kind",
        "late_compute",
        "late_ticks",
        "nis",
        "receive_to_send_us",
        "reinitialised",
        "seq",
        "server_time",
        "source",
        "t",
    )

    def __init__(self, scalars: list[_Scalars], texts: list[_Texts]) -> None:
        number = {c.field.name: c for c in scalars}
        text = {c.field.name: c for c in texts}
        self.seq, self.t, self.server_time = number["seq"], number["t"], number["server_time"]
        self.late_ticks, self.compute_us = number["late_ticks"], number["compute_us"]
        self.receive_to_send_us = number["receive_to_send_us"]
        self.frame_t, self.frame_delay, self.nis = number["frame_t"], number["frame_delay"], number["nis"]
        self.frame_received, self.reinitialised = number["frame_received"], number["reinitialised"]
        self.late_compute = number["late_compute"]
        self.kind, self.source = text["kind"], text["source"]
        # reject_reason and reject_message: "" in a result.
        self.empty = (text["reject_reason"], text["reject_message"])

    def targets(self) -> tuple[Any, ...]:
        """What `append_result` stores a row's scalars into, in its order; made again when the
        columns grow (their buffers are new)."""
        return (
            self.seq.view,
            self.t.view,
            self.server_time.view,
            self.late_ticks.view,
            self.compute_us.view,
            self.receive_to_send_us.view,
            self.frame_t.view,
            self.frame_t.valid,
            self.frame_delay.view,
            self.frame_delay.valid,
            self.nis.view,
            self.nis.valid,
            self.frame_received.values,
            self.reinitialised.values,
            self.late_compute.values,
            self.late_compute.valid,
        )


class WindowRows:
    """The rows of one commit window of one session, as columns of LOG_SCHEMA.

    Not thread-safe: the committer writes and swaps it under its own lock. `lengths` (from
    `columns.expected_lengths`) fixes the width of the model's vector columns.
    """

    def __init__(self, *, lengths: dict[str, int], capacity: int = INITIAL_ROWS) -> None:
        if capacity < 1:
            raise InvalidArgument(f"capacity must be >= 1 row, got {capacity}")
        unknown = sorted(set(lengths) - set(ARRAY_FIELDS))
        if unknown:
            raise InvalidArgument(f"lengths must name array columns of the log, got {unknown}")
        self._lengths = dict(lengths)
        self._capacity = capacity
        self._scalars = [_Scalars(f, capacity) for f in SCALAR_FIELDS if f.type != pa.string()]
        self._texts = [_Texts(f, capacity) for f in SCALAR_FIELDS if f.type == pa.string()]
        self._vectors = [_Vectors(name, capacity, lengths.get(name)) for name in ARRAY_FIELDS]
        self._order = self._column_order()
        # The fast path's groups: numbers that are never null, then the other scalars.
        self._numbers = [c for c in self._scalars if c.valid is None and not isinstance(c.values, bytearray)]
        self._nullable = [
            c for c in self._scalars if c.valid is not None and not isinstance(c.values, bytearray)
        ]
        self._flags = [c for c in self._scalars if isinstance(c.values, bytearray)]
        self._get_vectors = operator.attrgetter(*ARRAY_FIELDS)
        self._seq = next(s for s in self._scalars if s.field.name == "seq")
        self._named = _Named(self._scalars, self._texts)
        self._targets = self._named.targets()
        named = self._named
        self._result_texts = (named.kind, named.source, *named.empty)
        self._viewed: pa.RecordBatch | None = None  # the batch viewing every column, at capacity
        # Each row's vectors (ARRAY_FIELDS order), held until `batch` copies them into their blocks.
        self._held: list[tuple[Any, ...] | None] = [None] * capacity
        self.rows = 0
        # The highest seq of a result among the rows (None: only rejections, or no rows).
        self.top_seq: int | None = None

    def _column_order(self) -> list[_Scalars | _Texts | _Vectors]:
        by_name: dict[str, _Scalars | _Texts | _Vectors] = {c.field.name: c for c in self._scalars}
        by_name.update({c.field.name: c for c in self._texts})
        by_name.update({c.name: c for c in self._vectors})
        return [by_name[name] for name in LOG_SCHEMA.names]

    def spare(self) -> WindowRows:
        """An empty window for the same session, as large as this one has grown."""
        return WindowRows(lengths=self._lengths, capacity=self._capacity)

    def append(self, record: TickRecord) -> None:
        """Write `record` as the next row. InvalidArgument, naming the column, when a value does not
        fit it; the row is then not added (nothing of it is stored)."""
        vectors = tuple(
            column.check(value) for column, value in zip(self._vectors, self._get_vectors(record))
        )
        row = self.rows
        if row == self._capacity:
            self._grow()
        try:
            stale = self._write_fast(row, record)
        except Exception:  # noqa: BLE001 - written again column by column, which names the culprit
            stale = self._write_checked(row, record)
        if stale:
            self._viewed = None
        self._held[row] = vectors
        self.rows = row + 1
        if record.kind == "result":
            seq = int(self._seq.values[row])
            if self.top_seq is None or seq > self.top_seq:
                self.top_seq = seq

    def append_result(self, values: ResultRow) -> None:
        """Write a tick's result as the next row, from its values (`ResultRow`), without a
        `TickRecord`: the server's record path (server/transport/messages.py `record_tick`). The
        vectors are held, not copied, until `batch` copies each column's into its block, so they
        must not change until then, and `batch` names a column whose vector does not fit. The
        scalars are stored in a straight line; a value it does not take (a word not yet encoded,
        a wrong type) is written by the checked path, as a record, which names the column."""
        (
            seq,
            source,
            t,
            server_time,
            frame_t,
            late_ticks,
            frame_delay,
            nis,
            reinitialised,
            late_compute,
            compute_us,
            receive_to_send_us,
            vectors,
        ) = values
        if len(vectors) != len(ARRAY_FIELDS):
            raise InvalidArgument(
                f"a row needs {len(ARRAY_FIELDS)} vectors ({', '.join(ARRAY_FIELDS)}), got {len(vectors)}"
            )
        row = self.rows
        if row == self._capacity:
            self._grow()
        # One function, no call per column: a row is written between a server's sleeps, its
        # caches cold, where every call and numpy item store costs microseconds.
        try:
            byte, bit = row >> 3, 1 << (row & 7)
            unset = 0xFF ^ bit
            (
                seq_at,
                t_at,
                server_time_at,
                late_ticks_at,
                compute_at,
                sent_at,
                frame_t_at,
                frame_t_valid,
                delay_at,
                delay_valid,
                nis_at,
                nis_valid,
                received_bits,
                reinitialised_bits,
                late_bits,
                late_valid,
            ) = self._targets
            seq_at[row] = seq
            t_at[row] = t
            server_time_at[row] = server_time
            late_ticks_at[row] = late_ticks
            compute_at[row] = compute_us
            sent_at[row] = receive_to_send_us
            if frame_t is None:
                frame_t_at[row] = 0.0
                frame_t_valid[byte] &= unset
                received_bits[byte] &= unset
            else:
                frame_t_at[row] = frame_t
                frame_t_valid[byte] |= bit
                received_bits[byte] |= bit
            if frame_delay is None:
                delay_at[row] = 0.0
                delay_valid[byte] &= unset
            else:
                delay_at[row] = frame_delay
                delay_valid[byte] |= bit
            if nis is None:
                nis_at[row] = 0.0
                nis_valid[byte] &= unset
            else:
                nis_at[row] = nis
                nis_valid[byte] |= bit
            if reinitialised is True:
                reinitialised_bits[byte] |= bit
            elif reinitialised is False:
                reinitialised_bits[byte] &= unset
            else:
                raise TypeError("reinitialised")
            late_valid[byte] |= bit
            if late_compute is True:
                late_bits[byte] |= bit
            elif late_compute is False:
                late_bits[byte] &= unset
            else:
                raise TypeError("late_compute")
            kind, source_text, reason, message = self._result_texts
            # A word not yet encoded (KeyError) or a full buffer (IndexError): the checked path.
            start = kind.end
            end = start + 6  # len("result")
            if end > len(kind.data):
                raise IndexError(end)
            kind.data[start:end] = kind.encoded["result"]
            kind.view[row + 1] = kind.end = end
            encoded = source_text.encoded[source]
            start = source_text.end
            end = start + len(encoded)
            if end > len(source_text.data):
                raise IndexError(end)
            source_text.data[start:end] = encoded
            source_text.view[row + 1] = source_text.end = end
            reason.view[row + 1] = reason.end
            message.view[row + 1] = message.end
            stale = False
        except Exception:  # noqa: BLE001 - written again as a record, column by column
            stale = self._write_checked(row, _result_record(values))
        if stale:
            self._viewed = None
        self._held[row] = vectors
        self.rows = row + 1
        top = self.top_seq
        if top is None or seq > top:
            self.top_seq = seq

    def _write_fast(self, row: int, record: TickRecord) -> bool:
        """A record's scalars: numbers into numpy; anything else goes to the column's own `write`.
        True when the viewing batch is stale."""
        byte, bit = row >> 3, 1 << (row & 7)
        unset = 0xFF ^ bit
        stale = False
        for number in self._numbers:
            number.values[row] = number.get(record)
        for scalar in self._nullable:
            value = scalar.get(record)
            if value is None:
                scalar.values[row] = 0
                scalar.valid[byte] &= unset  # type: ignore[index]
            else:
                scalar.values[row] = value
                scalar.valid[byte] |= bit  # type: ignore[index]
        for flag in self._flags:
            value = flag.get(record)
            if value is True and flag.valid is None:
                flag.values[byte] |= bit
            elif value is False and flag.valid is None:
                flag.values[byte] &= unset
            else:
                flag.write(row, value)
        for text in self._texts:
            value = text.get(record)
            encoded = text.encoded.get(value) if type(value) is str else None
            if encoded is None or text.end + len(encoded) > len(text.data):
                stale |= text.write(row, value)
            else:
                end = text.end + len(encoded)
                if encoded:
                    text.data[text.end : end] = encoded
                text.offsets[row + 1] = text.end = end
        return stale

    def _write_checked(self, row: int, record: TickRecord) -> bool:
        """A record's scalars column by column, each checking its value: InvalidArgument names the
        first that does not fit."""
        stale = False
        self._rewind(row)
        try:
            for scalar in self._scalars:
                scalar.write(row, scalar.get(record))
            for text in self._texts:
                stale |= text.write(row, text.get(record))
        except BaseException:
            self._viewed = None  # a column may have been allocated anew before the one that failed
            self._rewind(row)
            raise
        return stale

    def _rewind(self, row: int) -> None:
        for text in self._texts:
            text.rewind(row)

    def _grow(self) -> None:
        self._held.extend([None] * self._capacity)
        self._capacity *= 2
        for column in self._order:
            column.grow(self._capacity)
        self._targets = self._named.targets()
        self._viewed = None

    def batch(self) -> pa.RecordBatch:
        """The rows as one batch of LOG_SCHEMA, viewing these columns: serialise or copy it before
        the next `append` or `clear`. Each vector column's rows are copied into its block here,
        one numpy copy a column; InvalidArgument names a column whose vector does not fit."""
        rows = self.rows
        if rows:
            stale = False
            for vectors, values in zip(self._vectors, zip(*self._held[:rows], strict=True), strict=True):
                stale |= vectors.fill(values)
            if stale:
                self._viewed = None
        if self._viewed is None:
            columns = [c.array(self._capacity) for c in self._order]
            self._viewed = pa.RecordBatch.from_arrays(columns, schema=LOG_SCHEMA)
        batch = self._viewed.slice(0, self.rows)
        for vectors in self._vectors:
            if vectors.listed is not None:
                i = LOG_SCHEMA.get_field_index(vectors.name)
                listed = pa.array(vectors.listed[: self.rows], type=FLOAT_LIST)
                batch = batch.set_column(i, LOG_SCHEMA.field(i), listed)
        return batch

    def clear(self) -> None:
        """Forget the rows (their batch was written); the columns keep their size."""
        for vectors in self._vectors:
            vectors.clear()
        for text in self._texts:
            text.end = 0
        self._held[: self.rows] = [None] * self.rows
        self.rows = 0
        self.top_seq = None
