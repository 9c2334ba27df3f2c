"""The S3 path before storage takes it: pyarrow's own S3 client writes and reads a Parquet
dataset on a real S3-speaking server (moto_server), and DuckDB queries it through a pyarrow
dataset registered in DuckDB, as an analyst will query the data root (DuckDB's httpfs extension is
downloaded at run time, which these machines cannot do)."""

from __future__ import annotations

import duckdb
import numpy as np
import pyarrow as pa
import pyarrow.dataset as pads
import pyarrow.fs as pafs
import pyarrow.parquet as pq
from _cluster import MotoS3

BUCKET = "jitdyn-data"


def _s3(server: MotoS3) -> pafs.S3FileSystem:
    # The settings the replicas will take from AWS_ENDPOINT_URL, AWS_REGION and the keys; moto
    # accepts any keys.
    return server.filesystem()


def _frames(session: str, ticks: int) -> pa.Table:
    rng = np.random.default_rng(7)
    return pa.table(
        {
            "session_id": [session] * ticks,
            "seq": np.arange(ticks, dtype=np.int64),
            "t": np.arange(ticks) * 0.05,
            "qpos": [list(row) for row in rng.normal(size=(ticks, 2))],
        }
    )


def test_parquet_on_s3_is_written_read_and_queried_by_duckdb(moto_s3: MotoS3) -> None:
    s3 = _s3(moto_s3)
    s3.create_dir(BUCKET)
    written = {f"session-{n}": _frames(f"session-{n}", 20 + n) for n in range(3)}
    for session, table in written.items():
        pq.write_table(table, f"{BUCKET}/sessions/model=pendulum_2/{session}.parquet", filesystem=s3)

    listed = s3.get_file_info(pafs.FileSelector(f"{BUCKET}/sessions", recursive=True))
    assert sorted(info.base_name for info in listed if info.is_file) == [f"{s}.parquet" for s in written]
    back = pq.read_table(f"{BUCKET}/sessions/model=pendulum_2/session-1.parquet", filesystem=s3)
    assert back.equals(written["session-1"])

    dataset = pads.dataset(f"{BUCKET}/sessions", filesystem=s3, format="parquet", partitioning="hive")
    with duckdb.connect() as connection:
        connection.register("frames", dataset)
        rows = connection.sql(
            "SELECT session_id, model, count(*) AS ticks, max(seq) AS last FROM frames "
            "GROUP BY session_id, model ORDER BY session_id"
        ).fetchall()
    print(f"DuckDB over s3://{BUCKET}/sessions on moto_server: {rows}")
    assert rows == [(f"session-{n}", "pendulum_2", 20 + n, 19 + n) for n in range(3)]
