"""Recovery of sessions a dead server left open: torn logs, empty logs, live sessions left alone,
and a real writer process killed with SIGKILL."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from jitdyn.storage.columns import records_to_batch
from jitdyn.storage.db import open_index
from jitdyn.storage.index import SessionIndex
from jitdyn.storage.layout import log_location
from jitdyn.storage.log import LogWriter, read_log
from jitdyn.storage.parquet import header_to_json
from jitdyn.storage.recorder import SessionRecorder, recover_unfinished
from jitdyn.storage.records import SessionHeader, TickRecord

CHILD = Path(__file__).with_name("crash_child.py")
REPO = Path(__file__).resolve().parents[2]


def write_dead_log(
    data_root: Path, index: SessionIndex, header: SessionHeader, batches: list[list[TickRecord]]
) -> Path:
    """What a killed server leaves: an index row OPEN and a log of complete batches, unlocked."""
    path = data_root / log_location(header.session_id)
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = LogWriter(path, header_json=header_to_json(header))
    for batch in batches:
        writer.write(records_to_batch(batch))
    writer.release()  # without the end-of-stream marker, as after a kill
    index.create(header, log_path=log_location(header.session_id))
    return path


def results(seqs: range) -> list[TickRecord]:
    return [TickRecord(kind="result", seq=s, source="MEASURED", t=s * 0.01) for s in seqs]


def test_log_reads_back_to_its_last_complete_batch_at_every_cut(
    tmp_path: Path, make_header: Callable[..., SessionHeader], make_records: Any
) -> None:
    header = make_header()
    records = make_records(12)
    path = tmp_path / "whole.arrows"
    writer = LogWriter(path, header_json=header_to_json(header))
    sizes = [path.stat().st_size]
    for start in range(0, len(records), 4):
        writer.write(records_to_batch(records[start : start + 4]))
        sizes.append(path.stat().st_size)
    writer.release()
    whole = path.read_bytes()
    cut = tmp_path / "cut.arrows"
    # Every batch boundary and its neighbours, and a stride through everything between.
    lengths = set(range(0, len(whole) + 1, 29)) | {s + d for s in sizes for d in (-1, 0, 1)}
    for length in sorted(n for n in lengths if 0 <= n <= len(whole)):
        cut.write_bytes(whole[:length])
        contents = read_log(cut)
        complete = sum(1 for size in sizes[1:] if size <= length)
        assert contents.table.num_rows == min(4 * complete, len(records)), length
        assert contents.table.column("seq").to_pylist() == [r.seq for r in records[: contents.table.num_rows]]
        if length >= sizes[0]:
            assert contents.header_json == header_to_json(header)
        if length in sizes:
            assert not contents.torn, length


def test_recover_torn_log_to_parquet(
    data_root: Path, index: SessionIndex, make_header: Callable[..., SessionHeader]
) -> None:
    header = make_header()
    path = write_dead_log(data_root, index, header, [results(range(10)), results(range(10, 20))])
    with open(path, "ab") as f:  # a batch the writer was killed inside of
        f.write(b"\xff\xff\xff\xff\x10\x01\x00\x00partial")

    assert recover_unfinished(data_root=data_root, index=index) == [header.session_id]
    row = index.get(header.session_id, tenant="")
    assert row.status == "RECOVERED"
    assert row.summary.ticks == 20
    assert row.summary.measured == 20
    assert row.summary.duration == pytest.approx(0.0)
    assert pq.read_table(data_root / row.location).column("seq").to_pylist() == list(range(20))
    assert not path.exists()
    assert recover_unfinished(data_root=data_root, index=index) == []


def test_recover_empty_log_gives_zero_row_parquet(
    data_root: Path, index: SessionIndex, make_header: Callable[..., SessionHeader]
) -> None:
    header = make_header()
    write_dead_log(data_root, index, header, [])
    assert recover_unfinished(data_root=data_root, index=index) == [header.session_id]
    row = index.get(header.session_id, tenant="")
    assert row.status == "RECOVERED"
    table = pq.read_table(data_root / row.location)
    assert table.num_rows == 0
    assert table.schema.field("qpos").type == pa.list_(pa.field("element", pa.float64()))


def test_live_session_and_missing_log_are_left_open(
    data_root: Path, index: SessionIndex, make_header: Callable[..., SessionHeader]
) -> None:
    live = make_header()
    gone = make_header()
    gone_log = write_dead_log(data_root, index, gone, [results(range(3))])
    gone_log.unlink()
    with SessionRecorder(data_root=data_root, index=index, header=live) as recorder:
        recorder.append(TickRecord(kind="result", seq=0, source="MEASURED"))
        recorder.flush()
        # As a second server sharing the data root would: the live writer's lock keeps it out.
        assert recover_unfinished(data_root=data_root, index=index) == []
        assert index.get(live.session_id, tenant="").status == "OPEN"
    assert index.get(live.session_id, tenant="").status == "COMPLETE"
    assert index.get(gone.session_id, tenant="").status == "OPEN"


def test_sigkilled_writer_loses_no_durable_frame(tmp_path: Path) -> None:
    """A child process records through SessionRecorder and prints durable_seq as it advances; it is
    killed with SIGKILL mid-stream. Recovery must find every seq up to the last one printed."""
    data_root = tmp_path / "data"
    data_root.mkdir()
    url = f"sqlite:///{data_root / 'index.sqlite'}"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    with subprocess.Popen(
        [sys.executable, str(CHILD), str(data_root), url],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    ) as child:
        assert child.stdout is not None and child.stderr is not None
        session_id = child.stdout.readline().strip()
        last_durable = -1
        deadline = time.monotonic() + 60
        try:
            while time.monotonic() < deadline:
                line = child.stdout.readline()
                if not line:
                    break
                last_durable = int(line)
                if last_durable >= 3000:
                    break
        finally:
            child.send_signal(signal.SIGKILL)
            child.wait(30)
        stderr = child.stderr.read()
    assert child.returncode == -signal.SIGKILL, stderr
    assert last_durable >= 3000, f"the child printed durable_seq {last_durable} only; stderr: {stderr}"

    engine = open_index(url)
    index = SessionIndex(engine)
    assert index.get(session_id, tenant="").status == "OPEN"
    assert recover_unfinished(data_root=data_root, index=index) == [session_id]
    row = index.get(session_id, tenant="")
    assert row.status == "RECOVERED"
    seqs = pq.read_table(data_root / row.location, columns=["seq"]).column("seq").to_pylist()
    assert seqs[: last_durable + 1] == list(range(last_durable + 1))
    assert row.summary.ticks == len(seqs)
    engine.dispose()
