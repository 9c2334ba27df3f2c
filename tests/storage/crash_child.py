"""The writer test_recovery.py kills: records pendulum ticks through SessionRecorder without end,
printing the session id, then durable_seq each time it advances.

    python crash_child.py DATA_ROOT INDEX_URL
"""

from __future__ import annotations

import datetime as dt
import sys
import time
from pathlib import Path

import numpy as np

# Run as a script, this file's folder is first on sys.path: the storage tests' header is this one's.
from conftest import build_header

from jitdyn.storage.db import open_index
from jitdyn.storage.index import SessionIndex
from jitdyn.storage.recorder import SessionRecorder
from jitdyn.storage.records import TickRecord


def main() -> None:
    data_root, url = Path(sys.argv[1]), sys.argv[2]
    header = build_header(actuator_names=(), started_at=dt.datetime.now(dt.UTC))
    index = SessionIndex(open_index(url))
    recorder = SessionRecorder(data_root=data_root, index=index, header=header, commit_every=64)
    print(header.session_id, flush=True)
    rng = np.random.default_rng(1)
    printed: int | None = None
    seq = 0
    while True:
        recorder.append(
            TickRecord(
                kind="result",
                seq=seq,
                source="MEASURED",
                t=seq * 0.01,
                frame_received=True,
                qpos=rng.standard_normal(3),
                qvel=rng.standard_normal(3),
                qfrc_inverse=rng.standard_normal(3),
            )
        )
        seq += 1
        durable = recorder.durable_seq
        if durable is not None and durable != printed:
            # Printed only once durable: what a client would have seen in a result.
            print(durable, flush=True)
            printed = durable
        if seq % 256 == 0:
            time.sleep(0.001)


if __name__ == "__main__":
    main()
