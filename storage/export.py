"""Export of one stored session for tools outside jitdyn: CSV, and OpenSim's .sto.

    export_session(session_id, data_root=root, engine=engine, fmt="sto", out=Path("walk.sto"))

CSV holds every stored row (results, corrections and rejections, in the order the server
answered), one column per array element, named by the element: `qpos_hinge_1`, `qfrc_inverse_hinge_1`,
`actuator_force_motor_1`, `sensordata_0`. The .sto file holds one row per tick, the latest result
of each (a CORRECTED result replaces the PREDICTED one), with time, the coordinates named by joint
(radians and metres, inDegrees=no), the generalized forces `qfrc_inverse_<dof>` and the other
estimates; OpenSim, OpenSim Creator and pandas read it.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Final, Literal

import numpy as np
import numpy.typing as npt
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.csv as pacsv
import sqlalchemy as sa

from jitdyn.errors import InvalidArgument
from jitdyn.storage.columns import ARRAY_FIELDS, SCALAR_FIELDS, list_matrix
from jitdyn.storage.index import SessionIndex
from jitdyn.storage.stored import read_stored
from jitdyn.vocabulary import Source, to_proto

__all__ = [
    "FORMATS",
    "SOURCE_CODES",
    "SOURCE_LEGEND",
    "atomic_write",
    "element_names",
    "export_session",
    "export_target",
    "latest_results",
]

FORMATS: Final = ("csv", "sto")
# Source as numbers in .sto, whose columns are all numeric: the proto's enum values.
SOURCE_CODES: Final = {source: float(to_proto(source)) for source in Source}
# A .sto holds numbers only: the header says what the codes of the `source` column mean (a
# key=value line, which OpenSim keeps as metadata).
SOURCE_LEGEND: Final = "source=" + ", ".join(f"{code:g} {name}" for name, code in SOURCE_CODES.items())
# The estimate columns of .sto after time, coordinates and qfrc_inverse, in this order.
_STO_ESTIMATES: Final = (
    "qvel",
    "qacc",
    "qacc_forward",
    "actuator_force",
    "sensordata",
    "covariance_diagonal",
    "filter_state",
)


def element_names(column: str, metadata: dict[str, Any], length: int) -> list[str]:
    """Names of the `length` elements of an array column, from the file's metadata: qpos names,
    dof names or actuator names where they fit, indices otherwise."""
    if column in ("qpos", "frame_qpos"):
        names = metadata.get("qpos_names", [])
    elif column in ("qvel", "qacc", "qfrc_inverse", "qacc_forward", "frame_qvel", "frame_qacc"):
        names = metadata.get("dof_names", [])
    elif column in ("actuator_force", "frame_ctrl"):
        names = metadata.get("actuator_names", [])
    else:
        names = []
    if len(names) == length:
        return [str(n) for n in names]
    return [str(i) for i in range(length)]


def atomic_write(out: Path, write: Any) -> None:
    """`write(path)` into a temporary file beside `out`, renamed to `out` when it returns."""
    tmp = out.with_name(f".{out.name}.tmp")
    try:
        write(tmp)
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)


def _csv(table: pa.Table, metadata: dict[str, Any], out: Path) -> None:
    columns: dict[str, pa.Array] = {}
    for f in SCALAR_FIELDS:
        columns[f.name] = table.column(f.name)
    for name in ARRAY_FIELDS:
        matrix = list_matrix(table.column(name))
        if matrix is None:
            continue
        missing = pc.is_null(table.column(name)).to_numpy(zero_copy_only=False)
        for j, element in enumerate(element_names(name, metadata, matrix.shape[1])):
            columns[f"{name}_{element}"] = pa.array(matrix[:, j], mask=missing)
    flat = pa.table(columns)
    atomic_write(out, lambda p: pacsv.write_csv(flat, p, pacsv.WriteOptions(quoting_style="needed")))


def latest_results(table: pa.Table) -> pa.Table:
    """One result per seq, the last one appended (a correction comes after what it corrects),
    ordered by seq."""
    results = table.filter(pc.equal(table["kind"], "result"))
    seqs = results["seq"].to_numpy()
    last: dict[int, int] = {}
    for i, seq in enumerate(seqs.tolist()):
        last[seq] = i
    order = [last[seq] for seq in sorted(last)]
    return results.take(pa.array(order, pa.int64()))


def _format(value: float) -> str:
    return "NaN" if math.isnan(value) else repr(float(value))


def _sto(table: pa.Table, metadata: dict[str, Any], out: Path, name: str) -> None:
    ticks = latest_results(table)
    headers: list[str] = ["time"]
    blocks: list[npt.NDArray[np.float64]] = [ticks["t"].to_numpy().reshape(-1, 1)]
    qpos = list_matrix(ticks["qpos"])
    if qpos is not None:
        # Coordinates are named by their joint, as OpenSim names coordinates.
        headers += element_names("qpos", metadata, qpos.shape[1])
        blocks.append(qpos)
    for column in ("qfrc_inverse", *_STO_ESTIMATES):
        matrix = list_matrix(ticks[column])
        if matrix is None:
            continue
        headers += [f"{column}_{e}" for e in element_names(column, metadata, matrix.shape[1])]
        blocks.append(matrix)
    nis = ticks["nis"].to_numpy(zero_copy_only=False).astype(np.float64)
    codes = {source.value: code for source, code in SOURCE_CODES.items()}
    source = np.array([codes.get(s, math.nan) for s in ticks["source"].to_pylist()])
    headers += ["nis", "source"]
    blocks += [nis.reshape(-1, 1), source.reshape(-1, 1)]
    data = np.hstack(blocks) if ticks.num_rows else np.zeros((0, len(headers)))

    def write(path: Path) -> None:
        with open(path, "w", encoding="utf-8", newline="\n") as f:
            f.write(
                f"{name}\nversion=1\nnRows={data.shape[0]}\nnColumns={len(headers)}\ninDegrees=no\n"
                f"{SOURCE_LEGEND}\nendheader\n"
            )
            f.write("\t".join(headers) + "\n")
            f.writelines("\t".join(_format(v) for v in row) + "\n" for row in data)

    atomic_write(out, write)


def export_target(out: Path, session_id: str, fmt: str) -> Path:
    """The file to write: `out`, or `<id>.<fmt>` in it when it is a folder."""
    if out.is_dir():
        return out / f"{session_id}.{fmt}"
    if not out.parent.is_dir():
        raise InvalidArgument(f"the folder of the export target {out} does not exist")
    return out


def export_session(
    session_id: str,
    *,
    data_root: Path,
    engine: sa.Engine,
    tenant: str = "",
    fmt: Literal["csv", "sto"],
    out: Path,
    environ: Mapping[str, str] | None = None,
) -> Path:
    """Write the session's rows as `fmt` to `out` (a file, or a folder to put `<id>.<fmt>` in),
    atomically; returns the path written.

    The Parquet file is read where the index says: a URI on a data root (S3 settings from
    `environ`, default os.environ), or a path relative to `data_root`.

    Raises NotFound for an unknown session (or another tenant's), FailedPrecondition for a session
    still open (nothing compacted yet), InvalidArgument for an unknown format, Unavailable when the
    data root does not answer.
    """
    if fmt not in FORMATS:
        raise InvalidArgument(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    row = SessionIndex(engine).get(session_id, tenant=tenant)
    metadata, table = read_stored(
        row, data_root=data_root, environ=os.environ if environ is None else environ, purpose="export"
    )
    target = export_target(out, session_id, fmt)
    if fmt == "csv":
        _csv(table, metadata, target)
    else:
        _sto(table, metadata, target, name=f"jitdyn_{session_id}")
    return target
