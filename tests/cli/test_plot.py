"""`jitdyn sessions plot`: real sessions streamed to a real server over gRPC (LOCKSTEP with skips
and a late frame, REALTIME with gaps and a delayed frame, an empty one, one stored as FAILED), then
drawn by the command as a user runs it: a PNG of sensible size, an HTML page with its SVG inline,
and one line, never a traceback, for each thing a user can get wrong."""

from __future__ import annotations

import io
import os
import re
import struct
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import pyarrow as pa
import pytest
import sqlalchemy as sa
from _cli import jitdyn

from jitdyn.client import Client, FrameData, Rejection, SessionOptions
from jitdyn.registry import builtin_model_path
from jitdyn.storage.db import default_index_url, open_index
from jitdyn.storage.schema import sessions

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def one_line_error(result: subprocess.CompletedProcess[str]) -> str:
    assert result.returncode == 1, result.stdout + result.stderr
    assert "Traceback" not in result.stderr, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("jitdyn sessions plot: "), result.stderr
    return lines[0]


def truth(name: str, ticks: int, dt: float) -> list[tuple[np.ndarray, np.ndarray]]:
    model = mujoco.MjModel.from_xml_path(str(builtin_model_path(name)))
    data = mujoco.MjData(model)
    data.qpos[:] = np.random.default_rng(3).uniform(-0.6, 0.6, model.nq)
    states = []
    for _ in range(ticks):
        states.append((data.qpos.copy(), data.qvel.copy()))
        for _ in range(round(dt / model.opt.timestep)):
            mujoco.mj_step(model, data)
    return states


def lockstep_session(client: Client) -> str:
    """pendulum_2, 40 ticks: ticks 10-12 and 25 skipped (gaps), tick 12's frame sent late, tick 30's
    frame sent twice (the second rejected)."""
    dt = 0.05
    with client.open_session(SessionOptions(model_name="pendulum_2", scenario="PASSIVE", dt=dt)) as session:
        states = truth("pendulum_2", 40, dt)
        for k, (q, v) in enumerate(states):
            if k in (10, 11, 12, 25):
                session.skip(k)
            else:
                session.send_frame(FrameData(seq=k, t=k * dt, qpos=q, qvel=v))
            if k == 14:
                q12, v12 = states[12]
                session.send_frame(FrameData(seq=12, t=12 * dt, qpos=q12, qvel=v12))
            if k == 30:
                assert isinstance(session.send_frame(FrameData(seq=k, t=k * dt, qpos=q, qvel=v)), Rejection)
        return session.opened.session_id


def realtime_session(client: Client) -> str:
    """pendulum_1 on the server's clock, 30 ticks of 25 ms: frames 8-11 never sent, 20 sent late."""
    dt, ticks = 0.025, 30
    states = truth("pendulum_1", ticks, dt)
    with client.open_session(
        SessionOptions(model_name="pendulum_1", scenario="PASSIVE", dt=dt, clock="REALTIME")
    ) as session:
        session.sync()
        timers = []
        for k, (q, v) in enumerate(states):
            time.sleep(max(0.0, k * dt - session.now()))
            frame = FrameData(seq=k, t=k * dt, qpos=q, qvel=v)
            if 8 <= k <= 11:
                continue
            if k == 20:
                timers.append(threading.Timer(2.5 * dt, session.send, args=(frame,)))
                timers[-1].start()
            else:
                session.send(frame)
        for timer in timers:
            timer.join()
        time.sleep(3 * dt)
        return session.opened.session_id


@dataclass(frozen=True)
class Stored:
    data: Path
    lockstep: str
    realtime: str
    empty: str
    failed: str


@pytest.fixture(scope="module")
def stored(server: Any) -> Iterator[Stored]:
    with Client(server.address, timeout=60) as client:
        lockstep = lockstep_session(client)
        realtime = realtime_session(client)
        with client.open_session(SessionOptions(model_name="pendulum_3", dt=0.05)) as session:
            empty = session.opened.session_id
        failed = lockstep_session(client)
    data = Path(server.services.data_root)
    # A session that ended by an error keeps what it received; the plot must say which it is.
    engine = open_index(default_index_url(data))
    with engine.begin() as connection:
        connection.execute(sa.update(sessions).where(sessions.c.session_id == failed).values(status="FAILED"))
    engine.dispose()
    yield Stored(data=data, lockstep=lockstep, realtime=realtime, empty=empty, failed=failed)


def png_size(path: Path) -> tuple[int, int]:
    header = path.read_bytes()[:24]
    assert header[:8] == PNG_SIGNATURE and header[12:16] == b"IHDR", header
    width, height = struct.unpack(">II", header[16:24])
    return int(width), int(height)


@pytest.mark.parametrize("which", ["lockstep", "realtime"])
def test_a_session_plots_to_a_png_named_by_its_id(stored: Stored, which: str, tmp_path: Path) -> None:
    session_id = getattr(stored, which)
    result = jitdyn("sessions", "plot", session_id, "--data", str(stored.data), cwd=tmp_path)
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stdout == f"plotted {session_id} to {session_id}.png\n", result.stdout
    width, height = png_size(tmp_path / f"{session_id}.png")
    assert width == 1500 and 800 <= height <= 3000, (width, height)
    assert 30_000 < (tmp_path / f"{session_id}.png").stat().st_size < 3_000_000


def test_the_timeline_holds_the_gaps_and_the_late_frames(stored: Stored) -> None:
    from jitdyn.storage.db import open_index
    from jitdyn.storage.index import SessionIndex
    from jitdyn.storage.stored import read_stored
    from jitdyn.storage.timeline import session_timeline

    engine = open_index(default_index_url(stored.data))
    try:
        row = SessionIndex(engine).get(stored.lockstep, tenant="")
        _, table = read_stored(row, data_root=stored.data, environ={}, purpose="plot")
    finally:
        engine.dispose()
    timeline = session_timeline(table)
    assert timeline.seq.tolist() == list(range(40))
    assert np.flatnonzero(timeline.gap).tolist() == [10, 11, 25]
    assert np.flatnonzero(timeline.corrected).tolist() == [12]
    assert timeline.source[12] == "PREDICTED" and timeline.source[13] == "MEASURED"
    assert np.isnan(timeline.frame_qpos[10]).all() and not np.isnan(timeline.frame_qpos[12]).any()
    np.testing.assert_array_equal(timeline.frame_qpos[12], timeline.corrected_qpos[12])
    assert timeline.rejections.seq.tolist() == [30] and timeline.rejections.reason.tolist() == ["DUPLICATE"]

    engine = open_index(default_index_url(stored.data))
    try:
        row = SessionIndex(engine).get(stored.realtime, tenant="")
        _, table = read_stored(row, data_root=stored.data, environ={}, purpose="plot")
    finally:
        engine.dispose()
    realtime = session_timeline(table)
    assert {8, 9, 10, 11} <= set(realtime.seq[realtime.gap].tolist())
    # Frame 20 came 2.5 ticks late: replayed, unless a loaded machine made it too old to be.
    assert 20 in realtime.seq[realtime.corrected] or 20 in realtime.rejections.seq
    assert np.isfinite(realtime.frame_delay[realtime.framed]).all()


def test_html_is_one_page_with_the_figure_inline(stored: Stored, tmp_path: Path) -> None:
    out = tmp_path / "walk.html"
    result = jitdyn(
        "sessions",
        "plot",
        stored.realtime,
        "--data",
        str(stored.data),
        "--out",
        str(out),
        "--joints",
        "hinge_1",
    )
    assert result.returncode == 0, result.stderr
    page = out.read_text(encoding="utf-8")
    assert page.startswith("<!DOCTYPE html>") and page.count("<svg") == 1 and "</svg>" in page
    assert "<script" not in page and 'src="http' not in page
    assert f"<td>{stored.realtime}</td>" in page and "<td>REALTIME" not in page  # scenario, clock cell
    assert "PASSIVE, REALTIME" in page
    assert os.listdir(tmp_path) == ["walk.html"]  # nothing beside it (no temporary file left)


def png_title(path: Path) -> str:
    """The PNG's tEXt "Title", which the command sets to the figure's first title line."""
    data = path.read_bytes()
    at = 8
    while at < len(data):
        (length,) = struct.unpack(">I", data[at : at + 4])
        kind, body = data[at + 4 : at + 8], data[at + 8 : at + 8 + length]
        if kind == b"tEXt" and body.startswith(b"Title\0"):
            return body[len(b"Title\0") :].decode("latin-1")
        at += 12 + length
    raise AssertionError(f"{path} has no Title")


def test_a_failed_session_still_plots_with_its_status(stored: Stored, tmp_path: Path) -> None:
    out = tmp_path / "failed.png"
    result = jitdyn("sessions", "plot", stored.failed, "--data", str(stored.data), "--out", str(out))
    assert result.returncode == 0, result.stderr
    png_size(out)
    title = png_title(out)
    assert title.startswith(
        f"session {stored.failed}  ·  pendulum_2 v1  ·  PASSIVE LOCKSTEP, dt 50 ms  ·  FAILED  ·  "
    )


def test_the_first_joints_by_default_or_those_named_in_order() -> None:
    from jitdyn.storage.joints import MAX_SHOWN, choose_joints, stored_joints

    names = [f"j{i}" for i in range(MAX_SHOWN + 2)]
    joints = stored_joints({"joint_names": names, "joint_types": ["hinge"] * len(names)})
    assert [j.name for j in choose_joints(joints, [], model="m")] == names[:MAX_SHOWN]
    assert [j.name for j in choose_joints(joints, ["j7", "j0"], model="m")] == ["j7", "j0"]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["0e0529f0-0000-4000-8000-000000000000"],
            (
                r"NotFound: no session '0e0529f0-0000-4000-8000-000000000000' in \S+; "
                r"list them with `jitdyn sessions list`"
            ),
        ),
        (["{empty}"], r"FailedPrecondition: session {empty} \(COMPLETE\) is empty: no tick was answered"),
        (
            ["{lockstep}", "--joints", "hinge_1", "knee"],
            r"InvalidArgument: pendulum_2 has no joint 'knee'; its joints are hinge_1, hinge_2$",
        ),
        (
            ["{lockstep}", "--out", "walk.jpg"],
            r"InvalidArgument: --out must name a \.png or \.html file, got 'walk\.jpg'$",
        ),
    ],
)
def test_mistakes_are_one_line(stored: Stored, args: list[str], message: str, tmp_path: Path) -> None:
    ids = {"empty": stored.empty, "lockstep": stored.lockstep}
    args = [a.format(**ids) for a in args]
    result = jitdyn("sessions", "plot", *args, "--data", str(stored.data), cwd=tmp_path)
    line = one_line_error(result)
    assert re.fullmatch(r"jitdyn sessions plot: " + message.format(**ids) + r".*", line), line
    assert os.listdir(tmp_path) == []


def test_without_matplotlib_it_names_the_extra(tmp_path: Path) -> None:
    (tmp_path / "index.sqlite").touch()
    result = jitdyn(
        "sessions", "plot", "x", "--data", str(tmp_path), preamble="sys.modules['matplotlib'] = None"
    )
    assert one_line_error(result) == (
        "jitdyn sessions plot: needs matplotlib (plots), which is not installed: pip install 'jitdyn[experiments]'"
    )


def big_table(ticks: int, nq: int) -> pa.Table:
    """The rows of a session of `ticks` ticks of 10 ms: ticks 500-549 of every 1000 a gap, tick 999 of
    every 1000 PREDICTED then CORRECTED."""
    seq = np.arange(ticks)
    late = seq[seq % 1000 == 999]
    rows_seq = np.concatenate([seq, late])
    source = np.where(np.isin(seq, late), "PREDICTED", "MEASURED").tolist() + ["CORRECTED"] * len(late)
    gap = (seq % 1000 >= 500) & (seq % 1000 < 550)
    framed = np.concatenate([~gap & ~np.isin(seq, late), np.ones(len(late), dtype=bool)])
    t = rows_seq * 0.01
    q = np.sin(t)[:, None] + np.arange(nq)[None, :]

    def lists(values: np.ndarray, present: np.ndarray) -> pa.Array:
        offsets = pa.array(np.arange(len(values) + 1, dtype=np.int32) * values.shape[1])
        return pa.ListArray.from_arrays(offsets, pa.array(values.ravel()), mask=pa.array(~present))

    n = len(rows_seq)
    return pa.table(
        {
            "kind": ["result"] * n,
            "seq": rows_seq,
            "source": source,
            "t": t,
            "frame_received": framed,
            "frame_delay": np.where(framed, 0.02, np.nan),
            "nis": np.where(framed, 2.0, np.nan),
            "compute_us": np.full(n, 300),
            "receive_to_send_us": np.full(n, 400),
            "reject_reason": [""] * n,
            "frame_qpos": lists(q, framed),
            "qpos": lists(q, np.ones(n, dtype=bool)),
            "qfrc_inverse": lists(q * 2, np.ones(n, dtype=bool)),
        }
    )


def test_a_long_session_is_decimated_and_says_so_with_nothing_lost() -> None:
    from jitdyn.cli.session_figure import decimation, draw_session
    from jitdyn.storage.joints import stored_joints
    from jitdyn.storage.timeline import session_timeline

    timeline = session_timeline(big_table(120_000, 2))
    assert len(timeline.t) == 120_000 and timeline.gap.sum() == 120 * 50
    assert timeline.corrected.sum() == 120
    assert decimation(120_000).note == "every 40th tick drawn of 120 000 (sources and gaps: every tick)"
    assert decimation(3000).note == ""
    joints = stored_joints({"joint_names": ["a", "b"], "joint_types": ["hinge", "slide"]})
    started = time.perf_counter()
    figure = draw_session(timeline, joints, title=["big"], dt=0.01, realtime=True)
    figure.savefig(io.BytesIO(), format="png", dpi=50)
    assert time.perf_counter() - started < 20
    # The source strip counts every tick: all 120 corrections are in its label.
    labels = [label.get_text() for label in figure.axes[0].get_yticklabels()]
    assert labels == ["MEASURED 119880", "PREDICTED 120", "CORRECTED (late) 120", "rejected frames 0"]


def test_a_session_on_a_data_root_is_read_where_the_index_says(
    tmp_path: Path, make_config: Callable[..., Any]
) -> None:
    from jitdyn.server.transport.background import BackgroundServer

    data, shared = tmp_path / "data", tmp_path / "shared"
    shared.mkdir()
    with BackgroundServer(make_config(data, data_root_uri=f"file://{shared}")) as running:
        client = Client(running.address, timeout=60)
        with client:
            session_id = lockstep_session(client)
    engine = open_index(default_index_url(data))
    with engine.connect() as connection:
        location = connection.execute(
            sa.select(sessions.c.location).where(sessions.c.session_id == session_id)
        ).scalar_one()
    engine.dispose()
    assert location.startswith(f"file://{shared}/"), location
    assert not list(data.rglob("*.parquet"))  # only the data root's copy is left to read
    out = tmp_path / "shared.png"
    result = jitdyn("sessions", "plot", session_id, "--data", str(data), "--out", str(out))
    assert result.returncode == 0, result.stderr
    png_size(out)


def test_plot_explains_itself() -> None:
    result = jitdyn("sessions", "plot", "--help")
    assert result.returncode == 0 and "usage: jitdyn sessions plot" in result.stdout
    assert "--joints NAME [NAME ...]" in result.stdout and ".png or .html" in result.stdout
