"""Storage benchmark: sustained frames/s into a session's crash-safe log, and the compaction of a
long session to Parquet, with bytes per frame in each.

    python -m benchmarks.storage                 # 200k frames for throughput, 1e6 for compaction
    python -m benchmarks.storage --frames 500000 --compact-frames 1000000
    python -m benchmarks.storage --close         # only: the cost of closing a 20 Hz session
    python -m benchmarks.storage --record-path   # only: a record's CPU, columns against lists

Frames are pendulum_3-sized results (nq = nv = nu = 3) as the session runtime records them: the
frame's qpos and qvel, the estimate, qacc, qfrc_inverse, the covariance diagonal and the filter
state (6 values each), NIS and timings, on a smooth trajectory so that compression sees realistic
data. "append" is what the event loop pays per frame; "durable" counts until the last frame is
fsynced. Target: >= 100k frames/s. The many-sessions case compares one group committer for all the
sessions of a process (one fsync per commit window: docs/decisions/0040-group-commit-window.md) against one per session.
`--close` measures what the server pays when a slow session ends: the compaction of a log of many
tiny group commits, on a thread beside a thread that wakes every millisecond as the event loop does.
`--record-path` sets what a record costs the server, the tick's row and its share of the commit
thread's batch, as the committer does it now (the tick's values written straight into preallocated
columns, the window's batch a view of them: storage/buffers.py) beside the way it did before (a
TickRecord built and queued in a list, one batch converted from all sessions' records per window
and sliced per session), on the same values in one run; the write and the fsync, the same in both,
are left out.
"""

from __future__ import annotations

import argparse
import datetime as dt
import operator
import os
import statistics
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from jitdyn.storage.buffers import WindowRows
from jitdyn.storage.columns import ARRAY_FIELDS, expected_lengths, records_to_batch
from jitdyn.storage.commit import GroupCommitter
from jitdyn.storage.db import open_index
from jitdyn.storage.index import SessionIndex
from jitdyn.storage.recorder import SessionRecorder
from jitdyn.storage.records import SessionHeader, TickRecord
from jitdyn.vocabulary import Clock, EstimatorKind, Preset, Scenario, SigmaScheme, Source

DT = 0.001


def header() -> SessionHeader:
    return SessionHeader(
        session_id=str(uuid.uuid4()),
        tenant="",
        model_id="sha256:" + "00" * 32,
        model_name="pendulum_3",
        model_version=1,
        joint_names=("hinge_1", "hinge_2", "hinge_3"),
        joint_types=("hinge", "hinge", "hinge"),
        dof_names=("hinge_1", "hinge_2", "hinge_3"),
        nq=3,
        nv=3,
        nu=3,
        nsensordata=0,
        timestep=0.001,
        dt=DT,
        scenario=Scenario.PASSIVE,
        clock=Clock.LOCKSTEP,
        estimator={
            "estimator": EstimatorKind.UKF,
            "preset": Preset.JITDYN,
            "sigma_points": SigmaScheme.MERWE,
        },
        subject_pseudonym="",
        subject_attributes={},
        started_at=dt.datetime.now(dt.UTC),
    )


class Trajectory:
    """A smooth three-link motion and its derived channels, one row per frame."""

    def __init__(self, n: int, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        t = np.arange(n)[:, None] * DT
        freq = np.array([0.7, 1.1, 1.6])
        phase = rng.random(3) * 2 * np.pi
        self.t = t[:, 0]
        self.qpos = 0.8 * np.sin(2 * np.pi * freq * t + phase)
        self.qvel = 0.8 * 2 * np.pi * freq * np.cos(2 * np.pi * freq * t + phase)
        self.qacc = -((2 * np.pi * freq) ** 2) * self.qpos
        self.qfrc = 9.81 * np.sin(self.qpos) + 0.3 * self.qacc
        self.cov = 1e-4 + 1e-5 * rng.random((n, 6))
        self.state = np.hstack([self.qpos, self.qvel]) + 1e-4 * rng.standard_normal((n, 6))
        self.nis = rng.chisquare(6, n)
        self.compute = rng.integers(80, 400, n)

    def row(self, i: int) -> tuple[Any, ...]:
        """Frame `i` as `WindowRows.append_result` takes it: a tick's values, no TickRecord."""
        vectors: dict[str, npt.NDArray[np.float64] | None] = dict.fromkeys(ARRAY_FIELDS)
        vectors.update(
            frame_qpos=self.qpos[i],
            frame_qvel=self.qvel[i],
            qpos=self.qpos[i],
            qvel=self.qvel[i],
            qacc=self.qacc[i],
            qfrc_inverse=self.qfrc[i],
            covariance_diagonal=self.cov[i],
            filter_state=self.state[i],
        )
        t = float(self.t[i])
        compute = int(self.compute[i])
        return (
            i,
            Source.MEASURED,
            t,
            t + 2e-4,
            t,
            0,
            0.0,
            float(self.nis[i]),
            False,
            False,
            compute,
            compute + 30,
            tuple(vectors.values()),
        )

    def record(self, i: int) -> TickRecord:
        """Frame `i` as the committer takes it: the TickRecord the tick builds from `row(i)`."""
        return _record(*self.row(i))


def throughput(root: Path, index: SessionIndex, frames: int) -> dict[str, float]:
    trajectory = Trajectory(frames)
    started = time.perf_counter()
    records = [trajectory.record(i) for i in range(frames)]
    build_us = (time.perf_counter() - started) / frames * 1e6
    del records
    rows = [trajectory.row(i) for i in range(frames)]
    samples: list[float] = []
    recorder = SessionRecorder(data_root=root, index=index, header=header())
    append = recorder.append_result
    started = time.perf_counter()
    for i, row in enumerate(rows):
        if i % 97 == 0:
            t0 = time.perf_counter_ns()
            append(row)
            samples.append((time.perf_counter_ns() - t0) / 1e3)
        else:
            append(row)
    appended = time.perf_counter() - started
    recorder.flush()
    durable = time.perf_counter() - started
    result = {
        "build_us": build_us,
        "append_rate": frames / appended,
        "durable_rate": frames / durable,
        "append_p50_us": statistics.median(samples),
        "append_p99_us": float(np.percentile(samples, 99)),
        "commits": recorder.commits,
        "log_bytes_per_frame": recorder.log_bytes / frames,
    }
    recorder.close()
    return result


def paced(root: Path, index: SessionIndex, rate: float, seconds: float) -> dict[str, float]:
    """Append at `rate` frames/s in 1 ms bursts, idling between them as an event loop does, and
    sample how far durability lags behind (ms of frames appended but not yet fsynced)."""
    frames = int(rate * seconds)
    trajectory = Trajectory(frames, seed=2)
    records = [trajectory.row(i) for i in range(frames)]
    burst = max(1, int(rate / 1000))
    lags: list[float] = []
    recorder = SessionRecorder(data_root=root, index=index, header=header())
    started = time.perf_counter()
    for start in range(0, frames, burst):
        for row in records[start : start + burst]:
            recorder.append_result(row)
        durable = recorder.durable_seq
        lags.append((start + burst - 1 - (-1 if durable is None else durable)) / rate * 1e3)
        pause = started + (start + burst) / rate - time.perf_counter()
        if pause > 0:
            time.sleep(pause)
    recorder.flush()
    elapsed = time.perf_counter() - started
    commits = recorder.commits
    recorder.close()
    return {
        "rate": frames / elapsed,
        "lag_p50_ms": statistics.median(lags),
        "lag_p99_ms": float(np.percentile(lags, 99)),
        "lag_max_ms": max(lags),
        "commits": commits,
    }


def many_sessions(
    root: Path, index: SessionIndex, *, sessions: int, rate: float, seconds: float, shared: bool
) -> dict[str, float]:
    """`sessions` recorders, each appended at `rate` frames/s, their ticks spread over the period
    as a server's sessions are, from one thread (the event loop). `shared`: one GroupCommitter for
    all of them (the server's); else one per session (a commit thread and an fsync per session,
    as before group commit across sessions). CPU is this process's, every thread included."""
    trajectory = Trajectory(int(rate * seconds) + 1, seed=3)
    committers = [GroupCommitter()] if shared else []
    recorders = []
    for _ in range(sessions):
        if not shared:
            committers.append(GroupCommitter())
        recorders.append(
            SessionRecorder(data_root=root, index=index, header=header(), committer=committers[-1])
        )
    period = 1.0 / rate
    ticks = int(rate * seconds)
    lags: list[float] = []
    cpu0 = time.process_time()
    started = time.perf_counter()
    for k in range(ticks):
        for i, recorder in enumerate(recorders):
            due = started + k * period + i * period / sessions
            pause = due - time.perf_counter()
            if pause > 0:
                time.sleep(pause)
            recorder.append_result(trajectory.row(k))
        durable = recorders[0].durable_seq
        lags.append((k - (-1 if durable is None else durable)) * period * 1e3)
    for recorder in recorders:
        recorder.flush()
    cpu = time.process_time() - cpu0
    syncs = sum(c.stats().syncs for c in committers)
    commit_cpu = sum(c.stats().cpu_seconds for c in committers)
    for recorder in recorders:
        recorder.close()
    for committer in committers:
        committer.close()
    records = sessions * ticks
    return {
        "cpu_us_per_record": cpu / records * 1e6,
        "commit_cpu_us_per_record": commit_cpu / records * 1e6,
        "syncs_per_s": syncs / seconds,
        "lag_p99_ms": float(np.percentile(lags, 99)),
    }


def compaction(root: Path, index: SessionIndex, frames: int) -> dict[str, float]:
    trajectory = Trajectory(frames, seed=1)
    recorder = SessionRecorder(data_root=root, index=index, header=header(), commit_every=4096)
    started = time.perf_counter()
    for i in range(frames):
        recorder.append_result(trajectory.row(i))
    recorder.flush()
    built_and_logged = time.perf_counter() - started
    log_bytes = recorder.log_bytes
    started = time.perf_counter()
    location = recorder.close()
    close_seconds = time.perf_counter() - started
    return {
        "log_rate": frames / built_and_logged,
        "close_s": close_seconds,
        "log_bytes_per_frame": log_bytes / frames,
        "parquet_bytes_per_frame": os.path.getsize(root / location) / frames,
    }


def close_cost(root: Path, index: SessionIndex, *, ticks: int, per_commit: int) -> dict[str, float]:
    """Close a `ticks`-tick session whose log holds group commits of `per_commit` records (a 20 Hz
    session's hold one or two) on a thread, as the server does, while this thread sleeps 1 ms at a
    time as an event loop waits for its next tick: the close's wall and CPU time, and how late this
    thread woke (it waits for the GIL while the close holds it), at the 0.5 ms switch interval of a
    server serving a 400 Hz session."""
    trajectory = Trajectory(ticks, seed=4)
    recorder = SessionRecorder(data_root=root, index=index, header=header())
    for i in range(ticks):
        recorder.append_result(trajectory.row(i))
        if (i + 1) % per_commit == 0:
            recorder.flush()
    recorder.flush()
    batches = recorder.commits
    cpu: list[float] = []

    def close() -> None:
        started = time.thread_time()
        recorder.close()
        cpu.append(time.thread_time() - started)

    lags: list[float] = []
    interval = sys.getswitchinterval()
    sys.setswitchinterval(5e-4)
    try:
        closer = threading.Thread(target=close)
        started = time.perf_counter()
        closer.start()
        while closer.is_alive():
            t0 = time.perf_counter()
            time.sleep(0.001)
            lags.append(time.perf_counter() - t0 - 0.001)
        wall = time.perf_counter() - started
        closer.join()
    finally:
        sys.setswitchinterval(interval)
    return {
        "batches": batches,
        "wall_ms": wall * 1e3,
        "cpu_ms": cpu[0] * 1e3,
        "lag_p50_ms": statistics.median(lags) * 1e3,
        "lag_max_ms": max(lags) * 1e3,
    }


def _check_lengths(records: list[TickRecord], lengths: dict[str, int]) -> None:
    """The check the commit thread ran on every queued record before the columns did it on append."""
    checked = [(name, operator.attrgetter(name), expected) for name, expected in lengths.items()]
    for position, record in enumerate(records):
        for name, getter, expected in checked:
            array = getter(record)
            if array is not None and len(array) != expected:
                raise ValueError(f"{name} at {position}: {len(array)} values, not {expected}")


def _listed_window(windows: list[list[tuple[Any, ...]]], lengths: dict[str, int]) -> tuple[float, float]:
    """Before: each tick built a TickRecord and queued it in its session's list, then the commit
    thread converted one batch from every session's records, sliced and serialised per session.
    (s spent building and appending, s spent building the batch and serialising)."""
    queues: list[list[TickRecord]] = [[] for _ in windows]
    lock = threading.Lock()
    started = time.thread_time()
    for k in range(len(windows[0])):
        for queue, rows in zip(queues, windows, strict=True):
            record = _record(*rows[k])
            with lock:
                queue.append(record)
    appended = time.thread_time()
    _check_lengths([r for queue in queues for r in queue], lengths)
    batch = records_to_batch([r for queue in queues for r in queue])
    offset = 0
    for queue in queues:
        batch.slice(offset, len(queue)).serialize()
        offset += len(queue)
    return appended - started, time.thread_time() - appended


def _record(
    seq: int,
    source: str,
    t: float,
    server_time: float,
    frame_t: float | None,
    late_ticks: int,
    frame_delay: float | None,
    nis: float | None,
    reinitialised: bool,
    late_compute: bool,
    compute_us: int,
    receive_to_send_us: int,
    vectors: tuple[npt.NDArray[np.float64] | None, ...],
) -> TickRecord:
    """The TickRecord the tick built before, from the same values, as messages.tick_record did."""
    (
        frame_qpos,
        frame_qvel,
        frame_qacc,
        frame_ctrl,
        frame_sensordata,
        qpos,
        qvel,
        qacc,
        qfrc_inverse,
        qacc_forward,
        actuator_force,
        sensordata,
        covariance_diagonal,
        filter_state,
        forecast_weights,
    ) = vectors
    return TickRecord(
        kind="result",
        seq=seq,
        source=source,
        t=t,
        server_time=server_time,
        frame_received=frame_t is not None,
        frame_t=frame_t,
        frame_qpos=frame_qpos,
        frame_qvel=frame_qvel,
        frame_qacc=frame_qacc,
        frame_ctrl=frame_ctrl,
        frame_sensordata=frame_sensordata,
        late_ticks=late_ticks,
        frame_delay=frame_delay,
        qpos=qpos,
        qvel=qvel,
        qacc=qacc,
        qfrc_inverse=qfrc_inverse,
        qacc_forward=qacc_forward,
        actuator_force=actuator_force,
        sensordata=sensordata,
        covariance_diagonal=None if covariance_diagonal is None else covariance_diagonal.copy(),
        filter_state=filter_state,
        nis=nis,
        reinitialised=reinitialised,
        late_compute=late_compute,
        forecast_weights=forecast_weights,
        compute_us=compute_us,
        receive_to_send_us=receive_to_send_us,
        reject_reason="",
        reject_message="",
    )


def _columnar_window(windows: list[list[tuple[Any, ...]]], columns: list[WindowRows]) -> tuple[float, float]:
    """Now: each tick writes its values straight into its session's columns (no TickRecord), then
    per session a batch viewing them is serialised. (s spent appending, s spent serialising)."""
    lock = threading.Lock()
    started = time.thread_time()
    for k in range(len(windows[0])):
        for rows, values in zip(columns, windows, strict=True):
            with lock:
                rows.append_result(values[k])
    appended = time.thread_time()
    for rows in columns:
        rows.batch().serialize()
        rows.clear()
    return appended - started, time.thread_time() - appended


def record_path(*, sessions: int, per_window: int, windows: int) -> dict[str, dict[str, float]]:
    """us per record of both ways, alternating window by window so that a noisy moment of the
    shared machine hits both; the median window of each."""
    trajectory = Trajectory(per_window * windows, seed=5)
    lengths = expected_lengths(header())
    columns = [WindowRows(lengths=lengths) for _ in range(sessions)]
    samples: dict[str, list[tuple[float, float]]] = {"lists": [], "columns": []}
    for w in range(windows):
        base = w * per_window
        batch = [[trajectory.row(base + k) for k in range(per_window)] for _ in range(sessions)]
        samples["lists"].append(_listed_window(batch, lengths))
        samples["columns"].append(_columnar_window(batch, columns))
    records = sessions * per_window
    out = {}
    for way, runs in samples.items():
        append = statistics.median(a for a, _ in runs) / records * 1e6
        commit = statistics.median(c for _, c in runs) / records * 1e6
        out[way] = {"append_us": append, "commit_us": commit, "total_us": append + commit}
    return out


def print_record_path(args: argparse.Namespace) -> None:
    print(
        f"a record's CPU (us), pendulum_3 rows, {args.sessions_per_window} sessions a commit window, "
        f"median of {args.windows} windows each; {os.cpu_count()} CPUs"
    )
    print(f"{'rows/session/window':>20}{'way':>10}{'append':>10}{'batch':>10}{'total':>10}{'before/now':>12}")
    for per_window in args.rows_per_window:
        result = record_path(sessions=args.sessions_per_window, per_window=per_window, windows=args.windows)
        ratio = result["lists"]["total_us"] / result["columns"]["total_us"]
        for way, label in (("lists", "before"), ("columns", "now")):
            r = result[way]
            print(
                f"{per_window:>20}{label:>10}{r['append_us']:>10.2f}{r['commit_us']:>10.2f}{r['total_us']:>10.2f}"
                + (f"{ratio:>11.2f}x" if way == "columns" else "")
            )


def print_close(args: argparse.Namespace) -> None:
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        root = Path(tmp)
        engine = open_index(f"sqlite:///{root / 'index.sqlite'}")
        index = SessionIndex(engine)
        close_cost(root, index, ticks=args.close_ticks, per_commit=2)  # warm-up: imports, first writes
        for _ in range(args.close_rounds):
            c = close_cost(root, index, ticks=args.close_ticks, per_commit=2)
            print(
                f"close of {args.close_ticks} ticks in {c['batches']:.0f} batches: wall {c['wall_ms']:.1f} ms, "
                f"CPU {c['cpu_ms']:.1f} ms ({c['cpu_ms'] * 1e3 / args.close_ticks:.0f} us/tick); "
                f"loop wake-up lag p50 {c['lag_p50_ms']:.2f} max {c['lag_max_ms']:.2f} ms",
                flush=True,
            )
        engine.dispose()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--frames", type=int, default=200_000, help="frames for the throughput run (200000)")
    parser.add_argument("--compact-frames", type=int, default=1_000_000, help="frames to compact (1000000)")
    parser.add_argument("--rate", type=float, default=100_000, help="paced run: frames/s (100000)")
    parser.add_argument("--seconds", type=float, default=3.0, help="paced run: length in seconds (3)")
    parser.add_argument("--sessions", type=int, default=200, help="many-sessions run: sessions (200)")
    parser.add_argument("--session-rate", type=float, default=20.0, help="many-sessions run: Hz each (20)")
    parser.add_argument("--dir", type=Path, default=None, help="data root (default: a temporary folder)")
    parser.add_argument("--close", action="store_true", help="only the close of a 20 Hz session")
    parser.add_argument("--close-ticks", type=int, default=600, help="close: ticks, two a commit (600)")
    parser.add_argument("--close-rounds", type=int, default=3, help="close: sessions closed (3)")
    parser.add_argument("--record-path", action="store_true", help="only: a record's CPU, columns and lists")
    parser.add_argument(
        "--sessions-per-window", type=int, default=8, help="record path: sessions a window carries (8)"
    )
    parser.add_argument(
        "--rows-per-window",
        type=int,
        nargs="+",
        default=[1, 2, 8, 64],
        help="record path: rows of each session a window carries (1 2 8 64; 20 Hz at the widest window: 2)",
    )
    parser.add_argument("--windows", type=int, default=400, help="record path: windows of each way (400)")
    args = parser.parse_args(argv)
    if args.close:
        print_close(args)
        return 0
    if args.record_path:
        print_record_path(args)
        return 0

    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        root = Path(tmp)
        engine = open_index(f"sqlite:///{root / 'index.sqlite'}")
        index = SessionIndex(engine)
        t = throughput(root, index, args.frames)
        p = paced(root, index, args.rate, args.seconds)
        c = compaction(root, index, args.compact_frames)
        # Side by side, alternating, so that a noisy moment of the shared machine hits both.
        many = {True: [], False: []}
        for shared in (True, False, True, False):
            many[shared].append(
                many_sessions(
                    root, index, sessions=args.sessions, rate=args.session_rate, seconds=2.0, shared=shared
                )
            )
        engine.dispose()

    print(
        f"storage benchmark: pendulum_3 frames (nq = nv = 3), {os.cpu_count()} CPUs, data in {args.dir or 'tmp'}"
    )
    print(f"{'measure':<52}{'value':>20}")
    rows = [
        (f"append, {args.frames} prebuilt frames (frames/s)", f"{t['append_rate']:,.0f}"),
        ("durable: appended and fsynced (frames/s)", f"{t['durable_rate']:,.0f}"),
        ("append() latency p50 / p99 (us)", f"{t['append_p50_us']:.2f} / {t['append_p99_us']:.2f}"),
        ("group commits (fsyncs)", f"{t['commits']:,}"),
        (f"paced at {args.rate:,.0f} frames/s for {args.seconds:g} s: achieved", f"{p['rate']:,.0f}"),
        (
            "  durability lag p50 / p99 / max (ms)",
            f"{p['lag_p50_ms']:.1f} / {p['lag_p99_ms']:.1f} / {p['lag_max_ms']:.1f}",
        ),
        ("  group commits (fsyncs)", f"{p['commits']:,}"),
        ("building a TickRecord (us; the tick no longer does)", f"{t['build_us']:.2f}"),
        ("log bytes per frame", f"{t['log_bytes_per_frame']:.1f}"),
        (f"build + log, {args.compact_frames} frames (frames/s)", f"{c['log_rate']:,.0f}"),
        (f"close: compact {args.compact_frames} frames to Parquet (s)", f"{c['close_s']:.2f}"),
        ("log bytes per frame (1e6 run)", f"{c['log_bytes_per_frame']:.1f}"),
        ("Parquet bytes per frame", f"{c['parquet_bytes_per_frame']:.1f}"),
    ]
    for name, value in rows:
        print(f"{name:<52}{value:>20}")
    grouped = min(m["cpu_us_per_record"] for m in many[True])
    alone = min(m["cpu_us_per_record"] for m in many[False])
    print(
        f"\n{args.sessions} sessions at {args.session_rate:g} Hz, appended as a server's event loop does (best of 2):"
    )
    print(f"{'commit':<40}{'CPU us/record':>15}{'of it commit':>14}{'syncs/s':>10}{'lag p99 ms':>12}")
    for label, runs in (
        ("one committer for all (the server's)", many[True]),
        ("one committer per session (before)", many[False]),
    ):
        best = min(runs, key=lambda m: m["cpu_us_per_record"])
        print(
            f"{label:<40}{best['cpu_us_per_record']:>15.1f}{best['commit_cpu_us_per_record']:>14.1f}"
            f"{best['syncs_per_s']:>10.0f}{best['lag_p99_ms']:>12.1f}"
        )
    print(f"CPU per record, per-session / shared: {alone / grouped:.1f}x")
    target = 100_000
    verdict = "meets" if t["durable_rate"] >= target else "MISSES"
    print(f"target >= {target:,} durable frames/s: {verdict} ({t['durable_rate'] / target:.2f}x)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
