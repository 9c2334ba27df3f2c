"""The writer test_recovery.py kills: records pendulum ticks through SessionRecorder without end,
printing the session id, then durable_seq each time it advances.

    python crash_child.py DATA_ROOT INDEX_URL
"""

from __future__ import annotations

import datetime as dt
import sys
import time
import uuid
from pathlib import Path

import numpy as np

from jitdyn.storage.db import open_index
from jitdyn.storage.index import SessionIndex
from jitdyn.storage.recorder import SessionRecorder
from jitdyn.storage.records import SessionHeader, TickRecord


def main() -> None:
    data_root, url = Path(sys.argv[1]), sys.argv[2]
    header = SessionHeader(
        session_id=str(uuid.uuid4()),
        tenant="",
        model_id="sha256:" + "cd" * 32,
        model_name="pendulum_3",
        model_version=1,
        joint_names=("hinge_1", "hinge_2", "hinge_3"),
        joint_types=("hinge", "hinge", "hinge"),
        dof_names=("hinge_1", "hinge_2", "hinge_3"),
        nq=3,
        nv=3,
        nu=3,
        nsensordata=0,
        timestep=0.002,
        dt=0.01,
        scenario="PASSIVE",
        clock="LOCKSTEP",
        estimator={"estimator": "UKF"},
        subject_pseudonym="",
        subject_attributes={},
        started_at=dt.datetime.now(dt.UTC),
    )
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
