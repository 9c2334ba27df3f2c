"""Where the one PostgreSQL of a cluster saturates: N committers (replica processes) each commit one
transaction per commit window for their sessions' rows (storage/shared.py `SharedTier.commit`, the
statement replicas run), at the sessions' frame rate, and the session count grows until commits no
longer keep up. Prints, per rate and session count: commits/s, rows/s, WAL MB/s, commit latency,
how many windows started late, and PostgreSQL's CPU per commit and per session-window, the costs
that let a reader scale the ceiling to another machine.

    python -m benchmarks.pg_ceiling                       # 2 committers, 20 and 100 Hz
    python -m benchmarks.pg_ceiling --committers 4 --rates 100 --seconds 15

Needs PostgreSQL at 127.0.0.1:5432 (trust auth; a database per run is made in it and dropped). The
committers are processes of this machine, so on a small one they take CPU from PostgreSQL as
replicas on other hosts would not: their own CPU per commit is printed beside PostgreSQL's.

A window is MAX_WINDOW (storage/commit.py: the commit thread widens its window to that once a
commit costs a millisecond), so a committer commits 1/MAX_WINDOW times a second whatever its
session count; each session's part is a real Arrow batch of rate x MAX_WINDOW tick records of a
three-joint model, serialised as the commit thread does. A run is saturated when more than 5 % of
its windows start a whole window late, or its p99 commit takes longer than a window: the rows
then wait longer than durable_seq may trail the answers.
"""

from __future__ import annotations

import argparse
import datetime as dt
import multiprocessing as mp
import os
import statistics
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import psycopg
import sqlalchemy as sa

from benchmarks.storage import Trajectory
from jitdyn.storage.columns import records_to_batch
from jitdyn.storage.commit import MAX_WINDOW
from jitdyn.storage.db import open_index
from jitdyn.storage.schema import session_leases
from jitdyn.storage.shared import Lease, SharedTier, Window

ADMIN = "host=127.0.0.1 user=root dbname=test"
LATE_SHARE = 0.05  # of a run's windows that may start a window late before it counts as saturated


@dataclass(frozen=True)
class Committed:
    """One committer's run: each commit's latency, how late each window started, its CPU."""

    latencies: list[float]
    lateness: list[float]
    cpu: float


@dataclass(frozen=True)
class Point:
    sessions: int
    commits_per_s: float
    rows_per_s: float
    wal_mb_per_s: float
    p50_ms: float
    p99_ms: float
    late_share: float
    pg_cpu_per_commit_us: float
    pg_cpu_per_session_window_us: float
    committer_cpu_per_commit_us: float
    wal_bytes_per_row: float

    @property
    def saturated(self) -> bool:
        return self.late_share > LATE_SHARE or self.p99_ms > 1e3 * MAX_WINDOW


def window_bytes(rows: int) -> bytes:
    """One session's rows of a window, as the commit thread serialises them."""
    trajectory = Trajectory(rows)
    return records_to_batch([trajectory.record(i) for i in range(rows)]).serialize().to_pybytes()


def committer(
    url: str, leases: list[Lease], rows: int, seconds: float, start_at: float, out: mp.Queue
) -> None:  # type: ignore[type-arg]
    """One replica process's commit thread: a transaction for all its sessions every window."""
    engine = open_index(url)
    tier = SharedTier(engine, owner="bench", lease_ttl=30)
    data = window_bytes(rows)
    latencies, lateness = [], []
    time.sleep(max(0.0, start_at - time.time()))
    cpu_started = time.process_time()
    due = time.monotonic()
    end = due + seconds
    k = 0
    while due < end:
        now = time.monotonic()
        if now < due:
            time.sleep(due - now)
        lateness.append(max(0.0, time.monotonic() - due))
        windows = [Window(lease, (k + 1) * rows - 1, data, first=k * rows) for lease in leases]
        started = time.perf_counter()
        tier.commit(windows)
        latencies.append(time.perf_counter() - started)
        k += 1
        due += MAX_WINDOW
    out.put(Committed(latencies, lateness, time.process_time() - cpu_started))
    engine.dispose()


def postgres_cpu() -> float:
    """CPU seconds of every PostgreSQL process of this machine (backends, WAL writer, checkpointer),
    and of the backends that have exited (the postmaster's reaped children: a committer's backend
    ends with it)."""
    tick = os.sysconf("SC_CLK_TCK")
    total = 0
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
        except OSError:
            continue
        if "(postgres)" in text:
            fields = text.rsplit(")", 1)[1].split()
            total += sum(int(fields[i]) for i in (11, 12, 13, 14))
    return total / tick


def wal_lsn(admin: psycopg.Connection) -> str:
    return str(admin.execute("SELECT pg_current_wal_lsn()").fetchone()[0])  # type: ignore[index]


def seed(url: str, sessions: int, committers: int) -> list[list[Lease]]:
    """The sessions' leases, dealt round robin over the committers."""
    engine = open_index(url)
    leases = [Lease(str(uuid.uuid4()), 1) for _ in range(sessions)]
    with engine.begin() as conn:
        conn.execute(
            sa.insert(session_leases),
            [
                {
                    "session_id": lease.session_id,
                    "owner": "bench",
                    "epoch": 1,
                    "expires_at": dt.datetime.now(dt.UTC) + dt.timedelta(hours=1),
                    "header_json": "{}",
                }
                for lease in leases
            ],
        )
    engine.dispose()
    return [leases[c::committers] for c in range(committers)]


def run(*, sessions: int, committers: int, rate: float, seconds: float) -> Point:
    name = f"jitdyn_ceiling_{uuid.uuid4().hex[:8]}"
    url = f"postgresql+psycopg://root@127.0.0.1:5432/{name}"
    rows = max(1, round(rate * MAX_WINDOW))
    with psycopg.connect(ADMIN, autocommit=True) as admin:
        admin.execute(f'CREATE DATABASE "{name}"')
        try:
            shares = seed(url, sessions, committers)
            context = mp.get_context("spawn")
            queue = context.Queue()
            start_at = time.time() + 3.0  # after every committer has imported and connected
            processes = [
                context.Process(target=committer, args=(url, share, rows, seconds, start_at, queue))
                for share in shares
            ]
            for process in processes:
                process.start()
            time.sleep(max(0.0, start_at - time.time()))
            lsn, cpu = wal_lsn(admin), postgres_cpu()
            results = [queue.get(timeout=seconds + 120) for _ in processes]
            wal = int(admin.execute("SELECT pg_wal_lsn_diff(pg_current_wal_lsn(), %s)", [lsn]).fetchone()[0])  # type: ignore[index]
            pg = postgres_cpu() - cpu
            for process in processes:
                process.join(timeout=30)
        finally:
            admin.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
    latencies = sorted(x for r in results for x in r.latencies)
    lateness = [x for r in results for x in r.lateness]
    commits = len(latencies)
    return Point(
        sessions=sessions,
        commits_per_s=commits / seconds,
        rows_per_s=commits * (sessions / committers) * rows / seconds,
        wal_mb_per_s=wal / seconds / 1e6,
        p50_ms=1e3 * statistics.median(latencies),
        p99_ms=1e3 * latencies[min(commits - 1, int(0.99 * commits))],
        late_share=sum(x > MAX_WINDOW for x in lateness) / len(lateness),
        pg_cpu_per_commit_us=1e6 * pg / commits,
        pg_cpu_per_session_window_us=1e6 * pg / (commits * sessions / committers),
        committer_cpu_per_commit_us=1e6 * sum(r.cpu for r in results) / commits,
        wal_bytes_per_row=wal / (commits * (sessions / committers) * rows),
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.pg_ceiling",
        description=__doc__.split("\n\n")[0] if __doc__ else None,
    )
    parser.add_argument("--committers", type=int, default=2, help="replica processes committing (default 2)")
    parser.add_argument("--rates", type=float, nargs="+", default=[20.0, 100.0], help="sessions' Hz")
    parser.add_argument(
        "--sessions",
        type=int,
        nargs="+",
        default=[8, 32, 128, 256, 512, 1024, 2048],
        help="session counts tried in turn, until one saturates",
    )
    parser.add_argument("--seconds", type=float, default=8.0, help="length of each run (default 8)")
    args = parser.parse_args(argv)
    if args.committers < 1 or min(args.sessions) < args.committers:
        parser.error(f"--sessions must be at least --committers ({args.committers}), each at least 1")
    if min(args.rates) <= 0 or args.seconds <= 0:
        parser.error("--rates and --seconds must be positive")
    print(
        f"{args.committers} committers, a window every {1e3 * MAX_WINDOW:.0f} ms each; "
        f"PostgreSQL CPU read from /proc, WAL from pg_current_wal_lsn()"
    )
    header = (
        "  Hz  sessions  commits/s   rows/s  WAL MB/s  p50 ms  p99 ms  late  "
        "PG us/commit  PG us/session-window  committer us/commit  WAL B/row"
    )
    for rate in args.rates:
        print(f"\n{rate:.0f} Hz\n{header}")
        ceiling = None
        for sessions in sorted(args.sessions):
            point = run(sessions=sessions, committers=args.committers, rate=rate, seconds=args.seconds)
            print(
                f"{rate:4.0f}  {sessions:8d}  {point.commits_per_s:9.1f}  {point.rows_per_s:7.0f}  "
                f"{point.wal_mb_per_s:8.2f}  {point.p50_ms:6.1f}  {point.p99_ms:6.1f}  "
                f"{100 * point.late_share:3.0f}%  {point.pg_cpu_per_commit_us:12.0f}  "
                f"{point.pg_cpu_per_session_window_us:20.1f}  {point.committer_cpu_per_commit_us:19.0f}  "
                f"{point.wal_bytes_per_row:9.0f}" + ("  saturated" if point.saturated else ""),
                flush=True,
            )
            if point.saturated:
                ceiling = sessions
                break
        if ceiling is None:
            print(f"{rate:.0f} Hz: not saturated up to {max(args.sessions)} sessions")
        else:
            print(f"{rate:.0f} Hz: saturated at {ceiling} sessions ({args.committers} committers)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
