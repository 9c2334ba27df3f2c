"""A stalled event loop (a long garbage collection, a blocking call, a busy neighbour) makes a
REALTIME server skip the ticks it is too late for. In a session whose frames come late, after a
short stall (at most twice its wait of ticks left waiting) the frames that were waiting for those
ticks are applied as late frames, CORRECTED; after a longer one, or in a session whose frames come
on time, they are answered as TOO_OLD rejections and stored with their values: no measurement a
client sent is lost. A real server in this process, its loop blocked for real; the stored Parquet read
back."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq
import pytest

from jitdyn.client import Client, FrameData, Rejection, SessionOptions, TickResult

DT = 0.05


@pytest.mark.parametrize("stall_ticks", [4, 14], ids=["short", "long"])
def test_frames_waiting_for_ticks_a_stall_skipped_are_applied_or_rejected_and_stored(
    tmp_path: Path, make_config: Any, stall_ticks: int
) -> None:
    from jitdyn.server.transport.background import BackgroundServer

    data = tmp_path / "data"
    with BackgroundServer(make_config(data)) as server, Client(server.address, timeout=30) as client:
        session = client.open_session(
            SessionOptions(model_name="pendulum_3", dt=DT, clock="REALTIME", scenario="PASSIVE")
        )
        ticks = 30
        frames = [
            FrameData(seq=k, t=k * DT, qpos=[0.1 * k, -0.2, 0.3], qvel=[0.0, 0.0, 0.0]) for k in range(ticks)
        ]
        # Frames 0-9 come two ticks late: the session waits for late frames (its wait is 2, so a
        # stall may leave 4 ticks waiting); the rest are sent early and wait on the server.
        for k in range(10):
            time.sleep(max(0.0, (k + 2) * DT - session.now()))
            session.send(frames[k])
        for k in range(10, ticks):
            session.send(frames[k])
        time.sleep(0.05)
        # The server's own loop (a test may reach in): blocked for `stall_ticks` ticks.
        server._loop.call_soon_threadsafe(time.sleep, stall_ticks * DT)
        answers: dict[int, object] = {}
        for answer in session.results(timeout=10):
            if isinstance(answer, (TickResult, Rejection)):
                answers.setdefault(answer.seq, answer)
            # The first answer past the last frame's tick: every frame has been answered by then
            # (applied, or rejected with the stall's skipped ticks, which may reach the last one).
            if isinstance(answer, TickResult) and answer.seq >= ticks - 1:
                break
        summary = session.close()

    rejected = sorted(seq for seq, a in answers.items() if isinstance(a, Rejection))
    corrected = sorted(
        seq
        for seq, a in answers.items()
        if seq >= 10 and isinstance(a, TickResult) and a.source == "CORRECTED"
    )
    print(f"after a {stall_ticks}-tick stall: corrected {corrected}, rejected {rejected}")
    if stall_ticks <= 4:
        assert not rejected, "a short stall's frames are applied, not refused"
        assert len(corrected) >= stall_ticks - 2, "the skipped ticks' frames were applied late"
    else:
        assert rejected, "the stall skipped no tick with a waiting frame"
        assert all(answers[seq].reason == "TOO_OLD" for seq in rejected)  # type: ignore[attr-defined]
        assert "skipped ticks" in answers[rejected[0]].message  # type: ignore[attr-defined]
    table = pq.read_table(data / summary.location)
    kept = {}
    for row in table.select(["kind", "seq", "frame_received", "frame_qpos"]).to_pylist():
        if (row["kind"] == "result" and row["frame_received"]) or (
            row["kind"] == "rejected" and row["frame_qpos"] is not None
        ):
            kept.setdefault(row["seq"], row["frame_qpos"])
    assert sorted(kept) == list(range(ticks)), "every frame sent is in the record"
    for seq in rejected:
        assert kept[seq] == frames[seq].qpos, "a rejected frame's values as sent"
