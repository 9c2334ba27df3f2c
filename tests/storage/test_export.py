"""export_session: CSV (every row, one column per array element) and OpenSim .sto (one row per
tick, corrections replacing predictions), checked line by line."""

from __future__ import annotations

import csv
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import sqlalchemy as sa

from jitdyn.errors import FailedPrecondition, InvalidArgument, NotFound
from jitdyn.storage.export import export_session
from jitdyn.storage.index import SessionIndex
from jitdyn.storage.recorder import SessionRecorder
from jitdyn.storage.records import SessionHeader, TickRecord


def vec(*values: float) -> np.ndarray:
    return np.array(values, dtype=np.float64)


RECORDS = [
    TickRecord(
        kind="result",
        seq=0,
        source="MEASURED",
        t=0.0,
        server_time=0.001,
        frame_received=True,
        frame_t=0.0,
        frame_qpos=vec(0.1, 0.2, 0.3),
        qpos=vec(0.1, 0.2, 0.3),
        qvel=vec(1.0, 2.0, 3.0),
        qacc=vec(-1.0, -2.0, -3.0),
        qfrc_inverse=vec(0.5, 0.25, 0.125),
        nis=1.5,
        compute_us=40,
        receive_to_send_us=55,
    ),
    TickRecord(
        kind="result",
        seq=1,
        source="PREDICTED",
        t=0.01,
        server_time=0.011,
        qpos=vec(0.11, 0.21, 0.31),
        qvel=vec(1.1, 2.1, 3.1),
        qacc=vec(-1.1, -2.1, -3.1),
        qfrc_inverse=vec(0.6, 0.35, 0.225),
        compute_us=90,
        receive_to_send_us=95,
    ),
    TickRecord(
        kind="rejected",
        seq=7,
        t=0.07,
        server_time=0.012,
        reject_reason="BAD_CHECKSUM",
        reject_message='frame 7: checksum 0x1, expected 0x2, "quoted", with a comma',
    ),
    TickRecord(
        kind="result",
        seq=1,
        source="CORRECTED",
        t=0.01,
        server_time=0.015,
        frame_received=True,
        frame_t=0.01,
        frame_qpos=vec(0.12, 0.22, 0.32),
        late_ticks=1,
        frame_delay=0.004,
        qpos=vec(0.12, 0.22, 0.32),
        qvel=vec(1.2, 2.2, 3.2),
        qacc=vec(-1.2, -2.2, -3.2),
        qfrc_inverse=vec(0.7, 0.45, 0.325),
        nis=0.75,
        compute_us=120,
        receive_to_send_us=130,
    ),
]


@pytest.fixture()
def session(data_root: Path, index: SessionIndex, make_header: Callable[..., SessionHeader]) -> SessionHeader:
    header = make_header(tenant="lab")
    with SessionRecorder(data_root=data_root, index=index, header=header) as recorder:
        for r in RECORDS:
            recorder.append(r)
    return header


def test_csv_line_by_line(data_root: Path, engine: sa.Engine, session: SessionHeader, tmp_path: Path) -> None:
    out = export_session(
        session.session_id, data_root=data_root, engine=engine, tenant="lab", fmt="csv", out=tmp_path
    )
    assert out == tmp_path / f"{session.session_id}.csv"
    with open(out, newline="") as f:
        rows = list(csv.reader(f))
    header = rows[0]
    assert header[:16] == [
        "kind",
        "seq",
        "source",
        "t",
        "server_time",
        "frame_received",
        "frame_t",
        "late_ticks",
        "frame_delay",
        "nis",
        "reinitialised",
        "late_compute",
        "compute_us",
        "receive_to_send_us",
        "reject_reason",
        "reject_message",
    ]
    assert header[16:] == [
        "frame_qpos_hinge_1",
        "frame_qpos_hinge_2",
        "frame_qpos_hinge_3",
        "qpos_hinge_1",
        "qpos_hinge_2",
        "qpos_hinge_3",
        "qvel_hinge_1",
        "qvel_hinge_2",
        "qvel_hinge_3",
        "qacc_hinge_1",
        "qacc_hinge_2",
        "qacc_hinge_3",
        "qfrc_inverse_hinge_1",
        "qfrc_inverse_hinge_2",
        "qfrc_inverse_hinge_3",
    ]
    assert len(rows) == 1 + len(RECORDS)
    measured, predicted, rejected, corrected = (dict(zip(header, row, strict=True)) for row in rows[1:])
    assert measured["kind"] == "result" and measured["source"] == "MEASURED"
    assert (measured["seq"], measured["frame_received"], measured["nis"]) == ("0", "true", "1.5")
    assert [float(measured[f"qfrc_inverse_hinge_{i}"]) for i in (1, 2, 3)] == [0.5, 0.25, 0.125]
    assert [float(measured[f"frame_qpos_hinge_{i}"]) for i in (1, 2, 3)] == [0.1, 0.2, 0.3]
    assert predicted["source"] == "PREDICTED"
    assert (predicted["frame_t"], predicted["nis"], predicted["frame_qpos_hinge_1"]) == ("", "", "")
    assert [float(predicted[f"qvel_hinge_{i}"]) for i in (1, 2, 3)] == [1.1, 2.1, 3.1]
    assert (rejected["kind"], rejected["seq"], rejected["reject_reason"]) == ("rejected", "7", "BAD_CHECKSUM")
    assert rejected["reject_message"] == RECORDS[2].reject_message
    assert rejected["qpos_hinge_1"] == ""
    assert (corrected["source"], corrected["late_ticks"], corrected["frame_delay"]) == (
        "CORRECTED",
        "1",
        "0.004",
    )
    assert float(corrected["qfrc_inverse_hinge_3"]) == 0.325


def test_sto_line_by_line(data_root: Path, engine: sa.Engine, session: SessionHeader, tmp_path: Path) -> None:
    out = export_session(
        session.session_id,
        data_root=data_root,
        engine=engine,
        tenant="lab",
        fmt="sto",
        out=tmp_path / "walk.sto",
    )
    lines = out.read_text().splitlines()
    assert lines[:7] == [
        f"jitdyn_{session.session_id}",
        "version=1",
        "nRows=2",
        "nColumns=15",
        "inDegrees=no",
        "source=1 MEASURED, 2 PREDICTED, 3 CORRECTED",
        "endheader",
    ]
    assert lines[7] == "\t".join(
        ["time", "hinge_1", "hinge_2", "hinge_3"]
        + [f"qfrc_inverse_hinge_{i}" for i in (1, 2, 3)]
        + [f"qvel_hinge_{i}" for i in (1, 2, 3)]
        + [f"qacc_hinge_{i}" for i in (1, 2, 3)]
        + ["nis", "source"]
    )
    # Tick 0 as measured; tick 1 as corrected, its prediction gone; no rejected frame.
    assert lines[8] == "0.0\t0.1\t0.2\t0.3\t0.5\t0.25\t0.125\t1.0\t2.0\t3.0\t-1.0\t-2.0\t-3.0\t1.5\t1.0"
    assert lines[9] == "0.01\t0.12\t0.22\t0.32\t0.7\t0.45\t0.325\t1.2\t2.2\t3.2\t-1.2\t-2.2\t-3.2\t0.75\t3.0"
    assert len(lines) == 10


def test_sto_nan_for_missing_nis(
    data_root: Path,
    engine: sa.Engine,
    index: SessionIndex,
    make_header: Callable[..., SessionHeader],
    tmp_path: Path,
) -> None:
    header = make_header()
    with SessionRecorder(data_root=data_root, index=index, header=header) as recorder:
        recorder.append(RECORDS[1])
    lines = export_session(
        header.session_id, data_root=data_root, engine=engine, fmt="sto", out=tmp_path
    ).read_text()
    row = lines.splitlines()[-1].split("\t")
    assert row[-2] == "NaN" and math.isnan(float(row[-2]))
    assert row[-1] == "2.0"


def test_export_errors(
    data_root: Path,
    engine: sa.Engine,
    index: SessionIndex,
    session: SessionHeader,
    make_header: Callable[..., SessionHeader],
    tmp_path: Path,
) -> None:
    with pytest.raises(NotFound):
        export_session(
            session.session_id, data_root=data_root, engine=engine, tenant="", fmt="csv", out=tmp_path
        )
    with pytest.raises(InvalidArgument, match="format must be one of csv, sto, got 'mot'"):
        export_session(
            session.session_id,
            data_root=data_root,
            engine=engine,
            tenant="lab",
            fmt="mot",  # type: ignore[arg-type]
            out=tmp_path,
        )
    with pytest.raises(InvalidArgument, match="the folder of the export target"):
        export_session(
            session.session_id,
            data_root=data_root,
            engine=engine,
            tenant="lab",
            fmt="csv",
            out=tmp_path / "no" / "x.csv",
        )
    open_header = make_header()
    recorder = SessionRecorder(data_root=data_root, index=index, header=open_header)
    with pytest.raises(FailedPrecondition) as error:
        export_session(open_header.session_id, data_root=data_root, engine=engine, fmt="csv", out=tmp_path)
    assert str(error.value) == (
        f"session {open_header.session_id} is OPEN and has no Parquet file yet; export it once it has ended"
    )
    recorder.close()
