"""The balancer's cost: the same LOCKSTEP sessions straight to a replica and through HAProxy
(deploy/haproxy/haproxy.cfg), side by side in one run, in alternating rounds so that the shared
machine's drift falls on both alike.

A tick here is one LOCKSTEP round trip: the client sends a frame and waits for its result, so the
time a tick takes through the balancer less the time it takes direct is what HAProxy adds to every
answer. It reports, per path:

    ticks           round trips measured (every session, every round)
    p50 / p99 / max round trip, ms
    haproxy cpu     HAProxy's CPU (user + system) / ticks through it, us
    replica cpu     the replica's CPU / ticks, us (the work the balancer does not change)

then the added p50 and p99 (through - direct) and their ratios.

    python -m benchmarks.balancer                      # 4 sessions x 300 ticks x 4 rounds each way
    python -m benchmarks.balancer --sessions 8 --ticks 500 --estimator UKF

It starts one `jitdyn serve` (one process, its own data folder and SQLite index) on 127.0.0.2 and
HAProxy in front of it, both as tests/cluster starts them, and stops both at the end.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from jitdyn.client import Client, FrameData, SessionOptions, TickResult

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests" / "cluster"))

# The cluster's process helpers, shared with its tests.
from _cluster import Balancer, Replica


@dataclass
class Route:
    """One way to the replica, and what was measured along it."""

    name: str
    address: str
    round_trips: list[float] = field(default_factory=list)  # s
    haproxy_cpu: float = 0.0  # s
    replica_cpu: float = 0.0  # s


@dataclass(frozen=True)
class Column:
    header: str
    getter: Callable[[Route], str]


def _percentile(values: Sequence[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q))


COLUMNS = (
    Column("path", lambda p: p.name),
    Column("ticks", lambda p: str(len(p.round_trips))),
    Column("p50 ms", lambda p: f"{_percentile(p.round_trips, 50) * 1e3:.3f}"),
    Column("p99 ms", lambda p: f"{_percentile(p.round_trips, 99) * 1e3:.3f}"),
    Column("max ms", lambda p: f"{max(p.round_trips) * 1e3:.3f}"),
    Column("haproxy cpu/tick us", lambda p: f"{p.haproxy_cpu / len(p.round_trips) * 1e6:.1f}"),
    Column("replica cpu/tick us", lambda p: f"{p.replica_cpu / len(p.round_trips) * 1e6:.1f}"),
)


def _process_cpu(pid: int) -> float:
    stat = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(stat[11]) + int(stat[12])) / os.sysconf("SC_CLK_TCK")


def _session(
    address: str, options: SessionOptions, ticks: int, into: list[float], lock: threading.Lock
) -> None:
    times = []
    with Client(address, timeout=30) as client, client.open_session(options) as session:
        for k in range(ticks):
            frame = FrameData(seq=k, t=k * options.dt, qpos=[0.3 * np.cos(0.2 * k), 0.1], qvel=[0.0, 0.0])
            start = time.perf_counter()
            answer = session.send_frame(frame)
            times.append(time.perf_counter() - start)
            if not isinstance(answer, TickResult):
                raise RuntimeError(f"tick {k} was not answered with a result: {answer}")  # noqa: TRY004
    with lock:
        into.extend(times[1:])  # the first tick includes the filter's start


def _round(
    path: Route, options: SessionOptions, *, sessions: int, ticks: int, replica: Replica, balancer: Balancer
) -> None:
    lock = threading.Lock()
    haproxy_before, replica_before = balancer.cpu_seconds(), _process_cpu(replica.process.pid)
    threads = [
        threading.Thread(target=_session, args=(path.address, options, ticks, path.round_trips, lock))
        for _ in range(sessions)
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    path.haproxy_cpu += balancer.cpu_seconds() - haproxy_before
    path.replica_cpu += _process_cpu(replica.process.pid) - replica_before


def _table(paths: Sequence[Route]) -> str:
    rows = [[c.header for c in COLUMNS], *[[c.getter(p) for c in COLUMNS] for p in paths]]
    widths = [max(len(row[i]) for row in rows) for i in range(len(COLUMNS))]
    lines = [
        "| " + " | ".join(cell.rjust(w) for cell, w in zip(row, widths, strict=True)) + " |" for row in rows
    ]
    lines.insert(1, "|" + "|".join("-" * (w + 2) for w in widths) + "|")
    return "\n".join(lines)


def run(*, sessions: int, ticks: int, rounds: int, estimator: str, dt: float) -> str:
    options = SessionOptions(
        model_name="pendulum_2", dt=dt, clock="LOCKSTEP", estimator={"estimator": estimator}
    )
    with tempfile.TemporaryDirectory(prefix="jitdyn-balancer-") as folder:
        root = Path(folder)
        index = f"sqlite:///{root / 'index.sqlite'}"
        with (
            Replica.start("r1", host="127.0.0.2", data=root / "r1", index_url=index) as replica,
            Balancer.start([replica], workdir=root / "haproxy") as balancer,
        ):
            direct, through = Route("direct", replica.address), Route("haproxy", balancer.address)
            _round(direct, options, sessions=1, ticks=20, replica=replica, balancer=balancer)  # warm up
            direct.round_trips.clear()
            direct.haproxy_cpu = direct.replica_cpu = 0.0
            for _ in range(rounds):
                for path in (direct, through):
                    _round(path, options, sessions=sessions, ticks=ticks, replica=replica, balancer=balancer)
    p50 = [_percentile(p.round_trips, 50) for p in (direct, through)]
    p99 = [_percentile(p.round_trips, 99) for p in (direct, through)]
    mean = [statistics.fmean(p.round_trips) for p in (direct, through)]
    header = (
        f"balancer: {sessions} LOCKSTEP sessions x {ticks} ticks x {rounds} rounds each way, alternating; "
        f"pendulum_2, estimator {estimator}, dt {dt} s; one replica (1 process), HAProxy "
        "deploy/haproxy/haproxy.cfg; loopback"
    )
    added = (
        f"added by HAProxy per tick: p50 {(p50[1] - p50[0]) * 1e3:+.3f} ms, "
        f"p99 {(p99[1] - p99[0]) * 1e3:+.3f} ms, mean {(mean[1] - mean[0]) * 1e3:+.3f} ms"
    )
    ratio = f"ratio through/direct: p50 {p50[1] / p50[0]:.2f}, p99 {p99[1] / p99[0]:.2f}, mean {mean[1] / mean[0]:.2f}"
    return "\n".join([header, _table([direct, through]), added, ratio])


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.balancer", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("--sessions", type=int, default=4, help="concurrent sessions per round (default 4)")
    parser.add_argument("--ticks", type=int, default=300, help="ticks per session (default 300)")
    parser.add_argument("--rounds", type=int, default=4, help="rounds each way, alternating (default 4)")
    parser.add_argument("--estimator", default="STATIC", help="STATIC (default: transport alone) or UKF")
    parser.add_argument("--dt", type=float, default=0.05, help="session tick, s (default 0.05)")
    args = parser.parse_args(argv)
    print(
        run(
            sessions=args.sessions, ticks=args.ticks, rounds=args.rounds, estimator=args.estimator, dt=args.dt
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
