"""One finished session's Parquet file, read where the index says it is: a URI on a data root (S3
settings from the environment) or a path in the data folder. What export and plot both read.

    row = SessionIndex(engine).get(session_id, tenant="")
    metadata, table = read_stored(row, data_root=Path("jitdyn-data"), environ=os.environ, purpose="export")
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.fs as pafs
import pyarrow.parquet as pq

from jitdyn.errors import FailedPrecondition, NotFound, Unavailable
from jitdyn.storage.columns import LOG_SCHEMA
from jitdyn.storage.index import SessionRow
from jitdyn.storage.parquet import read_metadata
from jitdyn.storage.root import is_uri, open_location

__all__ = ["read_stored"]


def read_stored(
    row: SessionRow,
    *,
    data_root: Path,
    environ: Mapping[str, str],
    purpose: str,
    columns: Sequence[str] = LOG_SCHEMA.names,
) -> tuple[dict[str, Any], pa.Table]:
    """The session's Parquet metadata and its rows (`columns` of LOG_SCHEMA), from where its
    location says.

    Raises FailedPrecondition for a session with no Parquet file yet (still open; the message says
    to `purpose` it once it has ended), NotFound when the file is missing, Unavailable when it
    cannot be read (a data root that does not answer).
    """
    if not row.location:
        raise FailedPrecondition(
            f"session {row.session_id} is {row.status} and has no Parquet file yet; {purpose} it once it has ended"
        )
    filesystem, path = open_location(row.location, data=data_root, environ=environ)
    try:
        if filesystem.get_file_info(path).type != pafs.FileType.File:
            where = row.location if is_uri(row.location) else path
            raise NotFound(f"the Parquet file of session {row.session_id} is missing: {where}")
        metadata = read_metadata(path, filesystem=filesystem)
        present = set(pq.read_schema(path, filesystem=filesystem).names)
        table = pq.read_table(path, columns=[c for c in columns if c in present], filesystem=filesystem)
    except OSError as error:
        reason = " ".join(str(error).split())
        raise Unavailable(f"the Parquet file of session {row.session_id} cannot be read: {reason}") from None
    # Columns stored since the file was written are read as nulls.
    for name in columns:
        if name not in table.column_names:
            table = table.append_column(
                LOG_SCHEMA.field(name), pa.nulls(table.num_rows, LOG_SCHEMA.field(name).type)
            )
    return metadata, table.select(list(columns))
