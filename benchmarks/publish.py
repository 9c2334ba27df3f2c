"""What publishing a finished session's Parquet to the data root costs at its close
(storage/root.py `DataRoot.publish`): to an S3-compatible store (moto_server here) and to a
shared folder (a local one, with fsync), side by side in one run, for files of several sizes.
Prints p50/p99 per file.

    python benchmarks/publish.py [--sizes 100000 1000000 10000000] [--repeats 20]

Needs moto_server (pip install 'moto[server]').
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pyarrow.fs as pafs

from jitdyn.storage.root import DataRoot, open_data_root


def percentiles(samples: list[float]) -> str:
    ordered = sorted(samples)
    p99 = ordered[min(len(ordered) - 1, int(0.99 * len(ordered)))]
    return f"p50 {1e3 * statistics.median(ordered):7.2f} ms  p99 {1e3 * p99:7.2f} ms"


def timed(root: DataRoot, source: Path, repeats: int) -> list[float]:
    samples = []
    for n in range(repeats):
        started = time.perf_counter()
        root.publish(source, f"frames/model=bench/date=2026-11-25/{source.stem}-{n}.parquet")
        samples.append(time.perf_counter() - started)
    return samples


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[100_000, 1_000_000, 10_000_000])
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    port = 5077
    moto = subprocess.Popen(
        [str(Path(sys.executable).parent / "moto_server"), "-H", "127.0.0.1", "-p", str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        time.sleep(3)
        env = {
            "AWS_ENDPOINT_URL": f"http://127.0.0.1:{port}",
            "AWS_REGION": "us-east-1",
            "AWS_ACCESS_KEY_ID": "bench",
            "AWS_SECRET_ACCESS_KEY": "bench",
        }
        pafs.S3FileSystem(
            endpoint_override=f"127.0.0.1:{port}",
            scheme="http",
            access_key="bench",
            secret_key="bench",
            region="us-east-1",
            allow_bucket_creation=True,
        ).create_dir("bench")
        with tempfile.TemporaryDirectory() as tmp:
            shared = Path(tmp) / "shared"
            shared.mkdir()
            roots = {
                "S3 (moto)": open_data_root("s3://bench/root", environ=env),
                "shared folder": open_data_root(str(shared), environ={}),
            }
            for size in args.sizes:
                source = Path(tmp) / f"session-{size}.parquet"
                source.write_bytes(os.urandom(size))  # incompressible, as zstd'd floats nearly are
                for name, root in roots.items():
                    print(
                        f"{size / 1e6:6.1f} MB  {name:<14} {percentiles(timed(root, source, args.repeats))}"
                    )
    finally:
        moto.terminate()
        moto.wait(timeout=10)


if __name__ == "__main__":
    main()
