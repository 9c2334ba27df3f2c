"""Finding 8 (last part): compaction and recovery stream a session's log in bounded memory. A
server killed in a long session of a large model leaves a 190 MB log; the next `jitdyn serve`
recovers it with every acknowledged row and without holding it in memory."""

from __future__ import annotations

import datetime as dt
import uuid
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
from _hostile import Served, stored

from jitdyn.storage.columns import records_to_batch
from jitdyn.storage.db import default_index_url, open_index
from jitdyn.storage.index import SessionIndex
from jitdyn.storage.layout import log_location
from jitdyn.storage.log import LogWriter
from jitdyn.storage.parquet import header_to_json
from jitdyn.storage.records import SessionHeader, TickRecord

NV = 600
ROWS = 5000
BATCH = 100


def _dead_session(data: Path) -> str:
    """What a killed server leaves: an OPEN row and an unlocked log of ROWS results at nv = NV."""
    names = tuple(f"j{i}" for i in range(NV))
    header = SessionHeader(
        session_id=str(uuid.uuid4()),
        tenant="",
        model_id="sha256:" + "cd" * 32,
        model_name="big",
        model_version=1,
        joint_names=names,
        joint_types=("hinge",) * NV,
        dof_names=names,
        actuator_names=(),
        nq=NV,
        nv=NV,
        nu=0,
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
    engine = open_index(default_index_url(data))
    try:
        path = data / log_location(header.session_id)
        path.parent.mkdir(parents=True, exist_ok=True)
        writer = LogWriter(path, header_json=header_to_json(header))
        rng = np.random.default_rng(0)
        vector = rng.standard_normal(NV)
        for start in range(0, ROWS, BATCH):
            records = [
                TickRecord(
                    kind="result",
                    seq=seq,
                    source="MEASURED",
                    t=seq * 0.01,
                    server_time=seq * 0.01,
                    frame_received=True,
                    frame_qpos=vector,
                    frame_qvel=vector,
                    qpos=vector,
                    qvel=vector,
                    qacc=vector,
                    qfrc_inverse=vector,
                    covariance_diagonal=np.abs(np.concatenate([vector, vector])),
                    filter_state=np.concatenate([vector, vector]),
                    compute_us=100,
                )
                for seq in range(start, start + BATCH)
            ]
            writer.write(records_to_batch(records))
        writer.release()  # no end-of-stream marker: as after kill -9
        SessionIndex(engine).create(header, log_path=log_location(header.session_id))
    finally:
        engine.dispose()
    assert path.stat().st_size > 150e6
    return header.session_id


def test_recovery_streams_a_long_log_in_bounded_memory(serve: Callable[..., Served]) -> None:
    first = serve()
    baseline = first.resources().hwm_mb
    first.kill()
    session_id = _dead_session(first.data)
    second = serve()  # recovers before it listens
    (recovered,) = stored(second, "RECOVERED")
    assert recovered.session_id == session_id
    assert recovered.summary.ticks == ROWS and recovered.summary.measured == ROWS
    table = pq.read_table(second.data / recovered.location, columns=["seq"])
    assert table["seq"].to_pylist() == list(range(ROWS))  # no acknowledged row lost
    assert second.resources().hwm_mb - baseline < 150, (second.resources(), baseline)
