"""SQL over the stored sessions with DuckDB: the tenant's Parquet files as `frames`, its index rows
as `sessions`, and the names and units of the elements of frames' arrays as `coordinates`.

    table = run_query(
        "SELECT s.subject_pseudonym, max(list_max(f.qfrc_inverse)) FROM frames f "
        "JOIN sessions s USING (session_id) GROUP BY 1",
        data_root=root, engine=engine)

`frames` has the columns of storage.columns.FRAME_SCHEMA plus the Hive partitions `model`
(VARCHAR) and `date` (DATE). The connection can read exactly the tenant's files and nothing else:
no other file, no extension download, no Python variable, no configuration change.

Files on a data root (the index holds their URIs: s3://..., file://...) are read through a pyarrow
dataset registered in DuckDB, with pyarrow's S3 client (DuckDB's httpfs extension would be
downloaded at run time, which the connection forbids); files in the data folder by DuckDB itself.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Mapping, Sequence
from pathlib import Path, PurePosixPath
from typing import Any, Final

import duckdb
import pyarrow as pa
import pyarrow.dataset as pads
import pyarrow.fs as pafs
import sqlalchemy as sa

from jitdyn.errors import InvalidArgument, Unavailable
from jitdyn.storage.columns import FRAME_SCHEMA
from jitdyn.storage.index import SessionIndex, SessionRow
from jitdyn.storage.joints import stored_joints
from jitdyn.storage.parquet import read_metadata
from jitdyn.storage.records import FORCE_UNITS
from jitdyn.storage.root import is_uri, open_location

__all__ = ["COORDINATES_SCHEMA", "SESSIONS_SCHEMA", "coordinates_table", "run_query", "sessions_table"]

_log = logging.getLogger(__name__)

_TIMESTAMP: Final = pa.timestamp("us", tz="UTC")
SESSIONS_SCHEMA: Final = pa.schema(
    [
        pa.field("session_id", pa.string()),
        pa.field("model_id", pa.string()),
        pa.field("model_name", pa.string()),
        pa.field("model_version", pa.int32()),
        pa.field("scenario", pa.string()),
        pa.field("clock", pa.string()),
        pa.field("dt", pa.float64()),
        pa.field("estimator", pa.string()),  # JSON
        pa.field("subject_pseudonym", pa.string()),
        pa.field("subject_attributes", pa.map_(pa.string(), pa.string())),
        pa.field("started_at", _TIMESTAMP),
        pa.field("ended_at", _TIMESTAMP),
        pa.field("status", pa.string()),
        pa.field("ticks", pa.int64()),
        pa.field("frames", pa.int64()),
        pa.field("measured", pa.int64()),
        pa.field("predicted", pa.int64()),
        pa.field("corrected", pa.int64()),
        pa.field("rejected", pa.int64()),
        pa.field("late", pa.int64()),
        pa.field("mean_compute_us", pa.float64()),
        pa.field("max_compute_us", pa.float64()),
        pa.field("duration", pa.float64()),
        pa.field("stats", pa.string()),  # JSON
        pa.field("location", pa.string()),
    ]
)
_PARTITIONS: Final = (pa.field("model", pa.string()), pa.field("date", pa.date32()))
# One row per element of a session's arrays: `vector` 'qpos' (frame_qpos, qpos: nq) or 'dof' (qvel,
# qacc, qfrc_inverse, ...: nv); `i` as DuckDB indexes a list, from 1. `unit` of the coordinate (its
# rates per s and s^2; '' for a quaternion's), `force_unit` of a dof's generalized force.
COORDINATES_SCHEMA: Final = pa.schema(
    [
        pa.field("session_id", pa.string()),
        pa.field("vector", pa.string()),
        pa.field("i", pa.int32()),
        pa.field("name", pa.string()),
        pa.field("joint", pa.string()),
        pa.field("unit", pa.string()),
        pa.field("force_unit", pa.string()),
    ]
)


def sessions_table(rows: Sequence[SessionRow]) -> pa.Table:
    """Index rows as an Arrow table of SESSIONS_SCHEMA (the tenant column left out)."""
    columns: dict[str, list[object]] = {f.name: [] for f in SESSIONS_SCHEMA}
    for row in rows:
        s = row.summary
        values: dict[str, object] = {
            "session_id": row.session_id,
            "model_id": row.model_id,
            "model_name": row.model_name,
            "model_version": row.model_version,
            "scenario": row.scenario,
            "clock": row.clock,
            "dt": row.dt,
            "estimator": json.dumps(row.estimator),
            "subject_pseudonym": row.subject_pseudonym,
            "subject_attributes": list(row.subject_attributes.items()),
            "started_at": row.started_at,
            "ended_at": row.ended_at,
            "status": row.status,
            "ticks": s.ticks,
            "frames": s.frames,
            "measured": s.measured,
            "predicted": s.predicted,
            "corrected": s.corrected,
            "rejected": s.rejected,
            "late": s.late,
            "mean_compute_us": s.mean_compute_us,
            "max_compute_us": s.max_compute_us,
            "duration": s.duration,
            "stats": json.dumps(s.stats),
            "location": row.location,
        }
        for name, value in values.items():
            columns[name].append(value)
    return pa.table(columns, schema=SESSIONS_SCHEMA)


def coordinates_table(metadata: Sequence[dict[str, Any]]) -> pa.Table:
    """The `coordinates` rows of the sessions whose files' metadata (storage.parquet) is given."""
    rows: list[dict[str, Any]] = []
    for meta in metadata:
        session = meta.get("session_id", "")
        for joint in stored_joints(meta):
            units = joint.dof_units
            for k, (position, name) in enumerate(zip(joint.qpos, joint.qpos_names, strict=True)):
                # A free joint's x, y, z are metres; quaternion components have no unit.
                unit = units[0] if len(joint.qpos) == 1 else "m" if k < 3 and len(joint.qpos) == 7 else ""
                rows.append({"session_id": session, "vector": "qpos", "i": position + 1, "name": name,
                             "joint": joint.name, "unit": unit, "force_unit": ""})  # fmt: skip
            for dof, name, unit in zip(joint.dofs, joint.dof_names, units, strict=True):
                rows.append({"session_id": session, "vector": "dof", "i": dof + 1, "name": name,
                             "joint": joint.name, "unit": unit, "force_unit": FORCE_UNITS.get(unit, "")})  # fmt: skip
    return pa.Table.from_pylist(rows, schema=COORDINATES_SCHEMA)


def _session_metadata(
    rows: Sequence[SessionRow], *, data_root: Path, environ: Mapping[str, str]
) -> list[dict[str, Any]]:
    """The metadata of each session's Parquet file that can be read; a missing one is left out (its
    frames are too)."""
    found = []
    for row in rows:
        if not row.location:
            continue
        try:
            if is_uri(row.location):
                filesystem, path = open_location(row.location, data=data_root, environ=environ)
                found.append(read_metadata(path, filesystem=filesystem))
            else:
                found.append(read_metadata(data_root / row.location))
        except (OSError, InvalidArgument):
            continue
    return found


def _sql_string(text: str) -> str:
    return "'" + text.replace("'", "''") + "'"


def _frame_files(rows: Sequence[SessionRow], data_root: Path) -> list[str]:
    files: list[str] = []
    for row in rows:
        if not row.location:
            continue
        path = (data_root / row.location).resolve()
        if path.is_file():
            files.append(str(path))
        else:
            _log.warning("session %s: its Parquet file %s is missing", row.session_id, path)
    return files


def _root_datasets(rows: Sequence[SessionRow], *, data_root: Path, environ: Mapping[str, str]) -> Any:
    """One pyarrow dataset of every file the rows name (on data roots or in the data folder), Hive
    partitions parsed below each root's `frames` folder; None when there is none."""
    groups: dict[tuple[str, str], tuple[Any, list[str]]] = {}
    for row in rows:
        if row.location:
            filesystem, path = open_location(row.location, data=data_root, environ=environ)
            base = str(PurePosixPath(path).parents[2])  # <root>/frames, above model=/date=/<file>
            groups.setdefault((filesystem.type_name, base), (filesystem, []))[1].append(path)
    partitioning = pads.partitioning(pa.schema(_PARTITIONS), flavor="hive")
    schema = pa.schema([*FRAME_SCHEMA, *_PARTITIONS])
    datasets = []
    for (_, base), (filesystem, paths) in groups.items():
        try:
            infos = filesystem.get_file_info(paths)
        except OSError as error:
            reason = " ".join(str(error).split())
            raise Unavailable(f"the data root holding {base} cannot be read: {reason}") from None
        present = [info.path for info in infos if info.type == pafs.FileType.File]
        for info in infos:
            if info.type != pafs.FileType.File:
                _log.warning("a session's Parquet file %s is missing", info.path)
        if present:
            datasets.append(
                pads.dataset(
                    present,
                    filesystem=filesystem,
                    format="parquet",
                    partitioning=partitioning,
                    partition_base_dir=base,
                    schema=schema,
                )
            )
    return pads.dataset(datasets) if datasets else None


def _connect(
    *, sessions: pa.Table, coordinates: pa.Table, files: list[str], dataset: Any = None
) -> duckdb.DuckDBPyConnection:
    con = duckdb.connect(
        ":memory:",
        config={"autoinstall_known_extensions": False, "autoload_known_extensions": False},
    )
    try:
        # Otherwise a query could read any Python variable in scope by naming it.
        con.execute("SET python_enable_replacements = false")
        con.register("sessions", sessions)
        con.register("coordinates", coordinates)
        empty = pa.schema([*FRAME_SCHEMA, *_PARTITIONS]).empty_table()
        con.register("_empty_frames", empty)
        if dataset is not None:
            con.register("_root_frames", dataset)
            con.execute("CREATE VIEW frames AS SELECT * FROM _root_frames")
        elif files:
            listing = "[" + ", ".join(_sql_string(f) for f in files) + "]"
            # Explicit partition types: a model named "123" stays a name, not a number. The empty
            # table in front gives every column, those of files written before a column was stored
            # too (NULL there), in the schema's order.
            con.execute(
                "CREATE VIEW frames AS SELECT * FROM _empty_frames UNION ALL BY NAME "
                f"SELECT * FROM read_parquet({listing}, hive_partitioning = true, "
                "union_by_name = true, hive_types = {'model': 'VARCHAR', 'date': 'DATE'})"
            )
        else:
            con.execute("CREATE VIEW frames AS SELECT * FROM _empty_frames")
        con.execute(f"SET allowed_paths = [{', '.join(_sql_string(f) for f in files)}]")
        con.execute("SET enable_external_access = false")
        con.execute("SET lock_configuration = true")
    except BaseException:
        con.close()
        raise
    return con


def run_query(
    sql: str,
    *,
    data_root: Path,
    engine: sa.Engine,
    tenant: str = "",
    environ: Mapping[str, str] | None = None,
) -> pa.Table:
    """Run one SQL statement (DuckDB's dialect) over the tenant's `frames` and `sessions`. Files on
    a data root are reached with the S3 settings of `environ` (default os.environ).

    Raises InvalidArgument with DuckDB's message when the SQL fails (syntax, unknown column, access
    to a file outside the dataset). The statement runs in a throw-away in-memory database; one
    without a result (CREATE VIEW) gives an empty table, a write gives DuckDB's count of rows written.
    """
    rows = SessionIndex(engine).all_sessions(tenant=tenant)
    env = os.environ if environ is None else environ
    tables = {
        "sessions": sessions_table(rows),
        "coordinates": coordinates_table(_session_metadata(rows, data_root=data_root, environ=env)),
    }
    if any(is_uri(row.location) for row in rows):
        dataset = _root_datasets(rows, data_root=data_root, environ=env)
        con = _connect(**tables, files=[], dataset=dataset)
    else:
        con = _connect(**tables, files=_frame_files(rows, data_root))
    try:
        relation = con.sql(sql)
        if relation is None:
            return pa.table({})
        return relation.to_arrow_table()
    except duckdb.Error as exc:
        raise InvalidArgument(f"the query failed: {exc}") from exc
    finally:
        con.close()
