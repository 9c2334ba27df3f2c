"""What a commit window costs when it must reach storage off the host: one PostgreSQL transaction
for every session's rows (storage/shared.py), against one object per window in an S3-compatible
store (moto_server here), side by side in one run. Prints p50/p99 per window.

    python benchmarks/shared_commit.py [--sessions 8 32] [--windows 200]

Needs PostgreSQL at 127.0.0.1:5432 (database `test`) and moto_server (pip install 'moto[server]').
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import statistics
import subprocess
import sys
import time
import uuid

import psycopg
import pyarrow.fs as pafs
import sqlalchemy as sa

from jitdyn.storage.db import open_index
from jitdyn.storage.schema import session_leases
from jitdyn.storage.shared import Lease, SharedTier, Window

ROW_BYTES = 600  # about one tick record of a 2-link pendulum, serialised


def percentiles(samples: list[float]) -> str:
    ordered = sorted(samples)
    p99 = ordered[min(len(ordered) - 1, int(0.99 * len(ordered)))]
    return f"p50 {1e3 * statistics.median(ordered):6.2f} ms  p99 {1e3 * p99:6.2f} ms"


def postgres(sessions: int, windows: int) -> list[float]:
    name = f"jitdyn_bench_{uuid.uuid4().hex[:8]}"
    with psycopg.connect("host=127.0.0.1 user=root dbname=test", autocommit=True) as admin:
        admin.execute(f'CREATE DATABASE "{name}"')
    try:
        engine = open_index(f"postgresql+psycopg://root@127.0.0.1:5432/{name}")
        tier = SharedTier(engine, owner="bench", lease_ttl=10)
        leases = [Lease(str(uuid.uuid4()), 1) for _ in range(sessions)]
        with engine.begin() as conn:
            for lease in leases:
                conn.execute(
                    sa.insert(session_leases).values(
                        session_id=lease.session_id,
                        owner="bench",
                        epoch=1,
                        expires_at=dt.datetime.now(dt.UTC),
                        header_json="{}",
                    )
                )
        took = []
        for k in range(windows):
            batch = [Window(lease, k, os.urandom(ROW_BYTES), first=k) for lease in leases]
            started = time.perf_counter()
            tier.commit(batch)
            took.append(time.perf_counter() - started)
        engine.dispose()
        return took
    finally:
        with psycopg.connect("host=127.0.0.1 user=root dbname=test", autocommit=True) as admin:
            admin.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


def s3(sessions: int, windows: int, endpoint: str) -> list[float]:
    fs = pafs.S3FileSystem(
        access_key="x",
        secret_key="x",
        endpoint_override=endpoint,
        scheme="http",
        region="us-east-1",
        allow_bucket_creation=True,
    )
    bucket = f"bench-{uuid.uuid4().hex[:8]}"
    fs.create_dir(bucket)
    took = []
    for k in range(windows):
        data = os.urandom(ROW_BYTES * sessions)  # every session's rows of the window, one object
        started = time.perf_counter()
        with fs.open_output_stream(f"{bucket}/log/{k:08d}.arrows") as out:
            out.write(data)
        took.append(time.perf_counter() - started)
    return took


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--sessions", type=int, nargs="+", default=[8, 32])
    parser.add_argument("--windows", type=int, default=200)
    args = parser.parse_args()
    port = 5999
    moto = subprocess.Popen(
        [os.path.join(os.path.dirname(sys.executable), "moto_server"), "-p", str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        time.sleep(3)
        for n in args.sessions:
            print(f"{n:3d} sessions, one window: PostgreSQL {percentiles(postgres(n, args.windows))}")
            print(
                f"{n:3d} sessions, one window: S3 (moto)  {percentiles(s3(n, args.windows, f'127.0.0.1:{port}'))}"
            )
    finally:
        moto.terminate()
        moto.wait()


if __name__ == "__main__":
    main()
